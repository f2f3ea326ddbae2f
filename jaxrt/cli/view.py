"""`jaxrt view SCENE`: an interactive window with sliders for materials, light and camera
(`jaxrt.viewer.Viewer`)."""

from __future__ import annotations

import argparse

from jaxrt import integrators


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = """\
Sliders: the selected object's material parameters (log sliders for exponents and roughnesses show
the value, not its log), δ, the model (radio buttons), light 0's position and intensity, and a
camera orbit about the look-at point. Every change re-runs the compiled frame; the first frame
compiles (tens of seconds on a CPU for big scenes). Use a small --width/--height on a CPU.
Path-traced scenes (or --integrator path) refine progressively while idle: each timer tick adds
one pass of --spp samples per pixel; the title shows the count; any change starts again.

Examples:
  jaxrt view spheres --object phong --width 256 --height 192
  jaxrt view scenes/dragon.toml
  jaxrt view furnace --width 64 --height 64 --spp 1
"""
    parser.add_argument("scene", metavar="SCENE", help="scene file (.toml) or shipped scene name")
    parser.add_argument("--object", help="object whose material the sliders edit (default: the first non-plane object)")
    parser.add_argument("--width", type=int, help="render width in pixels (default: the scene's)")
    parser.add_argument("--height", type=int, help="render height in pixels (default: the scene's)")
    parser.add_argument("--exposure", type=float, default=0.0, help="display exposure in stops")
    parser.add_argument("--frame", action="store_true", help="zoom the camera onto the selected object")
    parser.add_argument("--integrator", help=f"{' or '.join(integrators.names())} (default: the scene's; path "
                                                 "refines progressively)")
    parser.add_argument("--spp", type=int, help="samples per pixel of one (progressive) pass (default: the scene's)")
    parser.add_argument("--devices", metavar="N", default="all",
                        help="split each frame's tiles over the first N devices of jax.devices(), as jaxrt render "
                             "(default: all; 1: the default device alone)")
    parser.add_argument("--confine", action="store_true",
                        help="refuse scene paths (meshes, textures, environment maps) outside the scene's "
                             "folder and the data folder (also JAXRT_CONFINE=1)")


def run(args: argparse.Namespace) -> int:
    import matplotlib
    import matplotlib.pyplot as plt

    from jaxrt.image import check_exposure
    from jaxrt.viewer import Viewer

    from jaxrt import _devices

    check_exposure(args.exposure, "--exposure")
    n = _devices.parse(args.devices, "--devices")  # the range is checked against the host's devices by Viewer
    v = Viewer(args.scene, object=args.object, width=args.width, height=args.height, exposure=args.exposure,
               frame=args.frame, integrator=args.integrator, spp=args.spp, confine=args.confine or None,
               devices="all" if n is None else n, devices_source="--devices")
    v.figure()
    if matplotlib.get_backend().lower() == "agg":
        print("jaxrt view: no interactive matplotlib backend (is a display available?); "
              f"rendered one frame in {v.frame_time * 1e3:.1f} ms", flush=True)
        return 0
    plt.show()
    return 0
