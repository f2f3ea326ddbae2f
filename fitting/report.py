"""Pictures and tables of fit results: target | fit | error heat map, and the cross-model matrix."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from fitting.solve import FitResult
from jaxrt.fsutil import atomic_path


def _display(img: np.ndarray, white: float) -> np.ndarray:
    import colour

    x = np.clip(np.asarray(img, np.float64) / white, 0.0, 1.0)
    return np.clip(colour.cctf_encoding(x, function="sRGB"), 0.0, 1.0)


def crop_box(mask: np.ndarray, margin: float = 0.1) -> tuple[slice, slice]:
    """(rows, columns) slices around the True pixels of an (H, W) mask, widened by `margin` of their
    extent (at least 2 pixels) and kept inside the image; the whole image when the mask is empty."""
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return slice(None), slice(None)
    out = []
    for idx, size in ((rows, mask.shape[0]), (cols, mask.shape[1])):
        lo, hi = int(idx.min()), int(idx.max()) + 1
        pad = max(2, int(round(margin * (hi - lo))))
        out.append(slice(max(0, lo - pad), min(size, hi + pad)))
    return out[0], out[1]


def comparison_figure(targets: np.ndarray, fits: np.ndarray, mask: np.ndarray, titles: Sequence[str] | None = None):
    """Rows of target | fit | error heat map, one row per (K, H, W, 3) image pair, as a Figure.

    Each row is cropped to the compared pixels (`crop_box` of the mask). Display: both images are
    scaled by the target's 99th-percentile value inside the mask ("white") and sRGB-encoded; the
    heat map shows the per-pixel RGB error norm |fit − target| in the images' radiance units,
    W/(m²·sr), with a colour bar; pixels that are not compared are grey.
    """
    import matplotlib as mpl
    from matplotlib.figure import Figure  # Agg, without touching pyplot's backend

    targets, fits, mask = np.asarray(targets), np.asarray(fits), np.asarray(mask) > 0
    k = targets.shape[0]
    fig = Figure(figsize=(10.4, 3.2 * k + 0.4))
    axes = fig.subplots(k, 3, squeeze=False)
    cmap = mpl.colormaps["magma"].with_extremes(bad="0.75")
    for i in range(k):
        rs, cs = crop_box(mask[i])
        t, f, m = targets[i][rs, cs], fits[i][rs, cs], mask[i][rs, cs]
        vals = t[m]
        white = float(np.percentile(vals, 99)) if vals.size else 1.0
        white = white if white > 0 else 1.0
        err = np.where(m, np.linalg.norm(f - t, axis=-1), np.nan)
        label = titles[i] if titles else f"view {i}"
        axes[i, 0].imshow(_display(t, white))
        axes[i, 0].set_title(f"{label}: target (white = {white:.3g})", fontsize=9)
        axes[i, 1].imshow(_display(f, white))
        axes[i, 1].set_title("fit", fontsize=9)
        top = max(float(np.nanmax(err)) if np.any(m) else 0.0, 1e-12)
        im = axes[i, 2].imshow(err, cmap=cmap, vmin=0.0, vmax=top)
        axes[i, 2].set_title(f"|fit − target| (max {top / white:.2g} of white)", fontsize=9)
        fig.colorbar(im, ax=axes[i, 2], fraction=0.046, label="W/(m²·sr)")
        for a in axes[i]:
            a.set_axis_off()
    fig.tight_layout()
    return fig


def comparison_png(
    path: str | os.PathLike,
    targets: np.ndarray,
    fits: np.ndarray,
    mask: np.ndarray,
    titles: Sequence[str] | None = None,
) -> None:
    """Write `comparison_figure` as a PNG (atomically)."""
    fig = comparison_figure(targets, fits, mask, titles)
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
        err = "(fixed)" if fixed else "(meaningless)" if name in r.meaningless else _fmt(r.stderr.get(name, float("nan")))
        row = f"  {name:<10} {_fmt(v):>26} {err:>26}"
        if truth is not None:
            row += f" {_fmt(truth.get(name, float('nan'))):>26}"
        lines.append(row)
    lines.append(f"  RMSE {r.rmse:.3g} ({r.relative_rmse:.3g} of the target's RMS)   ΔE2000 mean {r.delta_e_mean:.3g} max {r.delta_e_max:.3g}   "
                 f"cond(JᵀJ) {r.condition_number:.3g}")
    if r.correlated:
        pairs = ", ".join(f"{a}~{b} ({c:+.3f})" for a, b, c in r.correlated)
        lines.append(f"  note: correlated estimates {pairs}: these views determine a combination of them "
                     "better than each one; the ± errors above are per parameter and include the trade-off")
    elif r.ill_conditioned:
        lines.append(f"  note: cond(JᵀJ) = {r.condition_number:.3g}: the least determined combination of the "
                     f"(scaled) parameters is known {math.sqrt(r.condition_number):.3g}x less precisely than the "
                     "best; the ± errors above say how well each parameter is determined")
    lines += [f"  warning: {w}" for w in r.warnings]
    return "\n".join(lines)


def _fmt(v) -> str:
    a = np.asarray(v, np.float64)
    if a.ndim == 0:
        return f"{float(a):.5g}"
    return "[" + ", ".join(f"{x:.4g}" for x in a.ravel()) + "]"


def text_colour(rgba) -> str:
    """"black" or "white", whichever reads better on a background of colour `rgba` (sRGB in [0, 1]):
    black where the background's relative luminance (WCAG 2) is above 0.179, where both contrast
    ratios are equal."""
    lin = [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in rgba[:3]]
    return "black" if 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2] > 0.179 else "white"


def matrix_figure(names: Sequence[str], matrix: np.ndarray, title: str):
    """The heat map of a (targets × fitted models) matrix of relative RMSE values, as a Figure; each
    cell's label is black or white by the cell's colour (`text_colour`)."""
    from matplotlib.figure import Figure

    m = np.asarray(matrix, np.float64)
    fig = Figure(figsize=(1.2 * len(names) + 2.5, 1.0 * len(names) + 1.8))
    ax = fig.subplots()
    im = ax.imshow(np.log10(np.maximum(m, 1e-6)), cmap="viridis_r")
    ax.set_xticks(range(len(names)), names, rotation=35, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("fitted model")
    ax.set_ylabel("target rendered with")
    cells = im.cmap(im.norm(np.log10(np.maximum(m, 1e-6))))
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(j, i, f"{m[i, j]:.2g}", ha="center", va="center", fontsize=8, color=text_colour(cells[i, j]))
    fig.colorbar(im, ax=ax, label="log10 relative RMSE")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def matrix_png(path: str | os.PathLike, names: Sequence[str], matrix: np.ndarray, title: str) -> None:
    """Write `matrix_figure` as a PNG (atomically)."""
    fig = matrix_figure(names, matrix, title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
