"""Same-process A/B of the direct-light frame (`benchmarks/peers.py --rows direct`'s workload) between two trees.

    # 1. in the "before" tree (e.g. `git archive BASE | tar -x -C /tmp/before`): export its frame
    cd /tmp/before && JAXRT_DATA=… PYTHONPATH=/tmp/before python /path/to/frame_ab.py export bunny 512 before.bin
    # 2. in the "after" tree: compile both, check pixels, time them interleaved
    JAXRT_DATA=… PYTHONPATH=$PWD python benchmarks/frame_ab.py run bunny 512 before.bin --repeats 31

The frame (`jaxrt.integrators.whitted.whitted` of `peers.load_direct`: Lambert ρ = 0.5, the first light,
max_depth 1, 1 spp) is exported with `jax.export` with the scene's arrays as arguments, so both
programs run on the same arrays in one process: calls alternate (before, after, then after, before,
...), each timed in wall time and in the process's CPU seconds (all threads; steadier than wall time on
a shared machine), medians printed with the load average. Pixels: equal, or the largest difference.
Custom calls (the Embree / native traversal) are the running tree's: both trees must share them.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np
from jax import export

ROOT = Path(os.environ.get("PYTHONPATH", "").split(os.pathsep)[0] or Path(__file__).resolve().parents[1]).resolve()
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from peers import load_direct  # noqa: E402

from jaxrt.accel import traverse_cpu, traverse_embree  # noqa: E402
from jaxrt.integrators import whitted  # noqa: E402

TARGETS = tuple(getattr(traverse_embree, k) for k in ("TARGET", "KEY_TARGET", "KEYED_TARGET", "DIRECT_TARGET")
                if hasattr(traverse_embree, k)) + (traverse_cpu.TARGET,)


def exported(sc):
    """The frame as a function of the scene's arrays (a list), exported."""
    leaves, tdef = jax.tree.flatten(sc)
    idx = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array)]

    def f(arrs):
        lv = list(leaves)
        for i, a in zip(idx, arrs):
            lv[i] = a
        return whitted.whitted(jax.tree.unflatten(tdef, lv))

    arrs = [leaves[i] for i in idx]
    traverse_embree.available()  # compile and register the kernels before tracing
    checks = [export.DisabledSafetyCheck.custom_call(t) for t in TARGETS]
    return export.export(jax.jit(f), disabled_checks=checks)(arrs), arrs


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("export", "run"))
    ap.add_argument("scene", choices=("bunny", "dragon"))
    ap.add_argument("size", type=int)
    ap.add_argument("before", help="the exported program of the other tree (written by export, read by run)")
    ap.add_argument("--repeats", type=int, default=21)
    args = ap.parse_args(argv)
    sc = load_direct(args.scene, args.size)
    if args.mode == "export":
        Path(args.before).write_bytes(exported(sc)[0].serialize())
        return 0
    new, arrs = exported(sc)
    old = export.deserialize(Path(args.before).read_bytes())
    fns = {k: jax.jit(e.call).lower(arrs).compile() for k, e in (("before", old), ("after", new))}
    a, b = (np.asarray(fns[k](arrs)) for k in ("before", "after"))
    diff = np.abs(a - b)
    same = "equal" if np.array_equal(a, b) else (f"max |diff| {diff.max():.3g}, {np.mean(a != b):.4f} differ, "
                                                 f"{np.mean(diff.max(-1) > 1e-4) * a.shape[0] * a.shape[1]:.0f} "
                                                 "pixels by more than 1e-4")
    print(f"pixels: {same}; means {a.mean():.8g} / {b.mean():.8g}; after finite: {bool(np.isfinite(b).all())}")
    times = {k: [] for k in fns}
    load0 = os.getloadavg()[0]
    for r in range(args.repeats):
        for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
            t, c = time.perf_counter(), cpu_seconds()
            fns[k](arrs).block_until_ready()
            times[k].append((time.perf_counter() - t, cpu_seconds() - c))
    med = {k: (statistics.median(x[0] for x in v), statistics.median(x[1] for x in v)) for k, v in times.items()}
    print(f"{args.scene} {args.size}², direct + shadow, 1 spp, medians of {args.repeats}, load {load0:.1f} -> "
          f"{os.getloadavg()[0]:.1f}")
    for k, (w, c) in med.items():
        print(f"  {k:7s} wall {w * 1e3:8.2f} ms  cpu {c * 1e3:8.2f} ms")
    (wb, cb), (wa, ca) = med["before"], med["after"]
    print(f"  change: wall {wa / wb - 1:+.1%}, cpu {ca / cb - 1:+.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
