"""Pictures and tables of fit results: target | fit | error heat map, and the cross-model matrix."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from fitting.solve import FitResult
from jaxrt.fsutil import atomic_path


def _display(img: np.ndarray, white: float) -> np.ndarray:
    import colour

    x = np.clip(np.asarray(img, np.float64) / white, 0.0, 1.0)
    return np.clip(colour.cctf_encoding(x, function="sRGB"), 0.0, 1.0)


def comparison_png(
    path: str | os.PathLike,
    targets: np.ndarray,
    fits: np.ndarray,
    mask: np.ndarray,
    titles: Sequence[str] | None = None,
) -> None:
    """Write rows of target | fit | |fit − target| heat map, one row per (K, H, W, 3) image pair.

    Display: both images are scaled by the target's 99th-percentile value inside the mask and
    sRGB-encoded; the heat map shows the per-pixel RGB error norm relative to that same white.
    """
    from matplotlib.figure import Figure  # Agg, without touching pyplot's backend

    targets, fits, mask = np.asarray(targets), np.asarray(fits), np.asarray(mask) > 0
    k = targets.shape[0]
    fig = Figure(figsize=(9.6, 3.2 * k + 0.4))
    axes = fig.subplots(k, 3, squeeze=False)
    for i in range(k):
        vals = targets[i][mask[i]]
        white = float(np.percentile(vals, 99)) if vals.size else 1.0
        white = white if white > 0 else 1.0
        err = np.linalg.norm(fits[i] - targets[i], axis=-1) / white
        err = np.where(mask[i], err, np.nan)
        label = titles[i] if titles else f"view {i}"
        axes[i, 0].imshow(_display(targets[i], white))
        axes[i, 0].set_title(f"{label}: target", fontsize=9)
        axes[i, 1].imshow(_display(fits[i], white))
        axes[i, 1].set_title("fit", fontsize=9)
        im = axes[i, 2].imshow(err, cmap="magma", vmin=0.0, vmax=max(float(np.nanmax(err)) if np.any(mask[i]) else 0.0, 1e-6))
        axes[i, 2].set_title("|fit − target| / white", fontsize=9)
        fig.colorbar(im, ax=axes[i, 2], fraction=0.046)
        for a in axes[i]:
            a.set_axis_off()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)


def format_result(r: FitResult, truth: dict | None = None) -> str:
    """A table of recovered parameters ± standard errors (and the truth, when known) plus metrics."""
    lines = [f"model {r.model}: {'converged' if r.converged else 'NOT converged'} after {r.iterations} iterations "
             f"(best of {r.starts} starts, {r.starts_at_best} reached it; {r.wall_time_s:.2f} s, "
             f"{r.us_per_iteration:.0f} µs/iteration)"]
    head = f"  {'parameter':<10} {'fitted':>26} {'± std. error':>26}"
    if truth is not None:
        head += f" {'truth':>26}"
    lines.append(head)
    for name, v in r.params.items():
        fixed = name in r.fixed
        row = f"  {name:<10} {_fmt(v):>26} {('(fixed)' if fixed else _fmt(r.stderr.get(name, float('nan')))):>26}"
        if truth is not None:
            row += f" {_fmt(truth.get(name, float('nan'))):>26}"
        lines.append(row)
    lines.append(f"  RMSE {r.rmse:.3g}   ΔE2000 mean {r.delta_e_mean:.3g} max {r.delta_e_max:.3g}   "
                 f"cond(JᵀJ) {r.condition_number:.3g}")
    if r.ill_conditioned:
        pairs = ", ".join(f"{a}~{b} ({c:+.3f})" for a, b, c in r.correlated) or "large condition number"
        lines.append(f"  warning: ill-conditioned — parameters trade off: {pairs}")
    return "\n".join(lines)


def _fmt(v) -> str:
    a = np.asarray(v, np.float64)
    if a.ndim == 0:
        return f"{float(a):.5g}"
    return "[" + ", ".join(f"{x:.4g}" for x in a.ravel()) + "]"


def matrix_png(path: str | os.PathLike, names: Sequence[str], matrix: np.ndarray, title: str) -> None:
    """Heat map of a (targets × fitted models) matrix of relative RMSE values."""
    from matplotlib.figure import Figure

    m = np.asarray(matrix, np.float64)
    fig = Figure(figsize=(1.2 * len(names) + 2.5, 1.0 * len(names) + 1.8))
    ax = fig.subplots()
    im = ax.imshow(np.log10(np.maximum(m, 1e-6)), cmap="viridis_r")
    ax.set_xticks(range(len(names)), names, rotation=35, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("fitted model")
    ax.set_ylabel("target rendered with")
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(j, i, f"{m[i, j]:.2g}", ha="center", va="center", fontsize=8,
                    color="white" if np.log10(max(m[i, j], 1e-6)) < np.log10(max(np.nanmax(m), 1e-6)) - 1.5 else "black")
    fig.colorbar(im, ax=ax, label="log10 relative RMSE")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
