"""Where a Whitted frame's GPU time goes: per-kernel device time from a JAX profiler trace.

    JAXRT_DATA=../shared/data/meshes python benchmarks/profile_frame.py dragon --res 1024

Compiles `render.frame` for the scene, runs --frames frames under `jax.profiler.trace` (Perfetto
trace), and prints the kernels' summed device time per frame, grouped by name (largest first), with
the frame's wall time for reference. Nothing is written outside a temporary directory.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

import jaxrt as render  # noqa: E402
from jaxrt import scene as S  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--part", choices=("frame", "trace", "shade"), default="frame",
                    help="profile the whole frame, or only its trace or its shade half")
    ap.add_argument("--hlo", help="also write the frame's optimized HLO text here (maps kernel names to ops)")
    args = ap.parse_args(argv)
    scn = S.load(args.scene, overrides={"camera.width": args.res, "camera.height": args.res})
    if args.part == "shade":
        fn, fargs = render.shade, (jax.block_until_ready(render.trace(scn)), scn)
    else:
        fn, fargs = (render.frame if args.part == "frame" else render.trace), (scn,)
    jax.block_until_ready(fn(*fargs))
    if args.hlo:
        from jaxrt.fsutil import atomic_path

        with atomic_path(args.hlo) as p:
            Path(p).write_text(fn.lower(*fargs).compile().as_text())
    t = time.perf_counter()
    for _ in range(args.frames):
        jax.block_until_ready(fn(*fargs))
    wall = (time.perf_counter() - t) / args.frames
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(args.frames):
                jax.block_until_ready(fn(*fargs))
        path = next(Path(tmp).rglob("*.trace.json.gz"))
        events = json.load(gzip.open(path))
    events = events["traceEvents"] if isinstance(events, dict) else events
    # Device kernels live on the GPU "stream" threads; host threads are named by the runtime.
    pids = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu_pids = {p for p, n in pids.items() if "gpu" in n.lower() or "/device" in n.lower()}
    per = collections.defaultdict(float)
    count = collections.Counter()
    for e in events:
        if e.get("ph") == "X" and e.get("pid") in gpu_pids:
            per[e["name"]] += e.get("dur", 0.0)
            count[e["name"]] += 1
    total = sum(per.values()) / args.frames
    print(f"# {jax.devices()[0].device_kind}, scene {args.scene} {args.res}², {args.part}: wall {wall * 1e3:.2f} ms, "
          f"device kernels {total / 1e3:.2f} ms per frame ({sum(count.values()) // args.frames} launches)")
    print(f"# processes: {sorted(set(pids.values()))}")
    for name, us in sorted(per.items(), key=lambda kv: -kv[1])[: args.top]:
        print(f"{us / args.frames / 1e3:8.3f} ms  x{count[name] // args.frames:<4d} {name[:110]}")


if __name__ == "__main__":
    main()
