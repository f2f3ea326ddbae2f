"""Where a CPU path-tracing pass's time goes: per-op self time and how busy the threads are.

    JAXRT_DATA=… PYTHONPATH=$PWD python benchmarks/profile_path.py cornell --size 256 --passes 2

Compiles `path.samples_jit` for one of `benchmarks/path.py`'s scenes (16 spp, depth 4 unless told),
times --passes passes (wall and process CPU seconds), then runs them again under `jax.profiler.trace`
and prints, from the trace's host threads: the self time of each op name summed over threads (an
op's time minus the ops nested in it on the same thread, so a while loop or a conditional counts only
its own overhead), grouped by the name with its numeric suffix dropped, largest first; and how many
threads were running an op over the pass's wall time (time with 0, 1, 2, ... ops in flight), which
says whether the cores are used. Nothing is written outside a temporary directory.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import importlib.util
import json
import os
import re
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

from jaxrt.integrators import path as P  # noqa: E402


def _path_bench():
    spec = importlib.util.spec_from_file_location("bench_path", ROOT / "benchmarks" / "path.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def self_times(events):
    """(name, self µs, thread) of every complete event, nesting resolved per thread."""
    by_thread = collections.defaultdict(list)
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            by_thread[(e["pid"], e["tid"])].append(e)
    out = []
    for th, evs in by_thread.items():
        evs.sort(key=lambda e: (e["ts"], -e["dur"]))
        stack = []  # [end, event, children µs]
        def pop():
            end, ev, child = stack.pop()
            out.append((ev["name"], ev["dur"] - child, th, ev["ts"], ev["dur"]))
            if stack:
                stack[-1][2] += ev["dur"]
        for e in evs:
            while stack and stack[-1][0] <= e["ts"]:
                pop()
            stack.append([e["ts"] + e["dur"], e, 0.0])
        while stack:
            pop()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", choices=("cornell", "dragon"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--hlo", help="also write the pass's optimized HLO text here (maps op names to code)")
    args = ap.parse_args(argv)
    pb = _path_bench()
    with tempfile.TemporaryDirectory() as tmp:
        sc = pb.load(args.scene, args.size, args.spp, args.depth, pb.sky_exr(Path(tmp) / "sky.exr"), "dragon")
    t = time.perf_counter()
    jax.block_until_ready(P.samples_jit(sc, 0, jitter=True))
    print(f"# compile + first pass {time.perf_counter() - t:.2f} s")
    if args.hlo:
        Path(args.hlo).write_text(P.samples_jit.lower(sc, 0, jitter=True).compile().as_text())
    walls, cpus = [], []
    for i in range(args.passes):
        t, c = time.perf_counter(), cpu_seconds()
        jax.block_until_ready(P.samples_jit(sc, i + 1, jitter=True))
        walls.append(time.perf_counter() - t)
        cpus.append(cpu_seconds() - c)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            t0 = time.perf_counter()
            for i in range(args.passes):
                jax.block_until_ready(P.samples_jit(sc, i + 1, jitter=True))
            prof_wall = (time.perf_counter() - t0) / args.passes
        events = json.load(gzip.open(next(Path(tmp).rglob("*.trace.json.gz"))))
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {(e["pid"], e["tid"]): e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") == "thread_name"}
    rows = self_times(events)
    # host threads that ran XLA ops: skip the Python thread's own dispatch events
    per = collections.defaultdict(float)
    cnt = collections.Counter()
    threads = collections.defaultdict(float)
    spans = []
    # XLA's ops: events on the runtime's threads, not the Python thread's dispatch and waits
    rows = [r for r in rows if names.get(r[2], "") != "python" and "Execute" not in r[0] and not r[0].startswith("$")]
    for name, us, th, ts, dur in rows:
        key = re.sub(r"[.\d]+$", "", name)
        per[key] += us
        cnt[key] += 1
        threads[th] += us
    total = sum(per.values()) / args.passes
    print(f"# {args.scene} {args.size}², {args.spp} spp, depth {args.depth}: wall {statistics.median(walls) * 1e3:.0f} ms, "
          f"cpu {statistics.median(cpus) * 1e3:.0f} ms per pass (medians of {args.passes}), load {load:.1f}; "
          f"under the profiler {prof_wall * 1e3:.0f} ms; ops' self time {total / 1e3:.0f} ms per pass")
    for th, us in sorted(threads.items(), key=lambda kv: -kv[1])[:8]:
        print(f"#   thread {names.get(th, th)!s:40.40s} {us / args.passes / 1e3:8.1f} ms")
    # concurrency: leaf ops (self time > 0 and no nesting counted) over all threads
    leaf = [(ts, ts + dur) for name, us, th, ts, dur in rows if us >= 0.999 * dur]
    edges = sorted([(a, 1) for a, b in leaf] + [(b, -1) for a, b in leaf])
    hist = collections.defaultdict(float)
    level, last = 0, edges[0][0] if edges else 0
    for x, dlt in edges:
        hist[level] += x - last
        level, last = level + dlt, x
    span = sum(hist.values())
    print("# time with k leaf ops in flight: " + ", ".join(f"{k}: {v / span:.0%}" for k, v in sorted(hist.items())))
    for name, us in sorted(per.items(), key=lambda kv: -kv[1])[: args.top]:
        print(f"{us / args.passes / 1e3:8.1f} ms {100 * us / args.passes / total:5.1f} %  x{cnt[name] // args.passes:<6d} "
              f"{name[:100]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
