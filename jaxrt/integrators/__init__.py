"""Integrators: Whitted ray tracing, path tracing and stochastic progressive photon mapping, behind one
registry.

`REGISTRY` maps each integrator's name (the `[render] integrator` of scene files and
`jaxrt render --integrator`) to its frame function `render(scene, aovs=False, window=None)`; scene
validation and the CLI read the names from here. `frame` is the one compiled entry point for a whole
image: it dispatches on the scene's (static) integrator setting. `tile` is the compiled entry point
for one tile of an image (a `Window`: a rectangle of pixels and a run of their samples), the unit
that `jaxrt.render_tiles` schedules to render any image within a memory budget.

The jitted functions take the whole `Scene` pytree as an argument. Its static parts (resolution,
spp, max depth, ray budget, integrator, the set of BRDF models, array shapes) form the compile key;
every value (material parameters, δ, lights, camera, background, vertices) is traced, so changing
any of them re-runs the compiled frame without recompiling. A tile's extents (rows, columns,
samples) are static too, its origin and sample count are traced: one compiled tile serves every tile
of an image.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

from jaxrt.programs import cached_jit
from jaxrt.camera import Window
from jaxrt.integrators import path, sppm, whitted
from jaxrt.integrators.common import sample_order
from jaxrt.integrators.path import Accumulation, accumulate
from jaxrt.integrators.whitted import GBuffer

# name -> (frame function, one-line description); the first is the default
REGISTRY: dict[str, tuple[Callable, str]] = {
    "whitted": (whitted.whitted, "Whitted ray tracing: point lights, shadows, mirrors, glass (default)"),
    "path": (path.render, "path tracing with next-event estimation and MIS: area and environment lights"),
    "sppm": (sppm.render, "stochastic progressive photon mapping: caustics from point and area lights; "
                          "spp = passes"),
}


def names() -> tuple[str, ...]:
    """The registered integrator names, default first."""
    return tuple(REGISTRY)


def _frame(scene, aovs: bool = False):
    # the integrator is a static setting, so the choice is made at trace time
    return REGISTRY[scene.settings.integrator][0](scene, aovs=aovs)


def _tile(scene, window: Window, aovs: bool = False):
    # the window's extents are static fields of its pytree, so they join the compile key
    return REGISTRY[scene.settings.integrator][0](scene, aovs=aovs, window=window)


# One compiled function per (scene structure, aovs); reused across calls.
# `frame`, `tile`, `trace` and `shade` keep their traced programs on disk (`jaxrt.programs.cached_jit`): a
# new process with the same scene structure skips tracing as well as compilation.
frame = cached_jit(_frame, name="integrators.frame", static_argnames=("aovs",))
#: One tile: `tile(scene, window, aovs=False)` -> the window's share of the image, Σ over the
#: window's samples / spp, (window height, width, 3) (and with aovs the AOVs of those pixels), from
#: the whole image's random numbers: `frame`'s pixels when the window holds all spp samples, up to
#: how the compiler rounds the two program shapes (`jaxrt.render_tiles`); one compilation per
#: (scene structure, window extents, aovs).
tile = cached_jit(_tile, name="integrators.tile", static_argnames=("aovs",))
trace = cached_jit(whitted.trace, name="integrators.trace")
shade = cached_jit(whitted.shade, name="integrators.shade", static_argnames=("aovs",))

__all__ = [
    "REGISTRY", "Accumulation", "GBuffer", "Window", "accumulate", "frame", "names", "path", "sample_order",
    "shade", "sppm", "tile", "trace", "whitted",
]
