"""Same-process A/B of one path-tracing pass (`jaxrt.integrators.path.samples`) between two trees.

    # 1. in the "before" tree (e.g. `git archive BASE | tar -x -C /tmp/before`): export its program
    cd /tmp/before && JAXRT_DATA=… PYTHONPATH=/tmp/before python /path/to/path_ab.py export cornell 256 before.bin
    # 2. in the "after" tree: compile both, check pixels, time them interleaved
    JAXRT_DATA=… PYTHONPATH=$PWD python benchmarks/path_ab.py run cornell 256 before.bin --repeats 5

Scenes and parameters are `benchmarks/path.py`'s (16 spp, max_depth 4, --size²). The pass is exported
with `jax.export` with the scene's arrays as arguments, so both programs run on the same arrays in one
process: calls alternate (before, after, then after, before, ...), each timed in wall time and in the
process's CPU seconds (both threads; steadier than wall time on a shared machine), medians printed with
the load average. Pixels: equal, or the largest difference and the share of values that differ.
Custom calls (the Embree / native traversal) are the running tree's: both trees must share them.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import export

ROOT = Path(os.environ.get("PYTHONPATH", "").split(os.pathsep)[0] or Path(__file__).resolve().parents[1]).resolve()
sys.path.insert(0, str(ROOT))

from jaxrt.accel import traverse_cpu, traverse_embree  # noqa: E402
from jaxrt.integrators import path as P  # noqa: E402

TARGETS = (traverse_embree.TARGET, traverse_embree.KEY_TARGET, traverse_embree.KEYED_TARGET, traverse_cpu.TARGET)


def _path_bench():
    spec = importlib.util.spec_from_file_location("bench_path", ROOT / "benchmarks" / "path.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def scene(name: str, size: int, tmp: Path):
    pb = _path_bench()
    return pb.load(name, size, 16, 4, pb.sky_exr(tmp / "sky.exr"), "dragon")


def exported(sc):
    """The pass as a function of the scene's arrays (a list) and the pass index, exported."""
    leaves, tdef = jax.tree.flatten(sc)
    idx = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array)]

    def f(arrs, pass_index):
        lv = list(leaves)
        for i, a in zip(idx, arrs):
            lv[i] = a
        return P.samples(jax.tree.unflatten(tdef, lv), pass_index, jitter=True)

    arrs = [leaves[i] for i in idx]
    checks = [export.DisabledSafetyCheck.custom_call(t) for t in TARGETS]
    return export.export(jax.jit(f), disabled_checks=checks)(arrs, jnp.uint32(0)), arrs


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("export", "run"))
    ap.add_argument("scene", choices=("cornell", "dragon"))
    ap.add_argument("size", type=int)
    ap.add_argument("before", help="the exported program of the other tree (written by export, read by run)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        sc = scene(args.scene, args.size, Path(tmp))
    if args.mode == "export":
        Path(args.before).write_bytes(exported(sc)[0].serialize())
        return 0
    new, arrs = exported(sc)
    old = export.deserialize(Path(args.before).read_bytes())
    fns = {k: jax.jit(e.call).lower(arrs, jnp.uint32(0)).compile() for k, e in (("before", old), ("after", new))}
    a, b = (np.asarray(fns[k](arrs, jnp.uint32(0))) for k in ("before", "after"))
    diff = np.abs(a - b)
    same = "equal" if np.array_equal(a, b) else (f"max |diff| {diff.max():.3g}, {np.mean(a != b):.4f} differ, "
                                                 f"{np.mean(diff > 1e-4):.4f} by more than 1e-4")
    print(f"pixels: {same}; means {a.mean():.7g} / {b.mean():.7g}; after finite: {bool(np.isfinite(b).all())}")
    times = {k: [] for k in fns}
    load0 = os.getloadavg()[0]
    for r in range(args.repeats):
        for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
            t, c = time.perf_counter(), cpu_seconds()
            fns[k](arrs, jnp.uint32(r + 1)).block_until_ready()
            times[k].append((time.perf_counter() - t, cpu_seconds() - c))
    med = {k: (statistics.median(x[0] for x in v), statistics.median(x[1] for x in v)) for k, v in times.items()}
    print(f"{args.scene} {args.size}², 16 spp, depth 4, medians of {args.repeats}, load {load0:.1f} -> "
          f"{os.getloadavg()[0]:.1f}")
    for k, (w, c) in med.items():
        print(f"  {k:7s} wall {w * 1e3:8.1f} ms  cpu {c * 1e3:8.1f} ms")
    (wb, cb), (wa, ca) = med["before"], med["after"]
    print(f"  change: wall {wa / wb - 1:+.1%}, cpu {ca / cb - 1:+.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
