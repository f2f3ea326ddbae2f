"""Live-path compaction in the path tracer (`jaxrt.integrators.path._compacted`): one pass timed with
the bounces compacted into each of several chunk counts, and uncompacted, in one process.

    python benchmarks/path_chunks.py                      # 512², 16 spp, depth 4, both scenes
    python benchmarks/path_chunks.py --chunks 2 4 8 --size 256 --scenes dragon
    JAXRT_CACHE=off python benchmarks/path_chunks.py --no-off --scenes cornell --knobs LAST_RAYS_EMITTERS=0

Scenes are `benchmarks/path.py`'s (Cornell box with its area light; the dragon in an environment
map). For each variant: the first call's wall time (tracing + compilation, or the persistent cache's
load), then the median wall time of --repeats passes (different random streams, block_until_ready),
the image mean, and whether its pixels equal the uncompacted pass's (the largest difference where
they do not: compaction changes which paths run beside which, never a path's own arithmetic, so at
most a rounding difference from a different fusion). "off" runs every bounce on every path, as the
tracer did before compaction. --first also compares the GPU's first bounce on the whole batch
against compacted as the others (`path.GPU_WHOLE_FIRST_BOUNCE`). On the CPU the variants set the
chunks per batch (`path.CPU_BATCH_CHUNKS`); on a GPU the chunks per pass (`path.GPU_CHUNKS`).
"""

from __future__ import annotations

import argparse
import ast
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import path as bench  # noqa: E402  (benchmarks/path.py)
from jaxrt.accel import traverse_pallas as TP  # noqa: E402
from jaxrt.integrators import path as P  # noqa: E402


def _uncompacted(fn, carry, chunk, dense_at=None):
    return fn(carry)


# XLA:GPU command buffers (CUDA graphs) that also record conditionals and while loops: their
# predicates are then evaluated on the device (graph conditional nodes) instead of copied to the host
GRAPH_OPTIONS = {"xla_gpu_enable_command_buffer": "FUSION,CUBLAS,CUBLASLT,CUDNN,CUSTOM_CALL,CONDITIONAL,WHILE",
                 "xla_gpu_graph_min_graph_size": 1}


# modules whose constants --knobs may set, as "traverse_pallas.NAME=V" (a bare NAME is `path`'s)
KNOB_MODULES = {"path": P, "traverse_pallas": TP}


def _knobs(text: str) -> dict:
    """"NAME=value,NAME=value" (module constants of `jaxrt.integrators.path`, or of another module of
    `KNOB_MODULES` as "module.NAME"; values are Python literals, or strings); GRAPHS=1 compiles with
    `GRAPH_OPTIONS`; xla_*=value is an XLA compiler option of the pass's program. Returns {name: value}
    with names as given."""
    out = {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if name == "GRAPHS":
            out[name] = value == "1"
            continue
        if name.startswith("xla_"):  # an XLA compiler option of the pass's program, as a string
            out[name] = value
            continue
        if not hasattr(*_knob_target(name)):
            raise SystemExit(f"--knobs: no constant {name} (modules: {', '.join(KNOB_MODULES)})")
        try:
            out[name] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            out[name] = value
    return out


def _knob_target(name: str):
    """(module, attribute) of a knob's "NAME" or "module.NAME" (`KNOB_MODULES`)."""
    module, _, attr = name.rpartition(".")
    if module not in ("", *KNOB_MODULES):
        raise SystemExit(f"--knobs: no module {module!r} (modules: {', '.join(KNOB_MODULES)})")
    return KNOB_MODULES[module or "path"], attr


_pack = jax.jit(TP.pack_tables, static_argnames="layout")


def _retabled(sc):
    """The scene with every BVH's kernel tables packed again for `traverse_pallas.TREE_LAYOUT`."""
    import equinox as eqx

    from jaxrt.accel import bvh

    def pack(x):
        if not isinstance(x, bvh.BVH) or x.rows is None:
            return x
        tables = _pack(x.node_box, x.node_leaf, x.links, x.triangles, layout=TP.TREE_LAYOUT)
        return eqx.tree_at(lambda t: (t.rows, t.skips), x, tables)

    return jax.tree.map(pack, sc, is_leaf=lambda x: isinstance(x, bvh.BVH))


def run_variant(sc, chunks: int | None, repeats: int, whole_first: bool = False,
                knobs: dict | None = None) -> tuple[dict, np.ndarray]:
    attr = "CPU_BATCH_CHUNKS" if jax.default_backend() == "cpu" else "GPU_CHUNKS"
    knobs = dict(knobs or {})
    options = dict(GRAPH_OPTIONS) if knobs.pop("GRAPHS", False) else {}
    options.update({k: knobs.pop(k) for k in [k for k in knobs if k.startswith("xla_")]})
    options = options or None
    saved = getattr(P, attr), P._compacted, P.GPU_WHOLE_FIRST_BOUNCE
    saved_knobs = {k: getattr(*_knob_target(k)) for k in knobs}
    try:
        P.GPU_WHOLE_FIRST_BOUNCE = whole_first
        for k, v in knobs.items():
            setattr(*_knob_target(k), v)
        if "traverse_pallas.TREE_LAYOUT" in knobs:
            sc = _retabled(sc)  # the trees' GPU node tables in the knob's layout (the scene's are the default's)
        if chunks is None:
            P._compacted = _uncompacted
        elif chunks:
            setattr(P, attr, chunks)
        # a new function object: jit's trace cache is keyed by it, and the module's knobs are read
        # while tracing
        f = jax.jit(lambda s, i: P.samples(s, i, jitter=True), compiler_options=options)
        t0 = time.perf_counter()
        first = np.asarray(f(sc, 0))
        first_s = time.perf_counter() - t0
        times = []
        for i in range(1, repeats + 1):
            t = time.perf_counter()
            f(sc, i).block_until_ready()
            times.append(time.perf_counter() - t)
    finally:
        setattr(P, attr, saved[0])
        P._compacted, P.GPU_WHOLE_FIRST_BOUNCE = saved[1:]
        for k, v in saved_knobs.items():
            setattr(*_knob_target(k), v)
    assert np.all(np.isfinite(first))
    return dict(first_s=first_s, pass_s=statistics.median(times), mean=float(first.mean())), first


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--chunks", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--first", nargs="+", default=["compacted"], choices=["whole", "compacted"],
                    help="on a GPU, the first bounce on the whole batch (`path.GPU_WHOLE_FIRST_BOUNCE`) or "
                         "compacted as the others")
    ap.add_argument("--knobs", nargs="+", default=None, metavar="NAME=V,...",
                    help="instead of --chunks/--first: one variant per argument, each setting module constants "
                         "of jaxrt.integrators.path (e.g. GPU_COMPACT_MIN_TRIANGLES=0,GPU_CHUNKS=8; '' = the defaults), "
                         "or of another module as traverse_pallas.BRUTE_FORCE_MAX_TRIANGLES=0")
    ap.add_argument("--scenes", nargs="+", default=["cornell", "dragon"], choices=["cornell", "dragon"])
    ap.add_argument("--mesh", default="dragon")
    ap.add_argument("--no-off", action="store_true",
                    help="skip the uncompacted pass (ratios and pixels then against the first variant): with "
                         "JAXRT_CACHE=off the first variant's first call is then a fresh process's whole wait")
    args = ap.parse_args(argv)
    exr = bench.sky_exr(Path(tempfile.mkdtemp()) / "sky.exr")
    dev = jax.devices()[0]
    print(f"{getattr(dev, 'device_kind', dev.platform)}, jax {jax.__version__}; {args.size}², {args.spp} spp, "
          f"depth {args.depth}, median of {args.repeats} passes")
    for name in args.scenes:
        sc = bench.load(name, args.size, args.spp, args.depth, exr, args.mesh)
        base = ref = None
        of = "the first" if args.no_off else "off"
        if not args.no_off:
            base, ref = run_variant(sc, None, args.repeats)
            print(f"{name:8s} off      first {base['first_s']:6.2f} s  pass {base['pass_s'] * 1e3:8.2f} ms  "
                  f"mean {base['mean']:.7f}")
        if args.knobs is not None:
            variants = [(f"{text or 'default':36s}", dict(chunks=0, knobs=_knobs(text))) for text in args.knobs]
        else:
            variants = [(f"{m:<2d} chunks, 1st {how:9s}", dict(chunks=m, whole_first=how == "whole"))
                        for how in args.first for m in args.chunks]
        for label, kw in variants:
            try:
                r, img = run_variant(sc, repeats=args.repeats, **kw)
            except Exception as e:  # noqa: BLE001 -- one variant's failure (an XLA option, say) is reported
                print(f"{name:8s} {label} failed: {type(e).__name__}: {str(e)[:300]}")
                continue
            if ref is None:
                base, ref = r, img
            d = np.abs(img - ref)
            same = "equal" if not d.any() else f"max |diff| {d.max():.2e} on {np.mean(d > 0):.1e} of values"
            print(f"{name:8s} {label} first {r['first_s']:6.2f} s  "
                  f"pass {r['pass_s'] * 1e3:8.2f} ms  "
                  f"mean {r['mean']:.7f}  ({r['pass_s'] / base['pass_s']:.3f} of {of}; pixels {same})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
