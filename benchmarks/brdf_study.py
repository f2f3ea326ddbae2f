"""Timing of the BRDF-space study (Ngan et al. 2005): N measured materials × every study model, the whole
pipeline of `jaxrt study` without the pictures (sampling the materials on both grids, the batched
fits, the errors on the evaluation grid).

Runs the study twice in one process (`--runs`): the first run includes compilation (in a fresh
process on a fresh machine: tracing, lowering and XLA compilation of every model's solver), the second
reuses the compiled programs. Prints wall time and process CPU time per run and per model, the XLA
compilations of each run (jax.monitoring), the machine's load average (this benchmark is often run on
shared machines) and, when N < 100, the extrapolation to 100 materials: the fits run in chunks of
`--batch` materials (default `fitting.study.default_batch`: one on a CPU, all on a GPU), so on a CPU
the per-material cost does not depend on N. The issue's targets: the 100 MERL materials × every study
model in ≤ 2 minutes on one GPU and ≤ 15 minutes on the 2-core CPU (`--materials 100`).

    JAXRT_DATA=../shared/data python benchmarks/brdf_study.py [--materials 20] [--models a,b] [--runs 2]
        [--batch B] [--devices N] [--json numbers.json] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax

from fitting import study


COMPILES = [0]


def _count(name, secs, **kwargs):
    if name == "/jax/core/compile/backend_compile_duration":
        COMPILES[0] += 1


def once(materials, models, batch, starts, max_steps, devices):
    t0, c0, n0 = time.perf_counter(), time.process_time(), COMPILES[0]
    result = study.run(materials, models, starts=starts, max_steps=max_steps, batch=batch, progress=False,
                       devices=devices)
    return time.perf_counter() - t0, time.process_time() - c0, COMPILES[0] - n0, result


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--materials", type=int, default=20, help="first N MERL materials (default 20)")
    ap.add_argument("--models", help="comma-separated (default all study models)")
    ap.add_argument("--batch", type=int)
    ap.add_argument("--starts", type=int, default=6)
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument("--devices", help="split each solve's materials over the first N devices (default: the default device)")
    ap.add_argument("--runs", type=int, default=2, help="runs in one process (default 2: the first compiles)")
    ap.add_argument("--json", help="also write the numbers here")
    ap.add_argument("--out", help="write the second run's study outputs (jaxrt study's files) into this folder")
    args = ap.parse_args()
    from brdfs import measured

    materials = list(measured.names("merl"))[: args.materials]
    models = study.parse_models(args.models)
    devices = None if args.devices is None else (args.devices if args.devices == "all" else int(args.devices))
    jax.monitoring.register_event_duration_secs_listener(_count)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, JAX {jax.__version__} "
          f"({jax.default_backend()}: {jax.devices()[0].device_kind}), load average {os.getloadavg()}")
    print(f"{len(materials)} MERL materials × {len(models)} models ({', '.join(models)}), {args.starts} starts, "
          f"≤ {args.max_steps} steps")
    out = {"materials": len(materials), "models": models, "backend": jax.default_backend(), "runs": []}
    for r in range(args.runs):
        label = "first (compiles)" if r == 0 else f"run {r + 1} (compiled)"
        wall, cpu, compiles, result = once(materials, models, args.batch, args.starts, args.max_steps, devices)
        print(f"{label}: wall {wall:.1f} s, process CPU {cpu:.1f} s, {compiles} XLA compilations; batch "
              f"{result.settings['batch']} on {result.settings['devices']} device(s); load average {os.getloadavg()}")
        print(f"    sampling the materials (both grids)  {result.settings['wall_s_sampling']:7.1f} s")
        for m, w in result.settings["wall_s_per_model"].items():
            print(f"    {m:<20} wall {w:7.1f} s")
        out["runs"].append({"label": label, "wall_s": wall, "cpu_s": cpu, "compilations": compiles,
                            "loadavg": os.getloadavg(),
                            "sampling_s": result.settings["wall_s_sampling"],
                            "per_model_s": result.settings["wall_s_per_model"]})
    print(study.summary_markdown(result))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        study.write(result, args.out)
    runs = out["runs"]
    print(f"{len(materials)} materials × {len(models)} models on {jax.default_backend()} "
          f"({jax.devices()[0].device_kind}): first run (cold: traces and compiles) {runs[0]['wall_s']:.1f} s"
          + (f", compiled run {runs[1]['wall_s']:.1f} s" if len(runs) > 1 else "")
          + "; the issue's goal for 100 × all models: ≤ 120 s on one GPU, ≤ 900 s on the 2-core CPU")
    if len(materials) < 100 and len(runs) >= 2:
        k = 100 / len(materials)
        first, second = runs[:2]
        compile_s = first["wall_s"] - second["wall_s"]
        est = compile_s + k * second["wall_s"]
        print(f"extrapolated to 100 materials: {est:.0f} s wall = compile {compile_s:.0f} s + {k:g} × {second['wall_s']:.1f} s "
              f"(CPU {k * second['cpu_s']:.0f} s + compile), at this load")
        out["extrapolated_100_wall_s"] = est
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
