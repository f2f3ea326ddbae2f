"""`jaxrt fit` and `jaxrt fit-matrix`: recover BRDF parameters from target renders."""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

import brdfs
from jaxrt.errors import InputError

# The demo: the default scene framed on its centre sphere, small enough to fit in seconds on a CPU.
DEMO_SCENE = "spheres"
DEMO_OBJECT = "cook_torrance"
DEMO_OVERRIDES = {
    "camera.look_at": [0.0, 0.5, 0.6],
    "camera.vfov": 7.0,
    "camera.width": 96,
    "camera.height": 96,
    "render.max_depth": 2,
}
DEMO_MODELS = ("phong", "cook_torrance", "ward")
# every model with an eval: a delta BSDF has no parameters a render can recover this way
FIT_MODELS = tuple(n for n in brdfs.names() if not brdfs.get(n).delta)
# A second view lit from behind the sphere: grazing half-angles separate Cook-Torrance's ρs from η,
# which front lighting determines only as ρs·F0.
DEMO_RIM_LIGHT = {"position": [1.2, 1.6, -1.2], "intensity": [25.0, 25.0, 25.0]}


def demo_views() -> list:
    """The demo's two views of the default scene: as shipped, and rim-lit."""
    from fitting import setup as fit_setup

    return [DEMO_SCENE, fit_setup.variant(DEMO_SCENE, lights=[DEMO_RIM_LIGHT])]

FIT_EPILOG = """\
Targets are linear RGB EXR files rendered (or photographed) at the scene's resolution; give one
--scene for all of them, or one --scene per target (several views or light positions fit jointly).
Only pixels whose camera ray hits the chosen object are compared.

Examples:
  jaxrt fit --demo                                   # hidden parameters on the default scene, 3 models
  jaxrt fit target.exr --scene scenes/bunny.toml --model cook_torrance --fix eta=1.5 --out fit.json --plot fit.png
Targets must be finite, at most 1e12 (a float32 least-squares sum must hold them) and not negative
beyond noise (down to -0.1 x the largest value). The result says when the solver did not converge, when a parameter's standard error
is meaningless (the views do not determine it) and when the model cannot reproduce the target.
Outputs (--out, --plot; the demo's default fit_demo.png) are checked before any work and written
together at the end. --confine refuses scene paths outside the scene's folder and the data folder.
Exit codes: 0 success, 2 bad input (one-line message), 130 interrupted.
"""


#: The allowed --starts and --max-steps (a fit of more is a typing error, not a plan).
MAX_STARTS, MAX_STEPS = 1024, 100_000


def add_common_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--solver", default="lm", help="lm (Levenberg–Marquardt, default), gauss_newton, dogleg, bfgs")
    p.add_argument("--starts", type=int, default=6,
                   help=f"number of deterministic starts, 1..{MAX_STARTS} (default 6)")
    p.add_argument("--max-steps", type=int, default=200,
                   help=f"solver iterations per start, 1..{MAX_STEPS} (default 200)")
    p.add_argument("--grey", action="store_true", help="fit ρ parameters as one grey value instead of RGB")
    p.add_argument("--devices", metavar="N", default="all",
                   help="split the work over the first N devices of jax.devices() (default: all, on a CPU one fewer "
                        "than the cores; 1: the default device alone): fit's starts, fit-matrix's fits of each "
                        "model to every target")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = FIT_EPILOG
    parser.add_argument("targets", nargs="*", metavar="TARGET.exr", help="target images (linear EXR)")
    parser.add_argument("--scene", action="append", metavar="SCENE",
                        help="scene file or shipped name; once, or once per target")
    parser.add_argument("--model", help=f"model to fit: {', '.join(FIT_MODELS)}")
    parser.add_argument("--object", help="object whose material is fitted (default: the scene's first object)")
    parser.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                        help="hold a parameter fixed (RGB as r,g,b); repeatable")
    parser.add_argument("--init", action="append", default=[], metavar="NAME=VALUE",
                        help="starting value for the first start; repeatable")
    parser.add_argument("--out", metavar="FIT.json", help="write the result as JSON")
    parser.add_argument("--plot", metavar="FIT.png", help="write target | fit | error picture")
    parser.add_argument("--confine", action="store_true",
                        help="refuse scene paths (meshes, textures, environment maps) outside the scene's "
                             "folder and the data folder (also JAXRT_CONFINE=1)")
    parser.add_argument("--demo", action="store_true",
                        help="render targets of the default scene with hidden parameters and fit "
                             f"{', '.join(DEMO_MODELS)}")
    parser.add_argument("--split", choices=("starts", "nodes"), default="starts",
                        help="with several devices: run the starts at once, split over them (starts, default), "
                             "or split each residual evaluation's nodes over them (nodes)")
    add_common_options(parser)


def _assignments(items: list[str], flag: str) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise InputError(f"{flag} {item!r}: expected NAME=VALUE (RGB as NAME=r,g,b)")
        k, v = item.split("=", 1)
        try:
            vals = [float(x) for x in v.split(",")]
        except ValueError:
            raise InputError(f"{flag} {item!r}: {v!r} is not a number or r,g,b triple") from None
        if len(vals) not in (1, 3):
            raise InputError(f"{flag} {item!r}: give one value or three (r,g,b)")
        out[k.strip()] = vals[0] if len(vals) == 1 else vals
    return out


def check_common(args) -> None:
    """The solver options shared by fit and fit-matrix, before any work."""
    from fitting.solve import SOLVERS

    if args.solver not in SOLVERS:
        raise InputError(f"--solver {args.solver!r}: allowed: {', '.join(SOLVERS)}")
    if not 1 <= args.starts <= MAX_STARTS:
        raise InputError(f"--starts: expected an integer in [1, {MAX_STARTS}], got {args.starts}")
    if not 1 <= args.max_steps <= MAX_STEPS:
        raise InputError(f"--max-steps: expected an integer in [1, {MAX_STEPS}], got {args.max_steps}")
    args.devices = devices_option(args.devices)


def devices_option(text: str):
    """`--devices` of the fitting commands: the devices to split the work over (a tuple of
    `jax.devices()`), or None for the default device alone; one-line errors naming the flag."""
    from jaxrt import _devices

    n = _devices.parse(text, "--devices")
    devs = _devices.solver_devices("all" if n is None else n, "--devices")
    return devs if _devices.sharded(devs) else None


def check_outputs(*triples):
    """An `Outputs` holding every (path, suffix, flag) whose path is given, checked now."""
    from jaxrt.fsutil import Outputs

    outs = Outputs()
    for path, suffix, flag in triples:
        outs.add(path, suffix, flag)
    return outs


def write_json(path, obj) -> None:
    """Write `obj` as JSON to `path` (a temporary file of `Outputs.writing`, or any path)."""
    Path(path).write_text(json.dumps(obj, indent=2))


def fit_model(name: str | None, flag: str = "--model"):
    if name is None:
        raise InputError(f"{flag} is required (or use --demo)")
    if name not in brdfs.names():
        raise InputError(f"{flag} {name!r}: unknown model; allowed: {', '.join(FIT_MODELS)}")
    model = brdfs.get(name)
    if model.delta:
        raise InputError(f"{flag} {name}: a delta BSDF has no parameters a render can recover this way; "
                         f"allowed: {', '.join(FIT_MODELS)}")
    return model


def _read_targets(paths: list[str]) -> np.ndarray:
    from fitting.setup import check_targets
    from jaxrt import image

    imgs = []
    for p in paths:
        if not Path(p).is_file():
            raise InputError(f"{p}: no such target file")
        try:
            img = np.asarray(image.read_exr(p))
        except InputError:
            raise
        except Exception as e:  # OpenEXR raises its own types for unreadable files
            raise InputError(f"{p}: cannot read as OpenEXR ({e})") from None
        if img.ndim != 3 or img.shape[-1] != 3:
            raise InputError(f"{p}: expected an RGB image, got shape {img.shape}")
        check_targets(img, p)
        imgs.append(img)
    return imgs


def run(args: argparse.Namespace) -> int:
    from fitting import report
    from fitting import setup as fit_setup

    check_common(args)
    from jaxrt.cli.render import start_backend, start_kernels

    start_backend()  # the runtime starts while the targets and scene files are read
    if args.demo:
        outs = check_outputs((args.out, ".json", "--out"), (args.plot or "fit_demo.png", ".png", "--plot"))
        start_kernels()
        return _demo(args, outs)
    outs = check_outputs((args.out, ".json", "--out"), (args.plot, ".png", "--plot"))
    if not args.targets:
        raise InputError("give at least one TARGET.exr (or --demo)")
    model = fit_model(args.model)
    fix, init = _assignments(args.fix, "--fix"), _assignments(args.init, "--init")
    model.params(**fix)  # bounds-check before any JAX work
    model.params(**init)
    scenes = args.scene or []
    if len(scenes) not in (1, len(args.targets)):
        raise InputError(f"give one --scene, or one per target ({len(args.targets)}); got {len(scenes)}")
    if len(scenes) == 1:
        scenes = scenes * len(args.targets)
    targets = _read_targets(args.targets)
    start_kernels()  # the scene's trace needs one; it compiles while the scene loads
    setup = fit_setup.prepare(scenes, model, object=args.object, confine=args.confine or None,
                              progress=not args.quiet)
    expect = setup.mask.shape[1:]
    for p, t in zip(args.targets, targets):
        if t.shape[:2] != expect:
            raise InputError(f"{p}: target is {t.shape[1]}x{t.shape[0]} but the scene renders {expect[1]}x{expect[0]}")
    result, setup = fit_setup.fit(
        None, np.stack(targets), model, setup=setup, fix=fix, init=init, rgb=not args.grey, solver=args.solver,
        starts=args.starts, max_steps=args.max_steps, progress=not args.quiet, devices=args.devices,
        split=args.split,
    )
    print(f"object {setup.object!r}, {int(setup.mask.sum())} pixels")
    print(report.format_result(result))
    fitted = np.asarray(fit_setup.render_with(setup, _as_params(model, result))) if args.plot else None
    with outs.writing() as tmp:  # both outputs or neither
        if args.out:
            write_json(tmp[args.out], result.to_json())
        if args.plot:
            report.comparison_png(tmp[args.plot], np.stack(targets), fitted, setup.mask,
                                  titles=[Path(p).name for p in args.targets])
    return 0


def _as_params(model, result):
    import jax.numpy as jnp

    return {k: jnp.asarray(v, jnp.float32) for k, v in result.params.items()}


def hidden_params(model, seed: int) -> dict:
    """Deterministic 'unknown' parameters for demos and tests: uniform on each parameter's natural
    scale over the middle 70 % of its typical range (`Param.typical_range`: ordinary materials;
    a draw from the whole declared range, say a Phong exponent of 2e4, would make an unresolvable
    target)."""
    rng = np.random.default_rng(seed)

    def draw(p, t):
        lo, hi = p.typical_range
        if p.scale == "log":
            return float(np.clip(np.exp(np.log(lo) + t * (np.log(hi) - np.log(lo))), p.lo, p.hi))
        return float(lo + t * (hi - lo))

    out = {}
    for p in model.spec:
        if p.rgb:
            out[p.name] = [draw(p, t) for t in rng.uniform(0.15, 0.85, 3)]
        else:
            out[p.name] = draw(p, rng.uniform(0.15, 0.85))
    return out


def _in_thread(fn, *args) -> dict:
    """Start `fn(*args)` in a daemon thread; the returned dict gets "value" or "error", then its "done"
    Event is set. (Waiting on an Event, not `Thread.join`: a join interrupted by KeyboardInterrupt can
    mark a running thread as stopped in CPython 3.11.)"""
    box: dict = {"done": threading.Event()}

    def target():
        try:
            box["value"] = fn(*args)
        except BaseException as e:  # re-raised in the main thread
            box["error"] = e
        finally:
            box["done"].set()

    threading.Thread(target=target, name=f"jaxrt-{getattr(fn, '__name__', 'work')}", daemon=True).start()
    return box


def _demo(args, outs) -> int:
    from fitting import report
    from fitting import setup as fit_setup
    from jaxrt import integrators, scene
    from tqdm import tqdm

    import brdfs

    t0 = time.perf_counter()
    # The views are traced once for all models (a trace does not depend on the opaque model fitted,
    # and the demo's object is opaque); then each model's preparation, target, fit and fitted image run
    # in a thread of their own. Their programs are independent, and XLA compiles with the GIL released,
    # so the models' compilations (most of a first run) overlap; each thread computes what the same
    # calls compute one after another, bit for bit. The fits themselves run one at a time, as before:
    # their solves share XLA's CPU thread pool (nothing to gain from running them at once on a warm
    # run, which is almost all solving), and each fit's reported time stays its own.
    specs = [scene.parse(v if isinstance(v, dict) else scene.find_scene(v), overrides=DEMO_OVERRIDES)
             for v in demo_views()]
    traces = [integrators.trace(scene.build(s)) for s in specs]
    one_fit_at_a_time = threading.Lock()

    def one(i: int, name: str):
        model = brdfs.get(name)
        setup = fit_setup.prepare(specs, model, object=DEMO_OBJECT, traced=traces)
        truth = hidden_params(model, seed=100 + i)
        target = fit_setup.render_with(setup, model.params(**truth))
        with one_fit_at_a_time:
            result, _ = fit_setup.fit(None, target, model, setup=setup, rgb=not args.grey, solver=args.solver,
                                      starts=args.starts, max_steps=args.max_steps, progress=False,
                                      devices=args.devices)
        fitted = np.asarray(fit_setup.render_with(setup, _as_params(model, result))[0])
        return truth, np.asarray(target[0]), result, fitted

    targets, fits, titles, summary = [], [], [], []
    boxes = [_in_thread(one, i, name) for i, name in enumerate(DEMO_MODELS)]
    with tqdm(total=len(DEMO_MODELS), desc="fit --demo", unit="model", leave=False, disable=args.quiet,
              delay=0.5) as bar:
        try:
            for name, box in zip(DEMO_MODELS, boxes):
                while not box["done"].wait(0.1):
                    pass
                if "error" in box:  # the others finish first: no thread is left inside XLA at exit
                    for other in boxes:
                        other["done"].wait()
                    raise box["error"]
                truth, target, result, fitted = box["value"]
                bar.update(1)
                print(report.format_result(result, truth=truth))
                print()
                targets.append(target)
                fits.append(fitted)
                titles.append(name)
                summary.append({"truth": truth, "fit": result.to_json()})
        except KeyboardInterrupt:
            # The models' threads may be inside a compilation or a compiled call, which nothing can
            # stop from Python: exit at once (nothing has been written; outputs come at the end).
            bar.close()
            print("jaxrt: interrupted", file=sys.stderr, flush=True)
            sys.stdout.flush()
            os._exit(130)
    print(f"demo: {len(DEMO_MODELS)} fits in {time.perf_counter() - t0:.1f} s (including compilation)")
    plot = Path(args.plot or "fit_demo.png")
    with outs.writing() as tmp:  # both outputs or neither
        report.comparison_png(tmp[plot], np.stack(targets), np.stack(fits), np.ones(np.stack(targets).shape[:-1]),
                              titles=titles)
        if args.out:
            write_json(tmp[args.out], summary)
    print(f"wrote {plot}")
    return 0
