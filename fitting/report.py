"""Pictures and tables of fit results: target | fit | error heat map, the cross-model matrix, and the
BRDF-space pictures (measured vs fitted lobe slices and spheres, the study's error curves and sphere grid)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from fitting.solve import FitResult
from jaxrt.fsutil import atomic_path


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve (IEC 61966-2-1:1999, the inverse EOTF) of linear values, float64: the
    arithmetic of colour-science's `eotf_inverse_sRGB`, so the values are its bit for bit
    (`tests/fitting/test_fit_core.py`), without its import (scipy; 0.6 CPU s beside matplotlib)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * (np.sign(x) * np.abs(x) ** np.asarray(1 / 2.4)) - 0.055)


def _display(img: np.ndarray, white: float) -> np.ndarray:
    x = np.clip(np.asarray(img, np.float64) / white, 0.0, 1.0)
    return np.clip(srgb_encode(x), 0.0, 1.0)


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
    if r.at_bound:
        lines.append("  at a bound of the declared range: " + ", ".join(f"{k} ({v})" for k, v in r.at_bound.items()))
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


# --- BRDF-space fits and the study (fitting.brdf_space, fitting.study) ------------------------------------

# Lobe-slice light angles of the BRDF-space pictures [degrees]
SLICE_THETA_I = (0.0, 30.0, 60.0, 75.0)
SPHERE_CAPTION = ("spheres shaded in closed form per pixel (orthographic view, one distant light, "
                  "L = f cos θi; no ray tracing, shadows or interreflection)")


def _outline(ax, size: int) -> None:
    """The sphere's silhouette as a thin grey circle (its unlit part is as dark as the background)."""
    from matplotlib.patches import Circle

    ax.add_patch(Circle(((size - 1) / 2, (size - 1) / 2), size / 2, fill=False, lw=0.6, ec="0.45"))


def _sphere_white(img: np.ndarray) -> float:
    """Display white of a sphere row: the 99.5th percentile of the measured sphere's channel values."""
    v = np.asarray(img)[np.asarray(img).max(-1) > 0]
    w = float(np.percentile(v, 99.5)) if v.size else 1.0
    return w if w > 0 else 1.0


def brdf_fit_png(path: str | os.PathLike, fit, model, params, measured_model, measured_params,
                 sphere_size: int = 160) -> None:
    """Measured vs fitted lobe slices (incidence plane, θi in SLICE_THETA_I, log scale, channel mean)
    and closed-form spheres of each side by side, for one `fitting.brdf_space.BrdfFit`."""
    import math

    from matplotlib.figure import Figure

    from brdfs.analysis import lobe_slice
    from fitting.brdf_space import CUTOFF_DEG, sphere_image

    fig = Figure(figsize=(12.5, 4.4))
    gs = fig.add_gridspec(1, 3, width_ratios=[1.5, 1, 1])
    ax = fig.add_subplot(gs[0])
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple"]
    lo = np.inf
    for k, th in enumerate(SLICE_THETA_I):
        t, fm = lobe_slice(measured_model, measured_params, math.radians(th), n=721)
        _, ff = lobe_slice(model, params, math.radians(th), n=721)
        deg = np.degrees(t)
        ym, yf = np.asarray(fm).mean(-1), np.asarray(ff).mean(-1)
        pos = ym[ym > 0]
        lo = min(lo, float(pos.min()) if pos.size else lo)
        ax.plot(deg, np.where(ym > 0, ym, np.nan), color=colors[k], lw=1.6, label=f"θi = {th:g}°: measured")
        ax.plot(deg, np.where(yf > 0, yf, np.nan), color=colors[k], lw=1.2, ls="--", label="fit")
    ax.set_yscale("log")
    if np.isfinite(lo):
        ax.set_ylim(bottom=0.5 * lo)
    for x in (-CUTOFF_DEG, CUTOFF_DEG):
        ax.axvline(x, color="0.6", lw=0.8, ls=":")
    ax.set_xlim(-90, 90)
    ax.set_xlabel("θo in the plane of incidence [°] (mirror direction at +θi; dotted: the fit's 80° cutoff)")
    ax.set_ylabel("f, mean of R, G, B [1/sr]")
    ax.legend(fontsize=7, ncol=2, loc="upper left")
    ax.set_title(f"{fit.material}: {fit.model} fit ({fit.metric} metric), E = {fit.error:.4g} {fit.unit}",
                 fontsize=9)
    meas = sphere_image(measured_model, measured_params, sphere_size)
    fitted = sphere_image(model, params, sphere_size)
    white = _sphere_white(meas)
    for j, (img, label) in enumerate(((meas, "measured"), (fitted, f"fit: {fit.model}"))):
        a = fig.add_subplot(gs[1 + j])
        a.imshow(_display(img, white))
        _outline(a, sphere_size)
        a.set_title(label, fontsize=9)
        a.set_axis_off()
    fig.text(0.99, 0.01, SPHERE_CAPTION, ha="right", va="bottom", fontsize=7, color="0.3")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)


def _material_label(name: str) -> str:
    """A study material's short label: the name without its collection, or a file's name."""
    from pathlib import Path

    return Path(name).name if Path(name).suffix else name.split("/", 1)[-1]


def study_errors_png(path: str | os.PathLike, materials: Sequence[str], models: Sequence[str],
                     table: np.ndarray, metric: str, unit: str, space: str = "brdf") -> None:
    """Ngan et al. 2005's figure: materials sorted by error (the lowest error any model reaches),
    one curve per model, log scale; every material labelled."""
    from matplotlib.figure import Figure

    e = np.asarray(table, np.float64)
    order = np.argsort(e.min(axis=1), kind="stable")
    n = len(materials)
    fig = Figure(figsize=(max(8.0, 0.16 * n + 3.0), 6.0))
    ax = fig.subplots()
    markers = "os^vD<>ph*"
    for j, m in enumerate(models):
        ax.plot(np.arange(n), e[order, j], marker=markers[j % len(markers)], ms=3.5, lw=1.0, label=m)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(n), [_material_label(materials[i]) for i in order], rotation=90,
                  fontsize=7 if n > 40 else 9)
    ax.set_xlim(-0.5, n - 0.5)
    ax.set_ylabel(f"fitting error E ({metric} metric) [{unit}]")
    ax.set_xlabel("material, sorted by the lowest error of any model")
    ax.grid(True, which="both", axis="y", lw=0.4, alpha=0.5)
    ax.legend(fontsize=8)
    ax.set_title(f"{'Image' if space == 'image' else 'BRDF'}-space fits of {n} measured materials "
                 "(after Ngan, Durand & Matusik 2005)",
                 fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)


def study_spheres_png(path: str | os.PathLike, materials: Sequence[str], models: Sequence[str], fits: dict,
                      size: int = 112) -> None:
    """Rows of spheres: the measured material | each model's fit (`fits[(material, model)]`), one
    display white per row (the measured sphere's)."""
    from matplotlib.figure import Figure

    import brdfs
    from brdfs import measured
    from fitting.brdf_space import as_params, sphere_image

    rows, cols = len(materials), 1 + len(models)
    fig = Figure(figsize=(1.6 * cols + 0.4, 1.75 * rows + 0.6))
    axes = fig.subplots(rows, cols, squeeze=False)
    for i, a in enumerate(materials):
        mm, mp = measured.load(a)
        meas = sphere_image(mm, mp, size)
        white = _sphere_white(meas)
        axes[i, 0].imshow(_display(meas, white))
        _outline(axes[i, 0], size)
        axes[i, 0].set_title(f"{a.split('/', 1)[-1]}\nmeasured", fontsize=7)
        for j, m in enumerate(models):
            f = fits[(a, m)]
            img = sphere_image(brdfs.get(m), as_params(f), size)
            axes[i, 1 + j].imshow(_display(img, white))
            _outline(axes[i, 1 + j], size)
            axes[i, 1 + j].set_title(f"{m}\nE = {f.error:.3g} {f.unit}", fontsize=7)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.text(0.5, 0.005, SPHERE_CAPTION, ha="center", va="bottom", fontsize=6.5, color="0.3")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)


def study_renders_png(path: str | os.PathLike, materials: Sequence[str], models: Sequence[str], images: dict,
                      fits: dict) -> None:
    """Rows of renders (the image-space study's first view): the render of the measured material |
    each model's fit (`images[(material, "target")]`, `images[(material, model)]`), one display white
    per row (the target's, over the object's pixels `images[(material, "mask")]`)."""
    from matplotlib.figure import Figure

    rows, cols = len(materials), 1 + len(models)
    fig = Figure(figsize=(1.6 * cols + 0.4, 1.75 * rows + 0.4))
    axes = fig.subplots(rows, cols, squeeze=False)
    for i, a in enumerate(materials):
        target = np.asarray(images[(a, "target")])
        mask = np.asarray(images.get((a, "mask"), np.ones(target.shape[:2]))) > 0
        white = float(np.percentile(target[mask] if mask.any() else target, 99.5)) or 1.0
        axes[i, 0].imshow(_display(target, white))
        axes[i, 0].set_title(f"{_material_label(a)}\nmeasured", fontsize=7)
        for j, m in enumerate(models):
            f = fits[(a, m)]
            axes[i, 1 + j].imshow(_display(np.asarray(images[(a, m)]), white))
            axes[i, 1 + j].set_title(f"{m}\nE = {f.error:.3g}", fontsize=7)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)


def format_brdf_fit(fit) -> str:
    """A table of one BRDF-space fit: parameters ± standard errors, bounds, errors in the study's units."""
    lines = [f"{fit.material}: {fit.model}, {fit.metric} metric — "
             f"{'converged' if fit.converged else 'NOT converged'} after {fit.iterations} iterations "
             f"(best of {fit.starts} starts, {fit.starts_at_best} reached it; {fit.samples} direction pairs)",
             f"  {'parameter':<10} {'fitted':>26} {'± std. error':>26}"]
    for name, v in fit.params.items():
        if name in fit.fixed:
            se = "(fixed)"
        elif name in fit.tied:
            se = f"(= {fit.tied[name]})"
        else:
            se = _fmt(fit.stderr.get(name, float("nan")))
        lines.append(f"  {name:<10} {_fmt(v):>26} {se:>26}")
    errs = ", ".join(f"{k} {v:.4g}" for k, v in fit.errors.items())
    lines.append(f"  E = {fit.error:.4g} {fit.unit} ({fit.eval_samples} pairs; on the fit's own {fit.samples}: "
                 f"{fit.fit_error:.4g}); every metric: {errs}")
    if fit.at_bound:
        lines.append("  at a bound of the declared range: "
                     + ", ".join(f"{k} ({v})" for k, v in fit.at_bound.items()))
    if fit.ill_conditioned:
        pairs = ", ".join(f"{a}~{b} ({c:+.3f})" for a, b, c in fit.correlated) or "large condition number"
        lines.append(f"  warning: ill-conditioned — parameters trade off: {pairs}")
    return "\n".join(lines)
