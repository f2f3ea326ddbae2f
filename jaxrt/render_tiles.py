"""Tiled rendering: any allowed resolution and sample count within a memory budget.

`render(scene, memory=...)` renders an image as a sequence of tiles, each a rectangle of pixels and
a run of their samples (`jaxrt.camera.Window`), through one compiled program
(`jaxrt.integrators.tile`: the tile's extents are static, its origin and sample count traced), and
streams each tile into a host buffer. A job that fits the budget in one piece runs `integrators.frame`
itself, the program an untiled render compiles, so small renders compile nothing new.

This module sits above the integrators (it schedules any registered integrator's tiles and reads the
device's memory and `JAXRT_MEMORY`, which light transport never needs) and below the API and CLI; it is
also the unit that several devices share: every tile is independent, the scene is the same argument
for all of them, and a tile's origin is a traced value, so on a device mesh (`jaxrt._devices`, the
`devices` argument, all of `jax.devices()` by default) each call runs the same program on one
origin per device, `Plan.steps` taken N at a time, and the host gathers each call's tiles. The
budget then applies to each device (on a CPU, whose virtual devices share the RAM, it is split
between them), and the image has at least max(32, 4·N) tiles for load balance.

A progressive whole-frame integrator (`integrators.sppm`: each pass needs every pixel's visible point
and the whole photon map) is not tiled: `render` runs its passes through one compiled program, several
passes a call (`integrators.sppm.passes_per_call`: about `sppm.CALL_SECONDS` of work each, from the previous
call's time), the progress bar counting passes and Ctrl-C checked between calls; on several devices
each pass's photons are split over them and the per-pixel photon statistics summed
(`jaxrt._devices.sppm_program`), on one device it is the one-device program (`integrators.sppm.steps`)
unchanged. The image does not depend on how the passes are grouped into calls.


Memory model
------------
The budget B is `memory` (bytes or "2G"), else JAXRT_MEMORY, else `default_budget()`: on a GPU 90 %
of what the device's allocator can still hand out (``memory_stats()``: bytes_limit − bytes_in_use)
plus the scene's arrays already there; on a CPU half the physical RAM (``os.sysconf``). It bounds
the renderer's arrays: the scene (its device arrays), one tile's working set and outputs, and the
host image buffers (H·W·12 bytes of RGB, 32 more per pixel with AOVs) plus the caller's `reserve`
(the CLI's image writers); on a GPU the host buffers are checked against half the host's RAM
instead. The Python/XLA runtime itself (about 0.5 GB) and compilation are not counted.

A tile of p pixels × s samples needs p·(s·a + b) bytes, with (a, b) = `tile_cost(scene)` an upper
bound of the compiled tile program's temporaries, outputs and code (`memory_analysis()`), fitted to
measurements of the shipped scenes (see `tile_cost`). `plan` picks the largest tile within the
budget; `compile_plan` compiles it and reads the compiled program's own `memory_analysis()`; should
that exceed the budget the tile is shrunk in proportion and recompiled, so what runs has been
measured to fit. A job whose scene and image alone leave no room for one ray sample is refused before any
work with an `InputError` that names --memory / JAXRT_MEMORY.

Tile shape
----------
All spp samples of a pixel stay in one tile when at least one 8×4 block of pixels (the integrators'
ray order, `integrators.sample_order`) fits that way; otherwise the samples are split into equal
batches (the last one shorter, its surplus slots inactive). Pixels go in full-width strips when a
strip of four rows fits, else in blocks of four rows by a multiple of eight columns; tiles are
balanced (equal sizes) and the last row and column of tiles are shifted back inside the image (their
overlap with the previous tile is computed again and not written twice), so no ray leaves the
image.

Identity with the untiled render
--------------------------------
Every random number of a tile is the one the whole-image render gives the same pixel and sample
(camera jitter and lens: `camera.uniform_at` at the pixel's global counter; path tracing: the path's
global index i·spp + j), and a pixel's samples and their secondary rays keep their relative order, so
the tile computes the same per-ray arithmetic. The image is then bit for bit the untiled render's
wherever the compiler evaluates that arithmetic the same way for both program shapes. On XLA:CPU
that holds with FMA contraction and YNNPACK reduction fusions off (``XLA_FLAGS=--xla_cpu_max_isa=AVX
--xla_cpu_experimental_ynn_fusion_type=``): then the test scenes and the shipped spheres, showcase,
cornell_area and dragon tile bit for bit (`tests/test_tiles.py` checks two scenes that way). With
the default flags XLA fuses each program shape differently, contracts a·b + c into FMAs where it
fuses, and YNNPACK associates small reductions by shape, so each ray's floats differ by a few ulps;
mostly that stays at rounding level, but it can flip a discrete decision (a shadow ray grazing an
edge, total internal reflection, a roulette draw). Measured at 96x72 against `frame`: spheres
max |Δ| 1.9e-5 (0.01 % of pixels beyond 1e-4 relative), dragon 2.7e-5, cornell_area (path, 8 spp)
5e-5 relative at most, showcase (glass) 0.4 % of pixels beyond 1 % (max |Δ| 0.04 on radiance up to
1.7); `tests/test_tiles.py` holds 99 % of pixels to 1e-4 relative. When a pixel's samples are split
into batches, the batches' partial means are added on the host in float32 in sample order: beyond
the above, |Δ| ≤ (2·spp + batches)·2⁻²⁴ of the pixel (first order; tested). Whitted scenes whose
ray tree overflows its slot budget (glass with a small ray_budget, see `integrators.whitted`) drop
branches per tile rather than per image. Tiles are not differentiable; differentiate
`integrators.frame`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import _config, _devices, glare, integrators
from jaxrt.camera import Window
from jaxrt.errors import InputError

__all__ = ["TIMED_PASSES", "Plan", "accumulate", "compile_plan", "default_budget", "format_bytes", "plan", "render", "tile_cost"]

# progressive passes on several devices timed before the tiles are assigned by cost: the least of two
# timings of a tile discards most of the time that other work on a shared host adds to one of them
TIMED_PASSES = 2
BLOCK_PIXELS = 32  # one 8x4 block of `integrators.sample_order`: the smallest tile that keeps all spp
# bytes per pixel of the host buffers: RGB float32; AOVs depth (f32), normal and albedo (3 f32), object_id (i32)
RGB_BYTES = 12
AOV_BYTES = 32


def format_bytes(n: float) -> str:
    """A size in binary units with three significant digits: 1.50 GiB, 812 MiB."""
    for unit, scale in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} B"


def _physical_ram() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def default_budget(device=None, scene=None) -> tuple[int, str]:
    """(bytes, where it comes from): the default memory budget for rendering on `device`.

    GPU (a device with ``memory_stats``): 90 % of bytes_limit − bytes_in_use, plus the bytes of
    `scene`'s arrays (already in use on the device when the scene is there). CPU: half the
    physical RAM.
    """
    device = device or jax.devices()[0]
    stats = None
    if device.platform != "cpu":
        try:
            stats = device.memory_stats()
        except Exception:  # a backend without allocator statistics
            stats = None
    if stats and "bytes_limit" in stats:
        free = stats["bytes_limit"] - stats.get("bytes_in_use", 0)
        return int(0.9 * free) + (_tree_bytes(scene) if scene is not None else 0), \
            f"90% of the free memory of {device.device_kind}"
    ram = _physical_ram()
    return ram // 2, f"half of the {format_bytes(ram)} of RAM"


def _leaf_bytes(x) -> int:
    if isinstance(x, jax.ShapeDtypeStruct):  # a scene of shapes (`jaxrt.scene.build`'s on_shapes): as its array
        return math.prod(x.shape) * x.dtype.itemsize
    return int(x.nbytes) if hasattr(x, "nbytes") else 0


def _tree_bytes(tree) -> int:
    return sum(_leaf_bytes(x) for x in jax.tree.leaves(tree))


def tile_cost(scene, aovs: bool = False) -> tuple[int, int]:
    """(bytes per ray sample, bytes per pixel): an upper bound of one tile's working memory, from the
    static shapes; a tile of p pixels × s samples needs p·(s·per_sample + per_pixel).

    Fitted to the compiled tile programs' `memory_analysis()` (temporaries + outputs + code) at two
    tiles of 65536 ray samples (256² pixels × 1 sample and 128² × 4), which separate the two terms,
    for the shipped scenes spheres, showcase, cornell_area, furnace, instances, dragon, textured and
    bunnies with both integrators and with and without AOVs (0 to 2 point lights, ray_budget 1 and
    2, triangle and two-level BVHs, area and environment lights). Measured per ray sample: Whitted
    212 (cornell_area: ray_budget 1, no point light) to 1139 (showcase: ray_budget 2, two lights),
    about ray_budget·(260 + 155·L) for L point lights (each slot carries its ray, two candidate
    children and L shadow rays); path tracing 389 (cornell_area) to 942 (showcase with AOVs), about
    400 + 250·L, 462 with furnace's environment light, and 37 to 170 more with AOVs (first-hit
    records). Whitted shadow rays that cross glass (`jaxrt.shading.shadows`, scenes with glass) add
    about 150 per ray-budget slot and point light (a scene with glass, ray_budget 2 and two lights:
    1450-1490 against 860-910 with opaque glass shadows). Per pixel: at most 25, 75 with AOVs. The
    constants below are those fits with a margin
    (every measurement is 10 to 95 % under its bound); `compile_plan` checks the compiled program
    against the budget, so a scene the fit does not cover still cannot overrun it.
    """
    L = int(scene.lights.count)
    if scene.settings.integrator == "path":
        per_sample = _P0 + _P1 * L + (_P_AOV if aovs else 0)
    else:
        glass = _W_GLASS * L if integrators.whitted.transmits(scene) else 0
        per_sample = scene.settings.ray_budget * (_W0 + _W1 * L + glass)
    return int(per_sample), int(_PIX + (_PIX_AOV if aovs else 0))


# the constants of `tile_cost` [bytes]; see its docstring
_W0, _W1, _W_GLASS = 300, 180, 250
_P0, _P1, _P_AOV = 520, 290, 48
_PIX, _PIX_AOV = 32, 64


@dataclasses.dataclass(frozen=True)
class Plan:
    """How one image is rendered.

    shape: (tile height, tile width, samples per tile), or None when the whole job runs as one
    `integrators.frame` call. steps: the tiles in render order, each ((row, col) where the tile's
    own pixels start, (row, col) of the window actually rendered, (first sample, sample count)).
    budget: bytes (per device); budget_source: where the budget came from; fixed: bytes of the scene
    and the host buffers (those of the host only where the devices are the CPU; there the scene once
    per device); cost: `tile_cost`'s (per sample, per pixel) bound; tile_bytes: the compiled
    program's measured temporaries, outputs and code, per device (0 until `compile_plan`). devices:
    the devices that share the steps (each call renders one step on each of them, in order:
    `jaxrt._devices`), or () for the default device alone (the one-device renderer). costs: the
    device seconds of each step, the least over the first `timed` progressive passes (`accumulate`
    with ``return_plan=True``), or None; once `timed` reaches TIMED_PASSES, later passes assign the
    steps to devices by longest processing time first (`jaxrt._devices.lpt`).
    """

    height: int
    width: int
    spp: int
    shape: tuple[int, int, int] | None
    steps: tuple
    budget: int
    budget_source: str
    fixed: int
    cost: tuple[int, int]
    tile_bytes: int = 0
    devices: tuple = ()
    costs: tuple | None = None
    timed: int = 0

    @property
    def tiles(self) -> int:
        return len(self.steps)

    @property
    def schedule(self) -> tuple[tuple[int, ...], ...] | None:
        """The steps of each device for passes after the first (`jaxrt._devices.lpt` of `costs`),
        or None without costs or devices."""
        if self.costs is None or not self.devices:
            return None
        return _devices.lpt(self.costs, len(self.devices))

    @property
    def device_count(self) -> int:
        return max(1, len(self.devices))

    @property
    def tile_room(self) -> int:
        """Bytes one tile's program may use: the budget less the fixed part, split between the
        devices where they share the host's RAM (virtual CPU devices)."""
        room = self.budget - self.fixed
        return room // self.device_count if _on_cpu(self.devices) else room


def _balanced(total: int, most: int, align: int) -> int:
    """A tile extent ≤ most that splits `total` into pieces of nearly equal size, a multiple of
    `align` where most ≥ align."""
    if most >= total:
        return total
    if most >= align:
        step = most // align * align
        n = -(-total // step)
        return min(step, -(-(-(-total // n)) // align) * align)
    return -(-total // -(-total // most))


def _tile_shape(h: int, w: int, spp: int, room: int, cost: tuple[int, int], max_rays: int | None):
    """The largest balanced tile (rows, columns, samples) of p pixels × s samples with
    p·(s·per_sample + per_pixel) ≤ room and p·s ≤ max_rays; None when not even one ray sample fits."""
    per_sample, per_pixel = cost
    max_rays = max_rays or h * w * spp

    def pixels(sb):
        return min(room // (sb * per_sample + per_pixel), max_rays // sb)

    block = min(h * w, BLOCK_PIXELS)
    if pixels(spp) >= block:
        sb = spp
    else:  # the most samples that still fit a block, in equal batches
        most = min((room // block - per_pixel) // per_sample, max_rays // block)
        if most < 1:
            most = 1
            if pixels(1) < 1:
                return None
        batches = -(-spp // most)
        sb = -(-spp // batches)
    px = min(pixels(sb), h * w)
    if px >= w * min(h, 4):
        return _balanced(h, min(h, px // w), 4), w, sb
    th = min(h, 4) if px >= min(h, 4) * min(w, 8) else 1
    return th, _balanced(w, max(1, px // th), 8), sb


def _steps(h: int, w: int, spp: int, shape) -> tuple:
    th, tw, sb = shape
    out = []
    for r in range(0, h, th):
        for c in range(0, w, tw):
            for s in range(0, spp, sb):
                out.append(((r, c), (min(r, h - th), min(c, w - tw)), (s, min(sb, spp - s))))
    return tuple(out)


def _on_cpu(devices) -> bool:
    return (devices[0] if devices else jax.devices()[0]).platform == "cpu"


def _resolve_budget(memory, scene, devices=()) -> tuple[int, str]:
    if memory is None or memory == "auto":
        env = _config.config().memory
        if env is not None:
            return env, "JAXRT_MEMORY"
        if len(devices) > 1 and not _on_cpu(devices):  # per device: the one with the least free memory
            # (of this process's devices: another host's allocator cannot be asked from here)
            return min((default_budget(d, scene) for d in _devices.local(devices)), key=lambda b: b[0])
        return default_budget(devices[0] if devices else None, scene=scene)
    if isinstance(memory, str):
        b = _config.parse_size(memory, "memory")
    else:
        b = int(memory)
    if b <= 0:
        raise InputError(f"memory={memory!r}: must be a positive size, e.g. 8G")
    return b, "the memory argument"


def plan(scene, *, memory: int | str | None = None, aovs: bool = False, max_tile_rays: int | None = None,
         reserve: int = 0, budget_source: str | None = None, devices: Any = None,
         devices_source: str = "devices=") -> Plan:
    """The tiles for rendering `scene` within `memory` (see the module docstring), before any
    compilation.

    Args:
        memory: the budget in bytes or as "2G"; None or "auto": JAXRT_MEMORY, else `default_budget`
            (on several GPUs that of the one with the least free memory). The budget is per device.
        aovs: the AOV buffers are needed too.
        max_tile_rays: also cap a tile at this many ray samples (the CLI's progress granularity).
        reserve: bytes of host memory the caller needs besides the image buffers (writers).
        budget_source: how to name the budget in errors (the CLI: "--memory").
        devices: the devices to spread the tiles over (`jaxrt._devices.select`): None or "all" every
            device of `jax.devices()`, an int N the first N, or a list of devices. On more than one
            device the image is always tiled, into at least max(32, 4·N) tiles (load balance).
        devices_source: how to name `devices` in errors (the CLI: "--devices ").

    Raises:
        InputError: the scene and the image leave no room for a single ray sample; bad `devices`.
    """
    devs = _devices.select(devices, devices_source)
    devs = devs if _devices.sharded(devs) else ()
    n_dev = max(1, len(devs))
    budget, source = _resolve_budget(memory, scene, devs)
    source = budget_source or source
    cam, st = scene.camera, scene.settings
    h, w, spp = cam.height, cam.width, st.spp
    scene_bytes = _tree_bytes(scene)
    host = h * w * (RGB_BYTES + (AOV_BYTES if aovs else 0)) + int(reserve)
    on_cpu = _on_cpu(devs)
    # virtual CPU devices share the host's RAM: the scene is there once per device, and the image once
    fixed = scene_bytes * (n_dev if on_cpu else 1) + (host if on_cpu else 0)
    cost = tile_cost(scene, aovs)
    what = f"{scene.source}: {w}x{h} at {spp} spp"
    if not on_cpu and host > _physical_ram() // 2:
        raise InputError(f"{what} needs {format_bytes(host)} of host memory for the image, more than half "
                         f"of the {format_bytes(_physical_ram())} of RAM; render a smaller image")
    room = budget - fixed
    tile_room = room // n_dev if on_cpu else room
    if max_tile_rays is not None:
        max_tile_rays = max(1, int(max_tile_rays))
    if devs:
        # enough tiles that every device gets several, spread over the image (`_render_tiles`)
        # (not below one 8x4 block of all spp: a small image keeps its samples together)
        cap = -(-h * w * spp // max(_devices.MIN_TILES, _devices.TILES_PER_DEVICE * n_dev))
        cap = max(cap, min(h * w, BLOCK_PIXELS) * spp)
        max_tile_rays = min(max_tile_rays or cap, cap)
    elif h * w * (spp * cost[0] + cost[1]) <= room and (max_tile_rays is None or h * w * spp <= max_tile_rays):
        return Plan(h, w, spp, None, (((0, 0), (0, 0), (0, spp)),), budget, source, fixed, cost)
    shape = _tile_shape(h, w, spp, tile_room, cost, max_tile_rays) if tile_room > 0 else None
    if shape is None:
        each = f" on each of {n_dev} devices" if devs else ""
        raise InputError(
            f"{what} needs at least {format_bytes(fixed + sum(cost) * (n_dev if on_cpu else 1))} ({format_bytes(scene_bytes)} for the "
            f"scene{each}, {format_bytes(host)} for the image{' on the host' if not on_cpu else ''} and its "
            f"writers, {format_bytes(sum(cost))} for one ray sample{each}) but the memory budget is "
            f"{format_bytes(budget)} ({source}); raise it with --memory or JAXRT_MEMORY")
    return Plan(h, w, spp, shape, _steps(h, w, spp, shape), budget, source, fixed, cost, devices=devs)


def _compiled_bytes(compiled) -> int:
    """Temporaries, outputs and code/constants of a compiled program (its arguments, the scene, are
    counted in `Plan.fixed`)."""
    m = compiled.memory_analysis()
    if m is None:  # a backend without memory analysis: trust the bound
        return 0
    return int(m.temp_size_in_bytes + m.output_size_in_bytes + m.generated_code_size_in_bytes)


def _window(shape, origin, samples) -> Window:
    th, tw, sb = shape
    i32 = jnp.int32
    return Window(i32(origin[0]), i32(origin[1]), i32(samples[0]), i32(samples[1]), th, tw, sb)


def _compile_tile(scene, p: Plan, aovs: bool):
    if p.devices:  # the sharded program: its memory analysis is that of one device's share
        zeros = _devices.put_rows(np.zeros((len(p.devices), 2), np.int32), p.devices)
        return _devices.program(p.devices, p.shape, aovs).lower(scene, zeros, zeros).compile()
    return integrators.tile.lower(scene, _window(p.shape, (0, 0), (0, p.shape[2])), aovs=aovs).compile()


def compile_plan(scene, p: Plan, aovs: bool = False) -> Plan:
    """Compile the plan's program (`integrators.frame`, or `integrators.tile` at the plan's tile
    shape, or on several devices the sharded tile program of `jaxrt._devices`) and measure it
    (`memory_analysis()`); while it exceeds the budget, shrink the tile in proportion and compile
    again. Returns the plan that runs, with `tile_bytes` measured.

    Ahead-of-time compilation shares JAX's cache with calls, so the render's own calls compile
    nothing again, and a `frame` compiled before costs nothing here. For a plan on several devices
    `scene` should be already replicated over them (`_devices.replicate`), as `render` does.

    A plan already measured (`tile_bytes` > 0, a plan this function returned) is returned as it is:
    a scene of the same shapes compiles the same program (the viewer renders every frame so).

    Raises:
        InputError: not even a one-ray tile fits.
    """
    if p.tile_bytes > 0:
        return p
    room = p.tile_room
    h, w, spp = p.height, p.width, p.spp
    if p.shape is None:
        need = _compiled_bytes(integrators.frame.lower(scene, aovs=aovs).compile())
        if need <= room:
            return dataclasses.replace(p, tile_bytes=need)
        # the bound under-estimated this scene: tiles sized by the measurement
        scale = 0.9 * room / need
        shape = _tile_shape(h, w, spp, room, tuple(int(c / scale) + 1 for c in p.cost), None)
        p = dataclasses.replace(p, shape=shape, steps=_steps(h, w, spp, shape) if shape else ())
    need = 0
    for _ in range(4):
        if p.shape is None:
            break
        th, tw, sb = p.shape
        need = _compiled_bytes(_compile_tile(scene, p, aovs))
        if need <= room:
            return dataclasses.replace(p, tile_bytes=need)
        scale = 0.9 * room / need
        if th * tw * sb <= 1:
            break
        cost = tuple(int(c / scale) + 1 for c in p.cost)
        shape = _tile_shape(h, w, spp, room, cost, max(1, int(th * tw * sb * scale)))
        p = dataclasses.replace(p, shape=shape, steps=_steps(h, w, spp, shape) if shape else (), cost=cost)
    raise InputError(f"{p.width}x{p.height} at {p.spp} spp: the smallest tile tried needs {format_bytes(need)}, "
                     f"more than the {format_bytes(max(room, 0))} the memory budget ({format_bytes(p.budget)}, "
                     f"{p.budget_source}) leaves after the scene and image; raise it with --memory or JAXRT_MEMORY")


def _check_finite(part: np.ndarray, where: str) -> None:
    if not np.isfinite(part).all():  # a renderer bug, never bad input
        raise RuntimeError(f"{where}: the render contains NaN/Inf pixels")


def render(scene, *, memory: int | str | None = None, aovs: bool = False, progress: Any = False,
           max_tile_rays: int | None = None, reserve: int = 0, budget_source: str | None = None,
           should_stop: Callable[[], bool] | None = None, use_plan: Plan | None = None, devices: Any = None,
           devices_source: str = "devices="):
    """Render `scene` within a memory budget, in tiles when it does not fit in one piece, spread
    over `devices` (default: every device of `jax.devices()`).

    Args:
        scene: a `jaxrt.scene.Scene`.
        memory, aovs, max_tile_rays, reserve, budget_source, devices, devices_source: as for `plan`
            (`devices` is ignored with `use_plan`, which names its own).
        progress: False; True for a tqdm bar on stderr; or a tqdm-like object (``total``,
            ``update(n)``, ``set_description_str``) that this call drives.
        should_stop: called before each tile; when it returns True a KeyboardInterrupt is raised
            there (a Ctrl-C caught by another thread, as the CLI does).
        use_plan: a `Plan` from `plan` to use instead of planning again.

    The scene's glare (`Scene.glare`; `jaxrt.glare`), if any, is applied to the assembled image (not
    to the AOVs) after the last tile.

    Returns:
        (H, W, 3) float32 numpy image of linear radiance, or (image, AOV dict of numpy arrays) with
        `aovs`: as `integrators.frame` (see the module docstring for how equal).

    Raises:
        InputError: the job cannot fit one tile in the budget (before any rendering).
        KeyboardInterrupt: between tiles, from Ctrl-C or `should_stop`.
    """
    # glare is applied to the assembled image below; the compiled programs take the scene without it.
    # It runs after the tiles, as the writers do: the budget keeps room for the larger of the two.
    post, scene = scene.glare, scene.without_glare()
    if scene.settings.integrator == "sppm":
        devs = use_plan.devices if use_plan is not None else _devices.select(devices, devices_source)
        devs = devs if devs and _devices.sharded(devs) else ()
        _, step = check_passes(scene, memory=memory, aovs=aovs, reserve=max(int(reserve), glare.work_bytes(
            scene.camera.height, scene.camera.width, post)), budget_source=budget_source, devices=devs)
        out = _render_passes(scene, step, aovs, progress, should_stop, devs)
        if post is None:
            return out
        img, aov = out if aovs else (out, None)
        img = np.asarray(glare.apply(img, post))
        return (img, aov) if aovs else img
    p = use_plan or plan(scene, memory=memory, aovs=aovs, max_tile_rays=max_tile_rays,
                         reserve=_reserve(reserve, scene, post), budget_source=budget_source, devices=devices,
                         devices_source=devices_source)
    bar, own = progress, False
    if progress is True:
        from tqdm import tqdm

        bar, own = tqdm(total=p.tiles, unit="tile", desc="compiling", leave=False, dynamic_ncols=True), True
    elif progress is not False and progress is not None:
        bar.total = p.tiles
    try:
        if bar:
            bar.set_description_str("compiling")
        where = f"{scene.source}"
        if p.devices:  # every device holds the whole scene
            scene = _devices.replicate(scene, p.devices)
        p = compile_plan(scene, p, aovs)
        if bar:
            bar.total = p.tiles
            bar.set_description_str("rendering")
        if p.shape is None:
            if should_stop is not None and should_stop():
                raise KeyboardInterrupt
            out = integrators.frame(scene, aovs=aovs)
            img, aov = out if aovs else (out, None)
            img = np.asarray(img)
            _check_finite(img, where)
            if bar:
                bar.update(1)
            out = img if not aovs else (img, {k: np.asarray(v) for k, v in aov.items()})
        else:
            out = _render_tiles(scene, p, aovs, bar, should_stop, where)
        if post is None:
            return out
        img, aov = out if aovs else (out, None)
        img = np.asarray(glare.apply(img, post))  # the whole image: light crosses tile borders
        return (img, aov) if aovs else img
    finally:
        if own:
            bar.close()


def _reserve(reserve: int, scene, post) -> int:
    # the glare post-process runs after the tiles, as the writers do: room for the larger of the two
    return max(int(reserve), glare.work_bytes(scene.camera.height, scene.camera.width, post))


def compile_ahead(shapes, *, memory: int | str | None = None, aovs: bool = False, max_tile_rays: int | None = None,
                  reserve: int = 0, devices: Any = None) -> threading.Thread | None:
    """Start compiling, in a thread, the program that `render(scene, ...)` with these arguments will
    run, from `shapes`: the scene before its BVH is built (`jaxrt.scene.build`'s on_shapes, whose
    tree arrays are `jax.ShapeDtypeStruct`s). Returns the thread (join it before rendering), or None
    for photon mapping (its pass program is compiled by `check_passes`). On several devices the thread
    only plans: their program takes the scene replicated over them (`_devices.replicate`).

    XLA compiles with the GIL released, so the host's BVH build runs beside it (Wald 2007's binned
    SAH build of the full dragon takes seconds, as long as the frame's compilation on a small CPU).
    The render then plans and compiles as always: a scene of the same shapes finds the compiled
    program (`jaxrt.programs.cached_jit` keeps it per shapes), so nothing compiles twice and the
    images are those of a render without this. Where the built scene differs in a shape after all,
    the render compiles its own program, and the one compiled here is unused. Errors are left to the
    render to raise and report.
    """
    if shapes.settings.integrator == "sppm":
        return None
    post, shapes = shapes.glare, shapes.without_glare()

    def work():
        try:
            p = plan(shapes, memory=memory, aovs=aovs, max_tile_rays=max_tile_rays,
                     reserve=_reserve(reserve, shapes, post), devices=devices)
            if not p.devices:
                compile_plan(shapes, p, aovs)
        except Exception:  # noqa: BLE001 -- see the docstring
            pass

    t = threading.Thread(target=work, name="jaxrt-compile", daemon=True)
    t.start()
    return t


def check_passes(scene, *, memory: int | str | None = None, aovs: bool = False, reserve: int = 0,
                 budget_source: str | None = None, devices: tuple = ()) -> tuple[int, Callable]:
    """(bytes, compiled pass): the bytes one pass of a progressive whole-frame integrator (`integrators.sppm`) needs, checked
    against the memory budget before any pass runs: the scene, the per-pixel statistics, the compiled
    pass's temporaries and outputs (`memory_analysis()` of the program compiled for the scene's
    shapes; the statistics are described by `jax.eval_shape`, never allocated) and the host image.
    Such a pass cannot be tiled (every visible point meets the whole photon map), so a frame that does
    not fit is refused here with one line instead of running out of memory. The program measured is
    the one the passes run (`steps(scene, state, count)`), so checking costs no extra compilation. With
    `devices` (several, `jaxrt._devices.select`) that is the sharded pass (`jaxrt._devices.sppm_program`,
    photons split over the devices), called with the scene and state replicated over them; the scene,
    statistics and pass are then needed on each device, and on a CPU (virtual devices sharing the
    host's RAM) once per device.

    Raises:
        InputError: the pass does not fit in the budget.
    """
    budget, source = _resolve_budget(memory, scene, devices)
    source = budget_source or source
    sppm = integrators.sppm
    sppm.check(scene)
    state = jax.eval_shape(sppm.start, scene)
    cam = scene.camera
    host = cam.height * cam.width * (RGB_BYTES + (AOV_BYTES if aovs else 0)) + int(reserve)
    state_bytes = sum(int(np.prod(x.shape)) * x.dtype.itemsize for x in jax.tree_util.tree_leaves(state))
    copies = len(devices) if devices and _on_cpu(devices) else 1  # virtual CPU devices share the RAM
    fixed = copies * (_tree_bytes(scene) + state_bytes) + host
    each = f" on {len(devices)} devices" if devices else ""
    what = (f"{scene.source}: {cam.width}x{cam.height}, {sppm.photons_per_pass(scene)} photons per pass "
            f"(integrator sppm){each}")
    need, compiled = fixed, None
    if fixed <= budget:  # else refused without compiling: the arrays alone are too large
        if devices:
            compiled = _devices.sppm_program(tuple(devices)).lower(scene, state, sppm.pass_count(1)).compile()
        else:
            compiled = sppm.steps.lower(scene, state, sppm.pass_count(1)).compile()
        need += copies * _compiled_bytes(compiled)
    if need > budget:
        raise InputError(f"{what} needs {format_bytes(need)} per pass (a pass is one whole-frame program, not "
                         f"tiled) but the memory budget is {format_bytes(budget)} ({source}); render a smaller "
                         f"image, use fewer photons (--photons) or raise the budget with --memory or JAXRT_MEMORY")
    return need, compiled


def _render_passes(scene, step, aovs, progress, should_stop, devices=()):
    """A progressive integrator's image (`integrators.sppm`): settings.spp passes of one compiled
    whole-frame program, `sppm.passes_per_call` of them a call (1 first, then as many as the last
    call's time per pass fits in `sppm.CALL_SECONDS`), the progress bar counting passes and Ctrl-C
    (`should_stop`) checked between calls, `step` the compiled program (`check_passes`: ``step(scene,
    state, count)``). Its working set is one pass's (visible points and photons; the passes of a call
    run one after the other), checked against the budget before. With several `devices`, `step` is the sharded pass
    and the scene and statistics are replicated over them; the image is read from this process's
    first copy of the (replicated) statistics."""
    sppm = integrators.sppm
    passes = scene.settings.spp
    bar, own = progress, False
    if progress is True:
        from tqdm import tqdm

        bar, own = tqdm(total=passes, unit="pass", desc="compiling", leave=False, dynamic_ncols=True), True
    elif progress is not False and progress is not None:
        bar.total = passes
        bar.unit = "pass"
    try:
        if bar:
            bar.set_description_str("compiling")
        state = sppm.start(scene)
        run_scene = scene
        if devices:
            run_scene, state = _devices.replicate(scene, devices), _devices.replicate(state, devices)
        done, per_pass = 0, float("nan")
        while done < passes:
            if should_stop is not None and should_stop():
                raise KeyboardInterrupt
            count = sppm.passes_per_call(per_pass, passes - done)
            t0 = time.perf_counter()
            state = step(run_scene, state, sppm.pass_count(count))
            state.passes.block_until_ready()
            per_pass = (time.perf_counter() - t0) / count
            done += count
            if bar:
                bar.set_description_str("rendering")
                bar.update(count)
        if devices:  # every device holds the same statistics: this process's first copy
            state = jax.tree.map(lambda x: x.addressable_data(0) if isinstance(x, jax.Array) else x, state)
        img = np.asarray(state.image)
        _check_finite(img, f"{scene.source}")
        if not aovs:
            return img
        return img, {k: np.asarray(v) for k, v in sppm.first_aovs(scene).items()}
    finally:
        if own:
            bar.close()


def accumulate(scene, state: integrators.Accumulation | None = None, *, devices: Any = None,
               memory: int | str | None = None, use_plan: Plan | None = None, return_plan: bool = False):
    """`jaxrt.integrators.accumulate` (one more progressive pass of `settings.spp` jittered path-traced
    samples per pixel, pass P with random stream P) with the pass split into tiles over `devices`.

    On the default device alone (`devices=1`, or a host with one device) this is
    `integrators.accumulate` itself, bit for bit. On several devices (default: all of
    `jax.devices()`) the pass is planned as `render` plans an image (`plan`: at least max(32, 4·N)
    tiles, tile k·N + d on device d, the memory budget per device) and each call runs one tile of the
    pass on each device (`jaxrt._devices.pass_program`, the pass index traced, so every pass reuses
    one compiled program); the tiles are gathered and added on the host. A tile computes each path
    with the random numbers of the same path of the whole pass, so the pass equals the one-device
    pass up to the rounding of a differently compiled program, as tiled renders do (the tolerance
    is tested on 4 virtual CPU devices); on any N ≥ 2 devices the passes are equal bit for bit.
    The tiles are sized by `tile_cost`'s bound; unlike `render`, the compiled pass program is not
    measured against the budget (`compile_plan` would compile the one-pass tile program as well).

    Load balance: the first TIMED_PASSES passes of a plan (`Plan.timed`) run the tiles interleaved
    (tile k·D + d, rotated by one device each timed pass), each a one-device program dispatched to
    its device as soon as the device's previous tile is ready, and time each tile
    (`jaxrt._devices.timed`); with
    ``return_plan=True`` the plan comes back with the least time of each tile so far, and passes given
    a plan timed TIMED_PASSES times run each device's list of
    tiles (longest processing time first over the costs, `Plan.schedule`) in one call
    (`jaxrt._devices.queue_program`, a second compiled program; each device holds its list's tile
    outputs, th·tw·12 bytes each, until the call ends). Tiles are independent, so the
    assignment does not change the pixels: passes under any two schedules are equal bit for bit,
    and equal the interleaved pass within the ulps of two compiled modules (tested).

    Args:
        scene: a path-traced `jaxrt.scene.Scene` (`settings.integrator == "path"`).
        state: the accumulation so far, or None to start.
        devices, memory: as for `plan`; use_plan: a `plan` of this scene to reuse across passes.
        return_plan: also return the plan, with the tile costs this pass measured (a timed pass).

    Returns:
        The accumulation with this pass added; with `return_plan`, (accumulation, plan).

    Raises:
        InputError: a scene that is not path-traced; bad `devices` or `memory`.
    """
    if scene.settings.integrator != "path":
        raise InputError(f"{scene.source}: progressive passes need integrator = \"path\", not "
                         f"{scene.settings.integrator!r}")
    p = use_plan or plan(scene, memory=memory, devices=devices)
    if p.costs is not None and len(p.costs) != p.tiles:
        raise ValueError(f"use_plan: {len(p.costs)} tile costs for a plan of {p.tiles} tiles")
    if not p.devices:
        out = integrators.accumulate(scene, state)
        return (out, p) if return_plan else out
    cam, spp = scene.camera, scene.settings.spp
    if state is None:
        state = integrators.Accumulation(jnp.zeros((cam.height, cam.width, 3)), jnp.asarray(0), jnp.asarray(0))
    scene = _devices.replicate(scene, p.devices)
    if p.timed < TIMED_PASSES and jax.process_count() > 1:  # a device's time is seen by its own process only
        img = _render_tiles(scene, p, False, None, None, f"{scene.source}", pass_index=int(state.passes))
    elif p.timed < TIMED_PASSES:
        img, costs = _render_timed(scene, p, int(state.passes), f"{scene.source}", rotate=p.timed)
        if p.costs is not None:
            costs = tuple(min(a, b) for a, b in zip(p.costs, costs))
        p = dataclasses.replace(p, costs=costs, timed=p.timed + 1)
    else:
        img = _render_queue(scene, p, int(state.passes), f"{scene.source}")
    out = integrators.Accumulation(state.total + jnp.asarray(img) * spp, state.count + spp, state.passes + 1)
    return (out, p) if return_plan else out


def _own_pixels(r, c, r0, c0, th, tw, h, w):
    """A tile's own pixels, from its nominal origin (r, c) to the next tile's or the image's edge:
    (rows, cols) of the image and the same window in the rendered tile, which starts at (r0, c0)."""
    rows, cols = slice(r, min(r + th, h)), slice(c, min(c + tw, w))
    return rows, cols, (slice(r - r0, r - r0 + rows.stop - r), slice(c - c0, c - c0 + cols.stop - c))


def _place(img, steps, th, tw, parts, where):
    """Write tiles (`parts`, one per step of `steps`) into `img`: each tile's own pixels, from its
    nominal origin to the next tile's or the image's edge, a later sample batch added to the earlier."""
    h, w = img.shape[:2]
    for ((r, c), (r0, c0), (s0, _)), part in zip(steps, parts):
        rows, cols, local = _own_pixels(r, c, r0, c0, th, tw, h, w)
        part = _devices.to_host(part)[local]
        _check_finite(part, where)
        if s0 == 0:
            img[rows, cols] = part
        else:
            img[rows, cols] += part


def _render_timed(scene, p: Plan, pass_index: int, where, rotate: int = 0):
    """One progressive pass with tile k·D + d on device (d + rotate) mod D (the interleaved assignment),
    each tile a one-device program call on its device, timed (`_devices.timed`): (image, seconds per
    step)."""
    n = len(p.devices)
    run = _devices.tile_pass_program(p.shape)
    copies = _devices.views(scene, p.devices)
    lists = [list(range((d - rotate) % n, p.tiles, n)) for d in range(n)]
    pi = np.int32(pass_index)
    def args(d, i, count=None):
        (_, origin, (s0, c)) = p.steps[i]
        return copies[d], np.array(origin, np.int32), np.array((s0, c if count is None else count), np.int32), pi

    # compile before the clock starts (once per device and process: a program is compiled for its
    # device; the jit cache keeps it for later first passes): one tile of no samples on each device,
    # whose rays start inactive, so it costs little once compiled
    jax.block_until_ready([run(*args(d, x[0], 0)) for d, x in enumerate(lists) if x])
    calls = [[functools.partial(run, *args(d, i)) for i in x] for d, x in enumerate(lists)]
    # one tile in flight per device: the memory budget holds one tile's working set per device
    done = _devices.timed(calls, depth=1)
    tiles, costs = [None] * p.tiles, [0.0] * p.tiles
    for x, res in zip(lists, done):
        for i, (tile, sec) in zip(x, res):
            tiles[i], costs[i] = tile, sec
    th, tw, _ = p.shape
    img = np.empty((p.height, p.width, 3), np.float32)
    _place(img, p.steps, th, tw, tiles, where)
    return img, tuple(costs)


def _render_queue(scene, p: Plan, pass_index: int, where):
    """One progressive pass with each device rendering its `Plan.schedule` list in one call
    (`_devices.queue_program`); the tiles are written into the image in step order, as one device
    would (sample batches are added in the same order)."""
    lists = p.schedule
    origins, samples, counts, k = _devices.queue_arrays(p.steps, lists)
    run = _devices.queue_program(p.devices, p.shape, k)
    put = functools.partial(_devices.put_rows, devices=p.devices)
    out = _devices.gather(run(scene, put(origins), put(samples), put(counts), np.int32(pass_index)))
    tiles = [None] * p.tiles
    for d, x in enumerate(lists):
        for j, i in enumerate(x):
            tiles[i] = out[d, j]
    th, tw, _ = p.shape
    img = np.empty((p.height, p.width, 3), np.float32)
    _place(img, p.steps, th, tw, tiles, where)
    return img


def _render_tiles(scene, p: Plan, aovs, bar, should_stop, where, pass_index: int | None = None):
    """The plan's steps, one call at a time: on one device one tile a call (`integrators.tile`); on
    D devices D consecutive steps a call, step k·D + d on device d (`_devices.program`), so each
    device's tiles are interleaved with the others' over the whole image and the tiles of one call
    are neighbours, of similar cost (glass, sky), which keeps a call's slowest device close to the
    others. The host writes the tiles into the image in step order either way, so sample batches
    are added in the same order as on one device."""
    h, w = p.height, p.width
    th, tw, _ = p.shape
    img = np.empty((h, w, 3), np.float32)
    aov_out: dict[str, np.ndarray] | None = None
    n = len(p.devices) if p.devices else 1
    run = _devices.program(p.devices, p.shape, aovs) if p.devices else None
    extra = ()
    if pass_index is not None:  # a progressive path-tracing pass (`accumulate`, several devices)
        run, extra = _devices.pass_program(p.devices, p.shape), (np.int32(pass_index),)
    for k in range(0, p.tiles, n):
        if should_stop is not None and should_stop():
            raise KeyboardInterrupt
        steps = p.steps[k:k + n]
        # one call at a time: the next is dispatched only after this one is on the host, so at most
        # one tile's working set exists per device (asynchronous dispatch could otherwise queue several)
        if run is None:
            (_, (r0, c0), (s0, count)), = steps
            out = integrators.tile(scene, _window(p.shape, (r0, c0), (s0, count)), aovs=aovs)
            parts = [out if aovs else (out, None)]
        else:
            out = run(scene, *(_devices.put_rows(a, p.devices) for a in _devices.round_arrays(steps, n)), *extra)
            # the one gather of this call's tiles: each device's shard comes to the host (to every
            # host's, when the devices span several)
            img_d, aov_d = _devices.gather(out if aovs else (out, None))
            parts = [(img_d[j], {key: v[j] for key, v in aov_d.items()} if aovs else None)
                     for j in range(len(steps))]
        for ((r, c), (r0, c0), (s0, _)), (part, part_aov) in zip(steps, parts):
            rows, cols, local = _own_pixels(r, c, r0, c0, th, tw, h, w)
            part = _devices.to_host(part)[local]
            _check_finite(part, where)
            if s0 == 0:
                img[rows, cols] = part
            else:
                img[rows, cols] += part
            if aovs and s0 == 0:  # AOVs are those of each pixel's first sample
                if aov_out is None:
                    aov_out = {key: np.empty((h, w) + v.shape[2:], v.dtype) for key, v in part_aov.items()}
                for key, v in part_aov.items():
                    aov_out[key][rows, cols] = np.asarray(v)[local]
        if bar:
            bar.update(len(steps))
    return (img, aov_out) if aovs else img
