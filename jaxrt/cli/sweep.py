"""`jaxrt sweep MODEL PARAM`: render a parameter sweep of one BRDF model as a labelled image strip."""

from __future__ import annotations

import argparse
import sys

import brdfs
from jaxrt.errors import InputError

EPILOG = f"""\
MODEL is a registered BRDF ({', '.join(brdfs.names())}); PARAM is one of its parameters (see
`jaxrt brdf-report`) or `delta`, the mirror reflection
coefficient δ (not for glass). RGB parameters are swept grey. Without --from/--to the parameter's
whole declared range is swept, on its natural scale (log for exponents and roughnesses).

The object (default: the first sphere of the `spheres` scene) is shown alone on the floor, framed by
the camera; all frames share one compiled renderer. Each frame is captioned with model, parameter
and value. The PNG is written atomically.

Examples:
  jaxrt sweep phong s --steps 7 -o phong_s.png
  jaxrt sweep cook_torrance m --from 0.01 --to 1 --steps 5 -o ct_m.png --width 128 --height 128
  jaxrt sweep glass n_t --from 1 --to 2 -o glass.png
Exit codes: 0 success, 2 bad input (unknown model/parameter, value out of range), 130 interrupted.
"""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("model", metavar="MODEL", help=f"BRDF model: {', '.join(brdfs.names())}")
    parser.add_argument("param", metavar="PARAM", help="parameter to sweep, or delta")
    parser.add_argument("--from", dest="start", type=float, help="first value (default: the declared minimum)")
    parser.add_argument("--to", dest="stop", type=float, help="last value (default: the declared maximum)")
    parser.add_argument("--steps", type=int, default=7, help="number of frames (default 7)")
    parser.add_argument("-o", "--output", default="sweep.png", metavar="STRIP.png",
                        help="output PNG (default sweep.png)")
    parser.add_argument("--width", type=int, default=128, help="frame width in pixels (default 128)")
    parser.add_argument("--height", type=int, default=128, help="frame height in pixels (default 128)")
    parser.add_argument("--scene", default="spheres", help="scene file or shipped name (default spheres)")
    parser.add_argument("--object", help="object to re-material (default: the first object that is not a plane)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="fix another parameter of the model (grey value); repeatable")
    parser.add_argument("--exposure", type=float, default=0.0, help="display exposure in stops (default 0)")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")


def _assignments(items: list[str]) -> dict:
    out = {}
    for item in items:
        k, sep, v = item.partition("=")
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise InputError(f"--set {item!r}: expected NAME=VALUE with a number") from None
        if not sep:
            raise InputError(f"--set {item!r}: expected NAME=VALUE")
    return out


def run(args: argparse.Namespace) -> int:
    import brdfs
    from jaxrt import sweep

    model = brdfs.get(args.model)
    if not 1 <= args.steps <= 64:
        raise InputError(f"--steps: expected an integer in [1, 64], got {args.steps}")
    vals = sweep.span(model, args.param, args.start, args.stop, args.steps)
    from jaxrt.fsutil import Outputs
    from jaxrt.image import check_exposure

    outs = Outputs()
    out = outs.add(args.output, ".png", "-o")
    check_exposure(args.exposure, "--exposure")
    base = _assignments(args.set)
    if args.param in base:
        raise InputError(f"--set {args.param}: that is the swept parameter")
    images = sweep.sweep(model, args.param, vals, scene=args.scene, object=args.object, width=args.width,
                         height=args.height, base_params=base)
    with outs.writing() as tmp:
        sweep.strip_png(tmp[out], images, sweep.labels(model, args.param, vals), sweep.title(model, args.param),
                        exposure=args.exposure)
    if not args.quiet:
        print(f"{model.name}.{args.param}: {len(vals)} frames {args.width}x{args.height}; wrote {out}",
              file=sys.stdout)
    return 0
