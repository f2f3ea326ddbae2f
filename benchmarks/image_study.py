"""Timing of the image-space study (`jaxrt study --space image`, fitting.study_image): materials × every
study model fitted to renders of the measured material (two views), the whole pipeline without the
pictures.

Runs the study twice in one process (`--runs`): the first run includes compilation (the traces, the
target shade, one solver and one Jacobian per model), the second reuses the compiled programs. Prints
wall and process CPU time per run and per model, the XLA compilations of each run (counted with
jax.monitoring), the machine's load average, the scene used (the bunny, or the sphere when the bunny
mesh is missing) and the compared pixels, and the errors of the last run.

The fits are batched (`fitting.study_image.run_image(batched=True)`: each model's materials through one
compiled solve vmapped over materials and starts, `--batch` materials a call, default one on a CPU and
all on a GPU, `--devices N` to split each call over N devices); `--unbatched` fits each (material, model)
with `fitting.solve.fit_images` (its starts one after another), as before batching.

    JAXRT_DATA=../shared/data python benchmarks/image_study.py [--materials a,b] [--models a,b] [--size 64,64]
        [--scene auto|bunny|sphere] [--batch B] [--devices N] [--unbatched] [--runs 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax

from fitting import study, study_image


COMPILES = [0]


def _count(name, secs, **kwargs):
    if name == "/jax/core/compile/backend_compile_duration":
        COMPILES[0] += 1


def once(materials, models, scene, size, starts, max_steps, batched, batch, devices):
    t0, c0, n0 = time.perf_counter(), time.process_time(), COMPILES[0]
    result = study_image.run_image(materials, models, scene=scene, size=size, starts=starts, max_steps=max_steps,
                                   progress=False, batched=batched, batch=batch, devices=devices)
    return time.perf_counter() - t0, time.process_time() - c0, COMPILES[0] - n0, result


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--materials", help="comma-separated names (default: study_image.DEFAULT_MATERIALS)")
    ap.add_argument("--models", help="comma-separated (default all study models)")
    ap.add_argument("--size", default="64,64")
    ap.add_argument("--scene", default="auto", choices=study_image.SCENES)
    ap.add_argument("--starts", type=int, default=6)
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument("--batch", type=int, help="materials per compiled solve and device (default: 1 on a CPU, all on a GPU)")
    ap.add_argument("--devices", help="split each solve's materials over the first N devices (default: the default device)")
    ap.add_argument("--unbatched", action="store_true", help="one fit_images per (material, model), as before batching")
    ap.add_argument("--runs", type=int, default=2, help="runs in one process (default 2: the first compiles)")
    ap.add_argument("--json", help="also write the numbers here")
    ap.add_argument("--out", help="write the second run's study outputs (jaxrt study's files) into this folder")
    args = ap.parse_args()
    materials = study.parse_materials(args.materials) if args.materials else list(study_image.DEFAULT_MATERIALS)
    models = study.parse_models(args.models)
    size = tuple(int(v) for v in args.size.split(","))
    devices = None if args.devices is None else (args.devices if args.devices == "all" else int(args.devices))
    jax.monitoring.register_event_duration_secs_listener(_count)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, JAX {jax.__version__} "
          f"({jax.default_backend()}: {jax.devices()[0].device_kind}), load average {os.getloadavg()}")
    print(f"{len(materials)} materials × {len(models)} models ({', '.join(models)}), {size[0]}×{size[1]}, "
          f"{args.starts} starts, ≤ {args.max_steps} steps, {'unbatched' if args.unbatched else 'batched'}")
    out = {"materials": materials, "models": models, "size": size, "backend": jax.default_backend(), "runs": []}
    for r in range(args.runs):
        label = "first (compiles)" if r == 0 else f"run {r + 1} (compiled)"
        wall, cpu, compiles, result = once(materials, models, args.scene, size, args.starts, args.max_steps,
                                           not args.unbatched, args.batch, devices)
        st = result.settings
        print(f"{label}: wall {wall:.1f} s, process CPU {cpu:.1f} s, {compiles} XLA compilations; load average "
              f"{os.getloadavg()}; scene {st['scene']}, {st['pixels']} compared pixels, batch {st['batch']} on "
              f"{st['devices']} device(s); per material {wall / len(materials):.1f} s wall")
        for m, w in st["wall_s_per_model"].items():
            print(f"    {m:<20} wall {w:7.1f} s")
        out["runs"].append({"label": label, "wall_s": wall, "cpu_s": cpu, "compilations": compiles,
                            "loadavg": os.getloadavg(),
                            "scene": st["scene"], "pixels": st["pixels"], "per_model_s": st["wall_s_per_model"]})
    print(study.summary_markdown(result))
    for a in result.materials:
        print(f"  {a:<32} " + "  ".join(f"{m} {result.error(a, m):.3g} ({result.fits[(a, m)].errors['relative_rmse']:.1%})"
                                       for m in result.models))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        study.write(result, args.out)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
