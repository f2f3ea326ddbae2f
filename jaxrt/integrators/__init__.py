"""Integrators: Whitted ray tracing and path tracing, behind one registry.

`REGISTRY` maps each integrator's name (the `[render] integrator` of scene files and
`jaxrt render --integrator`) to its frame function `render(scene, aovs=False)`; scene validation
and the CLI read the names from here. `frame` is the one compiled entry point: it dispatches on the
scene's (static) integrator setting.

The jitted functions take the whole `Scene` pytree as an argument. Its static parts (resolution,
spp, max depth, ray budget, integrator, the set of BRDF models, array shapes) form the compile key;
every value (material parameters, δ, lights, camera, background, vertices) is traced, so changing
any of them re-runs the compiled frame without recompiling.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

from jaxrt.integrators import path, whitted
from jaxrt.integrators.common import sample_order
from jaxrt.integrators.path import Accumulation, accumulate
from jaxrt.integrators.whitted import GBuffer

# name -> (frame function, one-line description); the first is the default
REGISTRY: dict[str, tuple[Callable, str]] = {
    "whitted": (whitted.whitted, "Whitted ray tracing: point lights, shadows, mirrors, glass (default)"),
    "path": (path.render, "path tracing with next-event estimation and MIS: area and environment lights"),
}


def names() -> tuple[str, ...]:
    """The registered integrator names, default first."""
    return tuple(REGISTRY)


def _frame(scene, aovs: bool = False):
    # the integrator is a static setting, so the choice is made at trace time
    return REGISTRY[scene.settings.integrator][0](scene, aovs=aovs)


# One compiled function per (scene structure, aovs); reused across calls.
frame = jax.jit(_frame, static_argnames=("aovs",))
trace = jax.jit(whitted.trace)
shade = jax.jit(whitted.shade, static_argnames=("aovs",))

__all__ = [
    "REGISTRY", "Accumulation", "GBuffer", "accumulate", "frame", "names", "path", "sample_order", "shade",
    "trace", "whitted",
]
