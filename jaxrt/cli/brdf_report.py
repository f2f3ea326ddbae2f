"""`jaxrt brdf-report`: every model's directional albedo table and a lobe-plot PNG grid.

    jaxrt brdf-report [-o brdf_report.png] [--angles 0 30 45 60 75 85] [--samples 256] [--measured NAMES]

Rows: the registered models with their default parameters, then the measured materials given with
--measured (names such as merl/alum-bronze, or .h5 / .binary files); columns: view angles theta_o [deg].
Values are the channel-mean directional albedo ∫ f cos(theta_i) dω_i (brdfs.albedo); for glass,
a delta BSDF, the Fresnel reflectance R (the transmitted fraction is 1 - R).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from jaxrt.errors import InputError


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", default="brdf_report.png", help="lobe plot PNG path (default: %(default)s)")
    parser.add_argument(
        "--angles", type=float, nargs="+", default=[0, 30, 45, 60, 75, 85], metavar="DEG",
        help="view angles theta_o for the albedo table, degrees in [0, 90) (default: %(default)s)",
    )
    parser.add_argument(
        "--samples", type=int, default=256, metavar="N",
        help="albedo estimator grid size: N x N samples per lobe (default: %(default)s)",
    )
    parser.add_argument(
        "--lobe-angles", type=float, nargs="+", default=[0, 30, 60], metavar="DEG",
        help="light angles theta_i of the plotted lobe slices, degrees (default: %(default)s)",
    )
    parser.add_argument(
        "--measured", metavar="NAMES",
        help="comma-separated measured materials to add to the table and the lobe grid: names "
             "(merl/alum-bronze, found through JAXRT_DATA) or files (NAME.h5 neural BRDF, NAME.binary MERL table)",
    )


def entries(measured: tuple[str, ...] = ()) -> list[tuple[str, object, dict]]:
    """(label, model, parameters) of every registered model at its defaults, then of each measured
    material (`brdfs.measured.load`: a name or a file)."""
    import brdfs
    from brdfs import measured as _measured

    out = [(name, brdfs.get(name), brdfs.get(name).params()) for name in brdfs.names()]
    for ref in measured:
        model, p = _measured.load(ref)
        out.append((ref, model, p))
    return out


def albedo_table(angles_deg, samples: int = 256, measured: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """{label: (len(angles),) channel-mean albedo} for every model at its defaults and each measured
    material (`entries`)."""
    import jax.numpy as jnp

    import brdfs

    th = np.radians(np.asarray(angles_deg, dtype=np.float64))
    wo = jnp.asarray(np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1), jnp.float32)
    return {label: np.asarray(brdfs.albedo(m, p, wo, n=samples)).mean(-1) for label, m, p in entries(measured)}


def lobe_figure(lobe_angles_deg, measured: tuple[str, ...] = ()):
    """A grid of polar lobe slices (plane of incidence), one panel per model, four per row, as a Figure.

    Each opaque panel is scaled to its own maximum of f·cos θo (the panel's title gives that value,
    in 1/sr); glass draws R and 1 − R as lengths. One legend for all panels, under the grid, and two
    radial ticks per panel, so nothing covers the curves or overlaps."""
    from matplotlib.figure import Figure

    import brdfs
    from brdfs.analysis import draw_lobe

    th = [math.radians(a) for a in lobe_angles_deg]
    items = entries(measured)
    rows = -(-len(items) // 4)
    fig = Figure(figsize=(16, 4.1 * rows))
    handles = None
    for k, (name, m, p) in enumerate(items):
        ax = fig.add_subplot(rows, 4, k + 1, projection="polar")
        draw_lobe(ax, m, p, th)
        ax.set_rticks([0.5, 1.0])
        ax.set_rlabel_position(-60.0 if not m.delta else 200.0)
        ax.tick_params(labelsize=7)
        if m.delta:
            scale = "lengths R, 1 − R"
        else:
            peak = max(float(np.max(np.asarray(f).mean(-1) * np.cos(t))) for t, f in
                       (brdfs.lobe_slice(m, p, a) for a in th))
            scale = f"1 = {peak:.3g} /sr"
            handles = handles or ax.get_legend_handles_labels()
        ax.set_title(f"{name}  ({scale})", pad=10, fontsize=10)
    if handles:
        fig.legend(*handles, loc="lower center", ncol=len(handles[0]), fontsize=9, title="light angle θi")
    fig.suptitle("f·cos θo in the plane of incidence at default parameters (and of the measured materials); "
                 "each panel scaled to its own maximum (in its title); glass: R solid, 1 − R dashed")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return fig


def write_lobe_grid(path, lobe_angles_deg, measured: tuple[str, ...] = ()) -> None:
    """Write `lobe_figure` to `path` as a PNG (atomically)."""
    from jaxrt.fsutil import atomic_path

    fig = lobe_figure(lobe_angles_deg, measured)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)


def run(args: argparse.Namespace) -> int:
    if any(not (0.0 <= a < 90.0) for a in args.angles):
        raise InputError(f"--angles: view angles must be in [0, 90) degrees, got {args.angles}")
    if any(not (0.0 <= a < 90.0) for a in args.lobe_angles):
        raise InputError(f"--lobe-angles: light angles must be in [0, 90) degrees, got {args.lobe_angles}")
    if not (4 <= args.samples <= 2048):
        raise InputError(f"--samples: must be in [4, 2048], got {args.samples}")
    measured = tuple(n.strip() for n in (args.measured or "").split(",") if n.strip())
    from brdfs import measured as _measured
    from jaxrt.fsutil import Outputs

    for ref in measured:
        try:
            _measured.read(ref)  # numpy only: a bad name or file fails before any JAX work
        except InputError as e:
            raise InputError(f"--measured: {e}") from None
    outs = Outputs()
    out = outs.add(args.output, ".png", "-o")
    t0 = time.perf_counter()
    table = albedo_table(args.angles, args.samples, measured)
    width = max([18] + [len(k) + 2 for k in table])
    head = f"{'model':<{width}}" + "".join(f"{f'{a:g}°':>9}" for a in args.angles)
    print("Directional albedo ∫ f cosθi dωi at view angle θo (default parameters; glass: Fresnel R)")
    print(head)
    for name, row in table.items():
        print(f"{name:<{width}}" + "".join(f"{v:9.4f}" for v in row))
    with outs.writing() as tmp:
        write_lobe_grid(tmp[out], args.lobe_angles, measured)
    print(f"wrote {args.output}  ({time.perf_counter() - t0:.1f} s)")
    return 0
