"""Where a process's time to first result goes, each phase timed in one process (run it twice with the
same JAXRT_CACHE_DIR for the cold and the warm figure), in wall and in CPU seconds (all threads; steadier
on a shared machine), with the slowest functions of each phase (cProfile).

A render (import, scene load, trace+lower, compile, first frame, image write):

    JAXRT_DATA=../shared/data/meshes python benchmarks/phases.py dragon --size 1024 [--profile 12]

A fit (`--fit`): the steps of `jaxrt fit TARGET.exr --scene SCENE --model cook_torrance --grey` one after
another (import, backend, target read, scene build + trace + fit buffer, solve + standard errors + ΔE,
report), with what each compiled and traced: XLA compilation requests and how many the persistent cache
served (`jax.monitoring`), functions traced to jaxprs, and `jaxrt.programs` stored programs read or
written. The target and the scene file at `--size` are made first in `--work` (default: a temporary
folder; untimed, in a process with a cache folder of its own, as `latency.py`'s fit-cli case):

    JAXRT_DATA=../shared/data/meshes python benchmarks/phases.py bunny --fit --size 256 --work /tmp/fitwork
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Phases:
    """Times (wall, CPU) each phase and, with `profile`, keeps its cProfile; with `counts`, the
    compilations, traces and stored programs of each phase."""

    def __init__(self, profile: int = 0, counts: bool = False):
        self.profile = profile
        self.times: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.counts: dict[str, dict] = {}
        self.profiles: dict[str, str] = {}
        self._events = None
        if counts:
            from jax import monitoring

            self._events = {"requests": 0, "cache hits": 0, "traces": 0}
            self._traced: list[str] = []  # the functions traced to jaxprs, in order
            self._compiled: list[str] = []  # the XLA compilation requests, in order
            self.names: dict[str, list[str]] = {}
            self.compiled: dict[str, list[str]] = {}

            def on_duration(event, duration, **kw):
                if event == "/jax/core/compile/backend_compile_duration":
                    self._events["requests"] += 1
                    self._compiled.append(f"{kw.get('fun_name')} {duration:.2f}s")
                elif event == "/jax/core/compile/jaxpr_trace_duration":
                    self._events["traces"] += 1
                    self._traced.append(f"{kw.get('fun_name')} {duration:.2f}s")

            def on_event(event, **kw):
                if event == "/jax/compilation_cache/cache_hits":
                    self._events["cache hits"] += 1

            monitoring.register_event_duration_secs_listener(on_duration)
            monitoring.register_event_listener(on_event)

    def _snapshot(self) -> dict:
        from jaxrt import programs

        s = programs.program_stats()
        return {**self._events, "stored hits": s.hits, "stored misses": s.misses, "fallbacks": s.fallbacks}

    def __call__(self, name, fn):
        pr = cProfile.Profile() if self.profile else None
        before = self._snapshot() if self._events is not None else None
        first = len(self._traced) if self._events is not None else 0
        first_compiled = len(self._compiled) if self._events is not None else 0
        t, c = time.perf_counter(), time.process_time()
        if pr:
            pr.enable()
        out = fn()
        if pr:
            pr.disable()
            s = io.StringIO()
            pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats(self.profile)
            self.profiles[name] = s.getvalue()
        self.times[name] = time.perf_counter() - t
        self.cpu[name] = time.process_time() - c
        if before is not None:
            after = self._snapshot()
            self.counts[name] = {k: after[k] - before[k] for k in after}
            self.names[name] = self._traced[first:]
            self.compiled[name] = self._compiled[first_compiled:]
        return out

    def report(self) -> None:
        # CPU: seconds of the process (every thread): on a shared, loaded machine these vary far less than
        # wall seconds, and on an idle one with N cores the wall time is between cpu / N and cpu.
        for label, values in (("PHASES", self.times), ("CPU   ", self.cpu)):
            print(f"{label} " + " ".join(f"{k} {v:.2f}" for k, v in values.items())
                  + f" total {sum(values.values()):.2f}")
        for name, c in self.counts.items():
            print(f"COUNTS {name}: " + ", ".join(f"{k} {v}" for k, v in c.items()))
            if self.names[name]:
                print(f"TRACED {name}: " + ", ".join(self.names[name]))
            if self.compiled[name]:
                print(f"COMPILED {name}: " + ", ".join(self.compiled[name]))
        for name, text in self.profiles.items():
            print(f"--- {name}\n" + "\n".join(text.splitlines()[:self.profile + 12]))


def render(args) -> int:
    t0, c0 = time.perf_counter(), time.process_time()
    import numpy as np

    import jaxrt
    import jaxrt.scene  # the first JAX-using module: the cache and runtime defaults as the CLI gets them
    from jaxrt import image

    import_wall, import_cpu = time.perf_counter() - t0, time.process_time() - c0
    phase = Phases(args.profile, counts=args.counts)
    phase.times["import"], phase.cpu["import"] = import_wall, import_cpu
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
    phase.report()
    return 0


def _fit_inputs(work: Path, scene: str, size: int, obj: str | None) -> None:
    """target.exr and scene.toml in `work` (`latency.py`'s FIT_TARGET), made in a process of their own with
    a cache folder of their own, so the measured process's cache is untouched."""
    if (work / "target.exr").exists() and (work / "scene.toml").exists():
        return
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from latency import FIT_TARGET, _env

    with tempfile.TemporaryDirectory(prefix="jaxrt-phases-") as cache:
        p = subprocess.run([sys.executable, "-c", FIT_TARGET, scene, str(size), obj or ""], cwd=work,
                           env=_env(Path(cache)), capture_output=True, text=True, check=False)
    if p.returncode != 0:
        sys.exit(f"making the target failed: {(p.stderr.strip().splitlines() or ['?'])[-1]}")


def fit(args) -> int:
    """The steps of `jaxrt.cli.fit.run` for one target, one after another."""
    work = Path(args.work or tempfile.mkdtemp(prefix="jaxrt-phases-fit-"))
    work.mkdir(parents=True, exist_ok=True)
    _fit_inputs(work, args.scene, args.size or 64, args.object)
    os.chdir(work)
    t0, c0 = time.perf_counter(), time.process_time()
    import numpy as np

    import brdfs
    from fitting import report
    from fitting import setup as fit_setup
    from jaxrt.cli import fit as cli_fit

    import_wall, import_cpu = time.perf_counter() - t0, time.process_time() - c0
    phase = Phases(args.profile, counts=True)
    phase.times["import"], phase.cpu["import"] = import_wall, import_cpu
    import jax

    phase("backend", lambda: jax.devices())
    model = brdfs.get(args.model)
    targets = phase("target", lambda: cli_fit._read_targets(["target.exr"]))
    setup = phase("prepare", lambda: fit_setup.prepare(["scene.toml"], model, object=args.object))
    result, _ = phase("fit", lambda: fit_setup.fit(None, np.stack(targets), model, setup=setup, rgb=False,
                                                    starts=args.starts, progress=False))
    phase("report", lambda: report.format_result(result))
    phase.report()
    print(f"fit: {result.iterations} steps of the best start, {result.total_iterations} in all, "
          f"solve {result.wall_time_s:.2f} s; params {result.params}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--size", type=int, default=None, help="width and height (default: the scene's; --fit: 64)")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="print the N slowest functions per phase")
    ap.add_argument("--counts", action="store_true", help="compilations, traces and stored programs per phase "
                                                         "(always on with --fit)")
    ap.add_argument("--fit", action="store_true", help="the phases of `jaxrt fit` on a target of the scene")
    ap.add_argument("--model", default="cook_torrance", help="--fit: the model (default cook_torrance)")
    ap.add_argument("--object", default=None, help="--fit: the fitted object (default: the scene's first)")
    ap.add_argument("--starts", type=int, default=6, help="--fit: starts (default 6, as `jaxrt fit`)")
    ap.add_argument("--work", default=None, help="--fit: folder for target.exr and scene.toml (kept; reused)")
    args = ap.parse_args()
    return fit(args) if args.fit else render(args)


if __name__ == "__main__":
    sys.exit(main())
