"""Timing of the BRDF-space study (Ngan et al. 2005): N measured materials × every study model, the whole
pipeline of `jaxrt study` without the pictures (sampling the materials on both grids, the batched
fits, the errors on the evaluation grid).

Runs the study twice in one process: the first run includes compilation, the second reuses the
compiled programs. Prints wall time and process CPU time per run and per model, the machine's load
average (this benchmark is often run on shared machines) and, when N < 100, the extrapolation to 100
materials: the fits run in chunks of `--batch` materials (default `fitting.study.default_batch`: one
on a CPU, all on a GPU), so on a CPU the per-material cost does not depend on N.

    JAXRT_DATA=../shared/data/meshes python benchmarks/brdf_study.py [--materials 20] [--models a,b]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax

from fitting import study


def once(materials, models, batch, starts, max_steps):
    t0, c0 = time.perf_counter(), time.process_time()
    result = study.run(materials, models, starts=starts, max_steps=max_steps, batch=batch, progress=False)
    return time.perf_counter() - t0, time.process_time() - c0, result


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--materials", type=int, default=20, help="first N MERL materials (default 20)")
    ap.add_argument("--models", help="comma-separated (default all study models)")
    ap.add_argument("--batch", type=int)
    ap.add_argument("--starts", type=int, default=6)
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument("--json", help="also write the numbers here")
    ap.add_argument("--out", help="write the second run's study outputs (jaxrt study's files) into this folder")
    args = ap.parse_args()
    from brdfs import measured

    materials = list(measured.names("merl"))[: args.materials]
    models = study.parse_models(args.models)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, JAX {jax.__version__} "
          f"({jax.default_backend()}: {jax.devices()[0].device_kind}), load average {os.getloadavg()}")
    print(f"{len(materials)} MERL materials × {len(models)} models ({', '.join(models)}), {args.starts} starts, "
          f"≤ {args.max_steps} steps")
    out = {"materials": len(materials), "models": models, "backend": jax.default_backend(), "runs": []}
    for label in ("first (compiles)", "second (compiled)"):
        wall, cpu, result = once(materials, models, args.batch, args.starts, args.max_steps)
        print(f"{label}: wall {wall:.1f} s, process CPU {cpu:.1f} s; load average {os.getloadavg()}")
        print(f"    sampling the materials (both grids)  {result.settings['wall_s_sampling']:7.1f} s")
        for m, w in result.settings["wall_s_per_model"].items():
            print(f"    {m:<20} wall {w:7.1f} s")
        out["runs"].append({"label": label, "wall_s": wall, "cpu_s": cpu, "loadavg": os.getloadavg(),
                            "sampling_s": result.settings["wall_s_sampling"],
                            "per_model_s": result.settings["wall_s_per_model"]})
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        study.write(result, args.out)
        print(study.summary_markdown(result))
    if len(materials) < 100:
        k = 100 / len(materials)
        first, second = out["runs"]
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
