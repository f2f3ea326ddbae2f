"""`jaxrt study`: every analytic model fitted to every measured material (Ngan et al. 2005's study)."""

from __future__ import annotations

import argparse

EPILOG = """\
Writes into the output folder: study.csv and study.json (fitted parameters, standard errors, errors per
material and model), summary.md (median and quartile error per model, how often each is best),
errors.png (materials sorted by error, one curve per model, log scale) and spheres.png (measured | each
model's fit for a few materials). All five are written, or none.

Examples:
  jaxrt study --materials merl -o study/
  jaxrt study --materials merl/alum-bronze,merl/blue-acrylic --models ward,cook_torrance -o tiny/
Exit codes: 0 success, 2 bad input (one-line message), 130 interrupted.
"""


def configure(parser: argparse.ArgumentParser) -> None:
    from fitting import brdf_space as bs
    from fitting import study

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("--materials", default="merl",
                        help="merl (default), rgl, nielsen, all, or comma-separated names (merl/alum-bronze,...)")
    parser.add_argument("--models", help=f"comma-separated models (default all: {', '.join(study.study_models())})")
    parser.add_argument("--space", default="brdf", choices=("brdf", "image"),
                        help="brdf (default): fit in BRDF space; image: not implemented yet")
    parser.add_argument("--metric", default="ngan", choices=bs.METRICS, help="error metric (default ngan)")
    parser.add_argument("-o", "--output", default="study", metavar="DIR", help="output folder (default study/)")
    parser.add_argument("--grid", metavar="NAMES",
                        help="comma-separated materials of the sphere grid (default: six spread over the errors)")
    parser.add_argument("--starts", type=int, default=6, help="deterministic starts per fit (default 6)")
    parser.add_argument("--max-steps", type=int, default=100, help="solver iterations per start (default 100)")
    parser.add_argument("--batch", type=int, help="materials per compiled solve and device (default: all on a GPU, "
                                                  "1 on a CPU)")
    parser.add_argument("--devices", metavar="N", default="all",
                        help="split each solve's materials over the first N devices of jax.devices() (default: all; "
                             "1: the default device alone)")
    parser.add_argument("--sampling", metavar="NH,ND,NP",
                        help="fit grid: θh, θd, φd cells (default %s)" % ",".join(map(str, study.FIT_RESOLUTION)))
    parser.add_argument("--eval-sampling", metavar="NH,ND,NP",
                        help="grid the reported error is evaluated on (default %s)"
                             % ",".join(map(str, study.EVAL_RESOLUTION)))
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from fitting import study
    from jaxrt.errors import InputError

    if args.space == "image":
        raise InputError("--space image: the image-space study is not implemented yet; use --space brdf")
    out = study.check_output_dir(args.output)
    models = study.parse_models(args.models)
    materials = study.parse_materials(args.materials)
    grid = [g.strip() for g in args.grid.split(",") if g.strip()] if args.grid else None
    for g in grid or []:
        if g not in materials:
            raise InputError(f"--grid: {g!r} is not one of the study's materials")
    if args.starts < 1 or args.max_steps < 1 or (args.batch is not None and args.batch < 1):
        raise InputError("--starts, --max-steps and --batch must be at least 1")
    from jaxrt.cli.fit import devices_option

    devices = devices_option(args.devices)
    fit_res = study.parse_resolution(args.sampling, study.FIT_RESOLUTION, "--sampling")
    eval_res = study.parse_resolution(args.eval_sampling, study.EVAL_RESOLUTION, "--eval-sampling")
    result = study.run(materials, models, metric=args.metric, fit_resolution=fit_res, eval_resolution=eval_res,
                       starts=args.starts, max_steps=args.max_steps, batch=args.batch, progress=not args.quiet,
                       devices=devices)
    paths = study.write(result, out, grid)
    print(study.summary_markdown(result), end="")
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0
