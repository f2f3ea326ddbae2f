"""Where a process's time to first frame goes: import, scene load, trace+lower, compile, first frame,
image write, each phase timed in one process (run it twice with the same JAXRT_CACHE_DIR for the
cold and the warm figure), in wall and in CPU seconds (all threads; steadier on a shared machine),
with the slowest functions of each phase (cProfile).

    JAXRT_DATA=../shared/data/meshes python benchmarks/phases.py dragon --size 1024 [--profile 12]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--size", type=int, default=None, help="width and height (default: the scene's)")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="print the N slowest functions per phase")
    args = ap.parse_args()
    t0, c0 = time.perf_counter(), time.process_time()
    import numpy as np

    import jaxrt
    import jaxrt.scene  # the first JAX-using module: the cache and runtime defaults as the CLI gets them
    from jaxrt import image

    times = {"import": time.perf_counter() - t0}
    cpu = {"import": time.process_time() - c0}
    profiles = {}

    def phase(name, fn):
        pr = cProfile.Profile() if args.profile else None
        t, c = time.perf_counter(), time.process_time()
        if pr:
            pr.enable()
        out = fn()
        if pr:
            pr.disable()
            s = io.StringIO()
            pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats(args.profile)
            profiles[name] = s.getvalue()
        times[name] = time.perf_counter() - t
        cpu[name] = time.process_time() - c
        return out

    import jax

    # the runtime's start (CUDA context, allocator, plugin discovery), before any jaxrt work
    phase("backend", lambda: jax.devices())
    ov = {"camera.width": args.size, "camera.height": args.size} if args.size else None
    sc = phase("load", lambda: jaxrt.load_scene(args.scene, overrides=ov))
    lowered = phase("lower", lambda: jaxrt.frame.lower(sc))
    compiled = phase("compile", lambda: lowered.compile())
    img = phase("frame", lambda: np.asarray(compiled(sc)))
    with tempfile.TemporaryDirectory() as d:
        phase("write", lambda: (image.write(Path(d) / "a.exr", img), image.write_png(Path(d) / "a.png", img)))
    print("PHASES " + " ".join(f"{k} {v:.2f}" for k, v in times.items()) + f" total {sum(times.values()):.2f}")
    # CPU seconds of the process (every thread): on a shared, loaded machine these vary far less than
    # wall seconds, and on an idle one with N cores the wall time is between cpu / N and cpu.
    print("CPU    " + " ".join(f"{k} {v:.2f}" for k, v in cpu.items()) + f" total {sum(cpu.values()):.2f}")
    for name, text in profiles.items():
        print(f"--- {name}\n" + "\n".join(text.splitlines()[:args.profile + 12]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
