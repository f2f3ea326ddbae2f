"""`jaxrt render SCENE`: render a scene file to a linear EXR and a display PNG."""

from __future__ import annotations

import argparse
import sys
import time

from jaxrt.errors import InputError
from jaxrt import integrators
from jaxrt.fsutil import Outputs
from jaxrt.image import check_exposure
from jaxrt.shading import AOV_NAMES


EPILOG = """\
SCENE is a path to a TOML scene file or the name of a shipped scene (spheres, bunny, dragon,
cornell, showcase, instances, bunnies, and the path-traced cornell_area and furnace; `spheres`, `textured`,
`instances` and `furnace` need no data files, the others need $JAXRT_DATA).

Outputs: -o sets the EXR (linear float32 RGB, plus AOV channels with --aovs); --png sets the PNG
(sRGB, exposure applied). Without -o and --png, SCENE_STEM.exr and SCENE_STEM.png are written to the
current directory; with only one of them, only that one. Every output is checked (extension,
folder, writable) before any work, and all are written together at the end or none is.
With --confine (or JAXRT_CONFINE=1), mesh, texture and environment paths in the scene must stay
inside the scene file's folder or the data folder (JAXRT_DATA).

Exit codes: 0 success, 2 bad input (unreadable or invalid scene, bad option, missing mesh), 130
interrupted. Errors are one line; set JAXRT_DEBUG=1 for a traceback.

Examples:
  jaxrt render spheres                        # spheres.exr + spheres.png, 512x384
  jaxrt render scenes/dragon.toml -o d.exr --png d.png --width 256 --height 256 --spp 4
"""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("scene", metavar="SCENE", help="scene file (.toml) or shipped scene name")
    parser.add_argument("-o", "--output", metavar="OUT.exr", help="linear EXR output path")
    parser.add_argument("--png", metavar="OUT.png", help="sRGB PNG output path")
    parser.add_argument("--width", type=int, help="image width in pixels (overrides [camera] width)")
    parser.add_argument("--height", type=int, help="image height in pixels (overrides [camera] height)")
    parser.add_argument("--spp", type=int, help="samples per pixel, jittered when > 1 (overrides [render] spp)")
    parser.add_argument("--max-depth", type=int, help="ray tree depth, 1 = direct light only (overrides [render])")
    parser.add_argument("--integrator", choices=integrators.names(),
                        help="whitted (point lights, mirrors, glass) or path (path tracing with area and "
                             "environment lights; overrides [render] integrator)")
    parser.add_argument("--seed", type=int, help="random seed for jittered samples (overrides [render] seed)")
    parser.add_argument("--exposure", type=float, default=0.0,
                        help="PNG exposure in stops: pixel values are scaled by 2^EXPOSURE (default 0)")
    parser.add_argument("--aovs", action="store_true",
                        help=f"also store AOV channels in the EXR: {', '.join(AOV_NAMES)}")
    parser.add_argument("--confine", action="store_true",
                        help="refuse scene paths (meshes, textures, environment maps) outside the scene's "
                             "folder and the data folder (also JAXRT_CONFINE=1)")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")


def run(args: argparse.Namespace) -> int:
    check_exposure(args.exposure, "--exposure")
    outs = Outputs()
    outs.add(args.output, ".exr", "-o")
    outs.add(args.png, ".png", "--png")

    from jaxrt import scene as _scene

    path = _scene.find_scene(args.scene)
    overrides = {
        "camera.width": args.width, "camera.height": args.height, "render.spp": args.spp,
        "render.max_depth": args.max_depth, "render.seed": args.seed,
        "render.integrator": args.integrator,
    }
    spec = _scene.parse(path, overrides=overrides, confine=args.confine or None)  # input errors surface
    exr, png = args.output, args.png                                              # here, before JAX work
    if exr is None and png is None:
        exr = outs.add(f"{path.stem}.exr", ".exr", "output")
        png = outs.add(f"{path.stem}.png", ".png", "output")

    import numpy as np

    from jaxrt import image

    t0 = time.perf_counter()
    scn = _scene.build(spec)
    t1 = time.perf_counter()
    img, aovs = integrators.frame(scn, aovs=True)
    img = np.asarray(img)
    t2 = time.perf_counter()
    if not np.all(np.isfinite(img)):  # a renderer bug, never bad input: refuse to write it
        raise RuntimeError(f"{path}: the render contains NaN/Inf pixels; nothing was written")
    if not img.any():  # say so rather than write a black image silently
        print(f"jaxrt render: warning: {path.name}: the image is black everywhere (no light reaches the camera)",
              file=sys.stderr)
    with outs.writing() as tmp:  # all outputs or none
        if exr is not None:
            extra = {k: np.asarray(v) for k, v in aovs.items()} if args.aovs else None
            image.write_exr(tmp[exr], img, extra)
        if png is not None:
            image.write_png(tmp[png], img, exposure=args.exposure)
    if not args.quiet:
        c = spec.camera
        outs = " and ".join(str(p) for p in (exr, png) if p is not None)
        print(f"{path.name}: {c.width}x{c.height}, {spec.render.spp} spp, "
              f"{scn.geometry.triangle_count} triangles; scene {t1 - t0:.2f} s, "
              f"render {t2 - t1:.2f} s (incl. compile); wrote {outs}", file=sys.stdout)
    return 0
