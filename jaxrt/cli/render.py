"""`jaxrt render SCENE`: render a scene file to a linear EXR and a display PNG."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import threading
import time

from jaxrt.errors import InputError
from jaxrt import glare, integrators
from jaxrt.fsutil import Outputs
from jaxrt.image import check_exposure
from jaxrt.shading import AOV_NAMES


EPILOG = """\
SCENE is a path to a TOML scene file or the name of a shipped scene (spheres, bunny, dragon,
cornell, showcase, instances, bunnies, the path-traced cornell_area and furnace, and the photon-mapped
caustics; `spheres`, `textured`, `caustics`,
`instances` and `furnace` need no data files, the others need $JAXRT_DATA).

Outputs: -o sets the EXR (linear float32 RGB, plus AOV channels with --aovs); --png sets the PNG
(sRGB, exposure applied). Without -o and --png, SCENE_STEM.exr and SCENE_STEM.png are written to the
current directory; with only one of them, only that one. Every output is checked (extension,
folder, writable) before any work, and all are written together at the end or none is.
With --confine (or JAXRT_CONFINE=1), mesh, texture and environment paths in the scene must stay
inside the scene file's folder or the data folder (JAXRT_DATA).

Memory: the render keeps its arrays (scene, image, the tile being rendered) within --memory, else
JAXRT_MEMORY, else half the RAM on a CPU (90% of the free memory on a GPU); an image that does not fit
in one piece is rendered in tiles of pixels and batches of samples, with a progress bar on stderr
(not with -q). A job that cannot fit one tile stops before rendering, naming the memory it needs.

Devices: the tiles are spread over every device JAX sees (all GPUs of the host; on a CPU, one
device per core, at most 8, unless JAX_NUM_CPU_DEVICES or XLA_FLAGS=--xla_force_host_platform_device_count=N
say otherwise: XLA:CPU runs one program on one thread), each device rendering its own tiles with the
whole scene (integrator sppm: each pass's photons split over them); --devices N uses the first N.
The memory budget applies to each device.

Glare: --glare on|off|KEY=VALUE,... adds (or removes) the diffraction glare of the camera's aperture,
a post-process of the whole finished image that preserves its sum (the [glare] table of a scene file;
README "Glare").

Exit codes: 0 success, 2 bad input (unreadable or invalid scene, bad option, missing mesh, a memory
budget too small), 130 interrupted (Ctrl-C stops within a fraction of a second and writes nothing).
Errors are one line; set JAXRT_DEBUG=1 for a traceback.

Examples:
  jaxrt render spheres                        # spheres.exr + spheres.png, 512x384
  jaxrt render scenes/dragon.toml -o d.exr --png d.png --width 256 --height 256 --spp 4
  jaxrt render spheres --glare aperture=polygon,blades=6,f_number=32
  jaxrt render caustics --passes 64 --photons 200000   # SPPM: the progress bar counts passes
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
                        help="whitted (point lights, mirrors, glass), path (path tracing with area and "
                             "environment lights) or sppm (photon mapping: caustics); overrides [render] integrator")
    parser.add_argument("--passes", type=int, metavar="N",
                        help="SPPM passes (integrator sppm: --camera-samples visible points per pixel and one "
                             "photon pass each; the same setting as --spp, which it overrides)")
    parser.add_argument("--photons", type=int, metavar="N",
                        help="SPPM photons per pass (overrides [render] photons; default: the pixel count)")
    parser.add_argument("--radius", type=float, metavar="R",
                        help="SPPM initial gather radius in scene units (overrides [render] radius; default: "
                             "one pixel footprint at each pixel's visible point)")
    parser.add_argument("--camera-samples", type=int, metavar="K",
                        help="SPPM visible points per pixel per pass, sharing the pass's photons (overrides "
                             "[render] camera_samples; default 1)")
    parser.add_argument("--photon-aim", type=float, metavar="F",
                        help="SPPM fraction of photons aimed at glass and mirror objects, 0 <= F < 1 (overrides "
                             "[render] photon_aim; default 0.5 with glass or mirrors, else 0)")
    parser.add_argument("--alpha", type=float, metavar="A",
                        help="SPPM radius reduction 0 < A < 1 (overrides [render] alpha; default 0.7; smaller "
                             "shrinks the gather radius faster: less blur, more noise)")
    parser.add_argument("--seed", type=int, help="random seed for jittered samples (overrides [render] seed)")
    parser.add_argument("--exposure", type=float, default=0.0,
                        help="PNG exposure in stops: pixel values are scaled by 2^EXPOSURE (default 0)")
    parser.add_argument("--aovs", action="store_true",
                        help=f"also store AOV channels in the EXR: {', '.join(AOV_NAMES)}")
    parser.add_argument("--confine", action="store_true",
                        help="refuse scene paths (meshes, textures, environment maps) outside the scene's "
                             "folder and the data folder (also JAXRT_CONFINE=1)")
    parser.add_argument("--memory", metavar="SIZE",
                        help="memory budget for the render, e.g. 2G or 512M (binary units; default: JAXRT_MEMORY, "
                             "else half the RAM on a CPU, 90%% of the free memory on a GPU)")
    parser.add_argument("--devices", metavar="N", default="all",
                        help="spread the render's tiles (sppm: each pass's photons) over the first N devices of "
                             "jax.devices() (default: all; 1 renders on the default device alone)")
    parser.add_argument("--glare", metavar="SPEC",
                        help="diffraction glare of the aperture, applied to the finished image: on (the scene's "
                             "[glare] table, else the defaults), off, or KEY=VALUE[,KEY=VALUE...] with the keys of "
                             "the [glare] table (turns glare on), e.g. aperture=polygon,blades=6,f_number=16 "
                             "(default: the scene's; see README \"Glare\")")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing on success (no progress bar)")


# A tile on a CPU holds at most this many ray samples, so the progress bar moves every few seconds
# (about 1-5 s per tile on one core for the shipped scenes); a GPU takes tiles as large as memory allows.
CPU_TILE_RAYS = 1 << 20
# Host memory of the image writers besides the image, measured as the growth of peak RSS while
# writing a 4096² image: EXR 3.1 bytes/pixel (+ 52 with the four AOVs, which are converted and
# copied), PNG 12.4 bytes/pixel, plus its sRGB strips (`image.to_srgb8`: at most 2^20 pixels at a
# time, two float32 RGB temporaries and the int64 lookup indices, 48 bytes each).
EXR_PIXEL, EXR_AOV_PIXEL, PNG_PIXEL = 4, 56, 13
PNG_STRIP_PIXELS, PNG_STRIP_PIXEL = 1 << 20, 48
# How long Ctrl-C waits for the render thread to reach a tile boundary before the process exits
# without waiting for the compiled call in flight (nothing has been written at that point).
STOP_GRACE_S = 0.5


def _render_in_thread(work, bar):
    """Run `work(should_stop)` in a daemon thread and wait for it in a way Ctrl-C can interrupt.

    A compiled XLA call blocks the thread that waits for it and Python only runs signal handlers in
    the main thread between bytecodes, so waiting in the main thread would hold Ctrl-C until the
    call returns. Here the main thread waits in short joins (refreshing the progress bar's clock
    on a terminal); on KeyboardInterrupt it asks the worker to stop at its next tile boundary and,
    if the worker is inside a long compiled call or a compilation, exits the process at once with
    status 130 (nothing has been written by then: outputs are written after the render).
    """
    tick = bar is not None and sys.stderr.isatty()
    stop, done = threading.Event(), threading.Event()
    box: dict = {}

    def target():
        try:
            box["value"] = work(stop.is_set)
        except BaseException as e:  # re-raised in the main thread
            box["error"] = e
        finally:
            done.set()

    # (waiting on an Event, not Thread.join: a join interrupted by KeyboardInterrupt can mark a
    # running thread as stopped in CPython 3.11, bpo-45274's fix)
    threading.Thread(target=target, name="jaxrt-render", daemon=True).start()
    try:
        while not done.wait(0.1):
            if tick:
                bar.refresh()
    except KeyboardInterrupt:
        stop.set()
        if not done.wait(STOP_GRACE_S):
            if bar is not None:
                bar.close()
            print("jaxrt: interrupted", file=sys.stderr, flush=True)
            sys.stdout.flush()
            os._exit(130)
        raise
    if "error" in box:
        raise box["error"]
    return box["value"]


def parse_glare_option(text: str) -> tuple[str, dict]:
    """`--glare on | off | KEY=VALUE[,KEY=VALUE...]` -> (mode, {key: value}): mode "on", "off" or
    "set" (the values override the scene's [glare] table, which they create; the scene parser checks
    their types and ranges). Values read as an integer, else a number, else a string."""
    usage = (f"--glare {text}: expected on, off or KEY=VALUE[,KEY=VALUE...] with keys "
             f"{', '.join(glare.FIELDS)}, e.g. --glare aperture=polygon,blades=6,f_number=16")
    if text in ("on", "off"):
        return text, {}
    values: dict = {}
    for item in text.split(","):
        key, eq, raw = (part.strip() for part in item.partition("="))
        if not eq or not key or not raw:
            raise InputError(usage)
        if key not in glare.FIELDS:
            raise InputError(f"--glare {text}: unknown key {key!r}; allowed: {', '.join(glare.FIELDS)}")
        for kind in (int, float):
            try:
                values[key] = kind(raw)
                break
            except ValueError:
                continue
        else:
            values[key] = raw
    return "set", values


_backend: list[threading.Thread] = []


def start_backend() -> None:
    """Start JAX's runtime (`jax.devices()`: the platform plugins, the client, a GPU's context) in a
    background thread, once per process, so that it overlaps the reading of the input files (scene,
    targets, the cached mesh and BVH arrays) instead of waiting for the first transfer (~0.4 s on an
    H200 host). The first JAX call of the command waits for it if it is still starting. Nothing is
    compiled or placed on a device; an error here is left for that first call to raise and report.
    The process waits for the thread before it exits (`atexit`), so a command that stops on bad input
    meanwhile never tears the interpreter down under a runtime that is still starting."""
    if _backend:
        return
    from jaxrt import _config

    _config.apply_runtime_defaults()  # before the backend starts (no GPU preallocation), whoever imported what

    def start():
        try:
            import jax

            jax.devices()
        except Exception:  # noqa: BLE001 -- see the docstring
            pass

    import atexit

    t = threading.Thread(target=start, name="jaxrt-backend", daemon=True)
    _backend.append(t)
    t.start()
    atexit.register(t.join)


_kernels: list[threading.Thread] = []


def start_kernels() -> None:
    """On a CPU, compile and load the native traversal kernel the traversal will use now, in a
    background thread, once per process: Embree's (`jaxrt.accel.traverse_embree`) where it is
    installed, else (or with JAXRT_TRAVERSAL=cpu) jaxrt's own (`traverse_cpu`), which `jaxrt.accel.bvh`
    uses only where Embree is not there; a stored program loads just the kernels it calls
    (`jaxrt.programs`). Their C++ compilation (the first process of a cache folder only: they are kept
    in <cache folder>/native) runs in a compiler process, about 5-10 s each on a 2-core CPU; started
    here, after the command's input checks, it runs beside the mesh load and the BVH build instead of
    inside the first program's tracing, which needs it. Later `available()` calls wait for it. Errors
    are the kernels' to report (a warning, then the slower traversal), as without this. The process
    waits for the thread before it exits, so it never leaves a compiler running or a half-written
    library behind."""
    if _kernels:
        return
    from jaxrt import _config

    traversal = _config.config().traversal
    if traversal not in ("auto", "cpu", "embree"):
        return

    def build():
        try:
            import jax

            if jax.default_backend() != "cpu":  # a GPU process lowers its programs for the GPU
                return
            from jaxrt.accel import traverse_cpu, traverse_embree

            if traversal == "cpu" or not traverse_embree.available():
                traverse_cpu.available()
        except Exception:  # noqa: BLE001 -- see the docstring
            pass

    import atexit

    t = threading.Thread(target=build, name="jaxrt-kernels", daemon=True)
    _kernels.append(t)
    t.start()
    atexit.register(t.join)


def write_outputs(tmp, exr, png, img, extra, exposure: float) -> None:
    """The EXR and the PNG, each into its temporary path, at the same time: they are independent, and
    their compression (OpenEXR's ZIP, Pillow's zlib) runs in C with the GIL released for much of it."""
    from jaxrt import image

    jobs = []
    if exr is not None:
        jobs.append(lambda: image.write_exr(tmp[exr], img, extra))
    if png is not None:
        jobs.append(lambda: image.write_png(tmp[png], img, exposure=exposure))
    if len(jobs) < 2:
        for job in jobs:
            job()
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(jobs), thread_name_prefix="jaxrt-write") as pool:
        for f in [pool.submit(job) for job in jobs]:
            f.result()  # the first error, after both have finished


def run(args: argparse.Namespace) -> int:
    from jaxrt import _config

    check_exposure(args.exposure, "--exposure")
    memory = None  # None: JAXRT_MEMORY, else the device's default (`render_tiles.plan`)
    if args.memory is not None:
        memory = _config.parse_size(args.memory, "--memory")
        if memory <= 0:
            raise InputError(f"--memory {args.memory}: must be a positive size, e.g. 8G")
    from jaxrt import _devices

    devices = _devices.parse(args.devices, "--devices")  # the range is checked against the host's devices later
    start_backend()
    outs = Outputs()
    outs.add(args.output, ".exr", "-o")
    outs.add(args.png, ".png", "--png")

    from jaxrt import scene as _scene

    path = _scene.find_scene(args.scene)
    overrides = {
        "camera.width": args.width, "camera.height": args.height, "render.spp": args.spp,
        "render.max_depth": args.max_depth, "render.seed": args.seed,
        "render.integrator": args.integrator, "render.photons": args.photons, "render.radius": args.radius,
        "render.photon_aim": args.photon_aim, "render.camera_samples": args.camera_samples,
        "render.alpha": args.alpha,
    }
    if args.passes is not None:
        overrides["render.spp"] = args.passes
    glare_mode = "scene"
    if args.glare is not None:
        glare_mode, glare_values = parse_glare_option(args.glare)
        overrides.update({f"glare.{k}": v for k, v in glare_values.items()})
    spec = _scene.parse(path, overrides=overrides, confine=args.confine or None)  # input errors surface
    if glare_mode == "off":
        spec = dataclasses.replace(spec, glare=None)
    elif glare_mode == "on" and spec.glare is None:
        spec = dataclasses.replace(spec, glare=glare.Glare())
    exr, png = args.output, args.png                                              # here, before JAX work
    if exr is None and png is None:
        exr = outs.add(f"{path.stem}.exr", ".exr", "output")
        png = outs.add(f"{path.stem}.png", ".png", "output")
    start_kernels()

    from jaxrt import image, render_tiles

    c = spec.camera
    npix = c.width * c.height
    # the writers run at the same time, after the render (`write_outputs`)
    reserve = (npix * (EXR_PIXEL + (EXR_AOV_PIXEL if args.aovs else 0)) if exr is not None else 0) + \
              (npix * PNG_PIXEL + min(npix, PNG_STRIP_PIXELS) * PNG_STRIP_PIXEL if png is not None else 0)
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=1, unit="tile", desc="scene", leave=False, dynamic_ncols=True, file=sys.stderr,
                   mininterval=0.2)
    times = {}

    def work(should_stop):
        import jax

        t0 = time.perf_counter()
        cpu = jax.devices()[0].platform == "cpu"
        max_rays = CPU_TILE_RAYS if cpu else None
        ahead = []

        def on_shapes(shapes):  # the frame compiles while the BVH is built (`render_tiles.compile_ahead`)
            ahead.append(render_tiles.compile_ahead(shapes, memory=memory, aovs=args.aovs, max_tile_rays=max_rays,
                                                    reserve=reserve, devices=devices))

        scn = _scene.build(spec, on_shapes=on_shapes)
        times["scene"] = time.perf_counter() - t0
        for t in ahead:
            if t is not None:
                t.join()  # the render then finds the program compiled (never compiles it twice)
        out = render_tiles.render(scn, memory=memory, aovs=args.aovs, progress=bar if bar is not None else False,
                                  max_tile_rays=max_rays, reserve=reserve,
                                  budget_source="--memory" if memory is not None else None,
                                  should_stop=should_stop, devices=devices, devices_source="--devices")
        times["render"] = time.perf_counter() - t0 - times["scene"]
        return scn, out

    try:
        scn, out = _render_in_thread(work, bar)
    finally:
        if bar is not None:
            bar.close()
    img, extra = out if args.aovs else (out, None)
    t1 = times["scene"]
    if not img.any():  # say so rather than write a black image silently
        print(f"jaxrt render: warning: {path.name}: the image is black everywhere (no light reaches the camera)",
              file=sys.stderr)
    with outs.writing() as tmp:  # all outputs or none
        write_outputs(tmp, exr, png, img, extra, args.exposure)
    if not args.quiet:
        wrote = " and ".join(str(p) for p in (exr, png) if p is not None)
        print(f"{path.name}: {c.width}x{c.height}, {spec.render.spp} {'passes' if spec.render.integrator == 'sppm' else 'spp'}, "
              f"{scn.geometry.triangle_count} triangles; scene {t1:.2f} s, "
              f"render {times['render']:.2f} s (incl. compile); wrote {wrote}", file=sys.stdout)
    return 0
