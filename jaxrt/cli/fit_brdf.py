"""`jaxrt fit-brdf`: fit an analytic model to a measured material directly in BRDF space."""

from __future__ import annotations

import argparse

EPILOG = """\
The fit minimises the chosen metric over a fixed sampling of direction pairs (MERL's half/difference
grid, solid-angle weighted, θi and θo up to 80°; see fitting/brdf_space.py) with Levenberg–Marquardt
from deterministic starts. E is reported in the metric's units (ngan: 1/sr) on a finer grid.

Examples:
  jaxrt fit-brdf merl/gold-metallic-paint --model cook_torrance --out fit.json --plot fit.png
  jaxrt fit-brdf scans/alum-bronze.binary --model ward --metric cuberoot
Exit codes: 0 success, 2 bad input (one-line message), 130 interrupted.
"""


def configure(parser: argparse.ArgumentParser) -> None:
    from fitting import brdf_space as bs
    from fitting import study

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("material", metavar="MATERIAL",
                        help="a measured material: COLLECTION/NAME (e.g. merl/alum-bronze) or a .binary / .h5 file")
    parser.add_argument("--model", required=True, help=f"model to fit: {', '.join(study.study_models())}")
    parser.add_argument("--metric", default="ngan", choices=bs.METRICS,
                        help="ngan (cosine-weighted L2, default), cuberoot or log")
    parser.add_argument("--out", metavar="FIT.json", help="write the result as JSON")
    parser.add_argument("--plot", metavar="FIT.png", help="write lobe slices and spheres, measured vs fit")
    parser.add_argument("--starts", type=int, default=8, help="deterministic starts (default 8)")
    parser.add_argument("--max-steps", type=int, default=100, help="solver iterations per start (default 100)")
    parser.add_argument("--sampling", metavar="NH,ND,NP",
                        help="fit grid: θh, θd, φd cells (default %s)" % ",".join(map(str, study.FIT_RESOLUTION)))
    parser.add_argument("--eval-sampling", metavar="NH,ND,NP",
                        help="grid the reported error is evaluated on (default %s)"
                             % ",".join(map(str, study.EVAL_RESOLUTION)))
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import contextlib
    import json

    from brdfs import measured
    from fitting import brdf_space as bs
    from fitting import report, study
    from jaxrt.cli.fit import check_outputs
    from jaxrt.errors import InputError
    from jaxrt.fsutil import atomic_path

    check_outputs((args.out, ".json", "--out"), (args.plot, ".png", "--plot"))
    model = bs.fit_model(args.model)
    if model.name not in study.study_models():
        raise InputError(f"--model {args.model}: not a diffuse + one lobe model; allowed: "
                         f"{', '.join(study.study_models())}")
    if args.starts < 1 or args.max_steps < 1:
        raise InputError("--starts and --max-steps must be at least 1")
    fit_res = study.parse_resolution(args.sampling, study.FIT_RESOLUTION, "--sampling")
    eval_res = study.parse_resolution(args.eval_sampling, study.EVAL_RESOLUTION, "--eval-sampling")
    mmodel, mparams = measured.load(args.material)  # InputError for an unknown name or a bad file
    fit = bs.fit_measured([args.material], model, metric=args.metric, samp=bs.sampling(*fit_res),
                          eval_samp=bs.sampling(*eval_res), starts=args.starts,
                          max_steps=args.max_steps, progress=not args.quiet)[0]
    print(report.format_brdf_fit(fit))
    outs = [(p, kind) for p, kind in ((args.out, "json"), (args.plot, "png")) if p]
    with contextlib.ExitStack() as stack:  # every output or none: renamed into place only if all were written
        for path, kind in outs:
            tmp = stack.enter_context(atomic_path(path))
            if kind == "json":
                tmp.write_text(json.dumps(fit.to_json(), indent=1))
            else:
                report.brdf_fit_png(tmp, fit, model, bs.as_params(fit), mmodel, mparams)
    for path, _ in outs:
        print(f"wrote {path}")
    return 0
