"""`jaxrt fit-matrix`: fit every model to targets rendered by every other model (Ngan et al. 2005 style)."""

from __future__ import annotations

import argparse

from jaxrt.errors import InputError

from jaxrt.cli.fit import (
    DEMO_OBJECT,
    DEMO_OVERRIDES,
    DEMO_SCENE,
    FIT_MODELS,
    add_common_options,
    check_common,
    check_outputs,
    fit_model,
    hidden_params,
    write_json,
)


MATRIX_MODELS = ("lambert", "phong", "blinn_phong", "cook_torrance", "ward", "ashikhmin_shirley")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=DEMO_SCENE, help=f"scene (default {DEMO_SCENE}, framed on --object)")
    parser.add_argument("--object", default=DEMO_OBJECT, help=f"object to re-material (default {DEMO_OBJECT})")
    parser.add_argument("--models", default=",".join(MATRIX_MODELS),
                        help=f"comma-separated models, any of: {', '.join(FIT_MODELS)} (default: %(default)s)")
    parser.add_argument("-o", "--output", default="fit_matrix.png", help="heat-map PNG (default fit_matrix.png)")
    parser.add_argument("--out", metavar="MATRIX.json", help="also write the matrix as JSON")
    add_common_options(parser)


def run(args: argparse.Namespace) -> int:
    from fitting import report
    from fitting import setup as fit_setup

    names = [n.strip() for n in args.models.split(",") if n.strip()]
    if not names:
        raise InputError(f"--models {args.models!r}: give one or more comma-separated models of: "
                         f"{', '.join(FIT_MODELS)}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"--models {args.models!r}: {twice[0]} is given more than once")
    models = [fit_model(n, "--models") for n in names]
    check_common(args)
    outs = check_outputs((args.output, ".png", "-o"), (args.out, ".json", "--out"))
    overrides = [DEMO_OVERRIDES] if args.scene == DEMO_SCENE else None
    setups = {m.name: fit_setup.prepare(args.scene, m, object=args.object, overrides=overrides) for m in models}
    truths = {m.name: hidden_params(m, seed=7 + i) for i, m in enumerate(models)}
    mat = fit_setup.cross_model_matrix(setups, truths, rgb=not args.grey, solver=args.solver, starts=args.starts,
                                       max_steps=args.max_steps, progress=not args.quiet,
                                       devices=args.devices)
    width = max(len(n) for n in names) + 2
    print("relative RMSE of the best fit (rows: target model, columns: fitted model)")
    print(" " * width + "".join(f"{n[:10]:>11}" for n in names))
    for i, n in enumerate(names):
        print(f"{n:<{width}}" + "".join(f"{mat[i, j]:>11.3g}" for j in range(len(names))))
    with outs.writing() as tmp:  # both outputs or neither
        report.matrix_png(tmp[args.output], names, mat, f"cross-model fit residuals ({args.scene}, {args.object})")
        if args.out:
            write_json(tmp[args.out], {"models": names, "relative_rmse": mat.tolist()})
    print(f"wrote {args.output}")
    return 0

