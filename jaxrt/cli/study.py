"""`jaxrt study`: every analytic model fitted to every measured material (Ngan et al. 2005's study)."""

from __future__ import annotations

import argparse
import sys

EPILOG = """\
Writes into the output folder: study.csv and study.json (fitted parameters, standard errors, errors per
material and model), summary.md (median and quartile error per model, how often each is best),
errors.png (materials sorted by error, one curve per model, log scale) and spheres.png (measured | each
model's fit for a few materials). All five are written, or none.

--space image fits in image space instead (fitting.study_image): the bunny (or a sphere where the bunny
mesh is not installed; --scene) rendered with each measured material under two point lights (a key and
a rim light) is the target, every model is fitted to both renders jointly as `jaxrt fit` does; E is
the RMSE of the fitted renders (linear radiance) over the object's pixels, and renders.png (measured |
each model's fit) replaces spheres.png. Its default materials are a documented subset (%s).

Examples:
  jaxrt study --materials merl -o study/
  jaxrt study --materials merl/alum-bronze,merl/blue-acrylic --models ward,cook_torrance -o tiny/
  jaxrt study --space image --size 96,96 -o image-study/
Exit codes: 0 success, 2 bad input (one-line message), 130 interrupted.
"""


def configure(parser: argparse.ArgumentParser) -> None:
    from fitting import brdf_space as bs
    from fitting import study

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    from fitting import study_image

    parser.epilog = EPILOG % ", ".join(study_image.DEFAULT_MATERIALS)
    parser.add_argument("--materials",
                        help="merl, rgl, nielsen, all, or comma-separated names (merl/alum-bronze,...); default: "
                             "merl in BRDF space, a subset of four in image space")
    parser.add_argument("--models", help=f"comma-separated models (default all: {', '.join(study.study_models())})")
    parser.add_argument("--space", default="brdf", choices=("brdf", "image"),
                        help="brdf (default): fit in BRDF space; image: fit renders of the measured material")
    parser.add_argument("--scene", default="auto", choices=("auto", "bunny", "sphere"),
                        help="image space: the object rendered (default auto: the bunny if its mesh is found, "
                             "else a sphere)")
    parser.add_argument("--size", metavar="W,H", help="image space: render size (default %s)"
                        % ",".join(map(str, study_image.DEFAULT_SIZE)))
    parser.add_argument("--metric", default="ngan", choices=bs.METRICS, help="error metric (default ngan)")
    parser.add_argument("-o", "--output", default="study", metavar="DIR", help="output folder (default study/)")
    parser.add_argument("--grid", metavar="NAMES",
                        help="comma-separated materials of the sphere (or render) grid (default: six spread over the errors)")
    parser.add_argument("--starts", type=int, default=6, help="deterministic starts per fit (default 6)")
    parser.add_argument("--max-steps", type=int, default=100, help="solver iterations per start (default 100)")
    parser.add_argument("--batch", type=int, help="materials per compiled solve and device (default: all on a GPU, "
                                                  "1 on a CPU)")
    parser.add_argument("--devices", metavar="N", default="all",
                        help="split each solve's materials over the first N devices of jax.devices() (default: all, "
                             "on a CPU one fewer than the cores; 1: the default device alone)")
    parser.add_argument("--sampling", metavar="NH,ND,NP",
                        help="fit grid: θh, θd, φd cells (default %s)" % ",".join(map(str, study.FIT_RESOLUTION)))
    parser.add_argument("--eval-sampling", metavar="NH,ND,NP",
                        help="grid the reported error is evaluated on (default %s)"
                             % ",".join(map(str, study.EVAL_RESOLUTION)))
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from fitting import study, study_image
    from jaxrt.errors import InputError

    out = study.check_output_dir(args.output)
    models = study.parse_models(args.models)
    if args.materials:
        materials = study.parse_materials(args.materials)
    else:
        materials = list(study_image.DEFAULT_MATERIALS) if args.space == "image" else study.parse_materials("merl")
    grid = [g.strip() for g in args.grid.split(",") if g.strip()] if args.grid else None
    for g in grid or []:
        if g not in materials:
            raise InputError(f"--grid: {g!r} is not one of the study's materials")
    if args.starts < 1 or args.max_steps < 1 or (args.batch is not None and args.batch < 1):
        raise InputError("--starts, --max-steps and --batch must be at least 1")
    from jaxrt.cli.fit import devices_option

    devices = devices_option(args.devices)
    if args.space == "image":
        if args.metric != "ngan" or args.sampling or args.eval_sampling:
            raise InputError("--metric, --sampling and --eval-sampling apply to --space brdf only")
        size = parse_size(args.size)
        scene = study_image.choose_scene(args.scene)
        if args.scene == "auto" and scene == "sphere":
            print("jaxrt study: the bunny mesh is not found (JAXRT_DATA): the image-space study renders a sphere",
                  file=sys.stderr)
        result = study_image.run_image(materials, models, scene=scene, size=size, starts=args.starts,
                                       max_steps=args.max_steps, progress=not args.quiet, batch=args.batch,
                                       devices=devices)
    else:
        if args.size or args.scene != "auto":
            raise InputError("--scene and --size apply to --space image only")
        fit_res = study.parse_resolution(args.sampling, study.FIT_RESOLUTION, "--sampling")
        eval_res = study.parse_resolution(args.eval_sampling, study.EVAL_RESOLUTION, "--eval-sampling")
        result = study.run(materials, models, metric=args.metric, fit_resolution=fit_res, eval_resolution=eval_res,
                           starts=args.starts, max_steps=args.max_steps, batch=args.batch, progress=not args.quiet,
                           devices=devices)
    paths = study.write(result, out, grid)
    print(study.summary_markdown(result), end="")
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def parse_size(text: str | None) -> tuple[int, int]:
    """"W,H" -> (width, height) of the image-space study's renders (default `study_image.DEFAULT_SIZE`)."""
    from fitting import study_image
    from jaxrt.errors import InputError

    if not text:
        return study_image.DEFAULT_SIZE
    try:
        w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--size {text!r}: expected two integers W,H (e.g. 64,64)") from None
    if not (8 <= w <= 1024 and 8 <= h <= 1024):
        raise InputError(f"--size {text!r}: width and height must be between 8 and 1024")
    return w, h
