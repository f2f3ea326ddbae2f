"""`jaxrt.render`: the compiled frame function and its trace/shade halves.

The jitted functions below take the whole `Scene` pytree as an argument. Its static parts
(resolution, spp, max depth, ray budget, the set of BRDF models, array shapes) form the compile
key; every value (material parameters, δ, lights, camera, background, vertices) is traced, so
changing any of them re-runs the compiled frame without recompiling.
"""

from __future__ import annotations

import os
from typing import Any

import jax
from jaxtyping import Array, Float

from jaxrt import integrators


def _frame(scene, aovs: bool = False):
    # the integrator is a static setting, so this branch is resolved at trace time
    if scene.settings.integrator == "path":
        from jaxrt import path

        return path.render(scene, aovs=aovs)
    return integrators.whitted(scene, aovs=aovs)


# One compiled function per (scene structure, aovs); reused across calls.
frame = jax.jit(_frame, static_argnames=("aovs",))
trace = jax.jit(integrators.trace)
shade = jax.jit(integrators.shade, static_argnames=("aovs",))


def _as_scene(scene: Any, overrides=None):
    from jaxrt import scene as _scene

    if isinstance(scene, _scene.Scene):
        if overrides:
            raise TypeError("overrides apply only when rendering a scene file or name")
        return scene
    if isinstance(scene, (str, os.PathLike, dict)):
        return _scene.load(scene, overrides=overrides)
    raise TypeError(f"expected a Scene, a scene file path or a shipped scene name, got {type(scene).__name__}")


def render(scene: Any, *, aovs: bool = False, overrides: dict | None = None):
    """Render a scene with its integrator.

    Args:
        scene: a `jaxrt.scene.Scene`, a scene file path, or a shipped scene name ("spheres").
        aovs: also return a dict of AOVs (depth, normal, albedo, object_id; see
            `jaxrt.integrators.shade`).
        overrides: for a path/name, values applied before validation, e.g. {"camera.width": 64}.

    Returns:
        (H, W, 3) float32 linear RGB radiance, or (image, aovs dict) with `aovs=True`.
        Differentiable (reverse mode: jax.grad, jax.vjp) with respect to material parameters and light
        positions/intensities.
    """
    scene = _as_scene(scene, overrides)
    return frame(scene, aovs=aovs)


def gbuffer(scene: Any) -> "integrators.GBuffer":
    """Trace once: the ray tree of `scene` for re-shading with `reshade` (fitting)."""
    return trace(_as_scene(scene))


def reshade(gb: "integrators.GBuffer", scene, *, aovs: bool = False) -> Float[Array, "H W 3"]:
    """Shade a cached G-buffer with the scene's current materials and lights (differentiable)."""
    return shade(gb, scene, aovs=aovs)


# `import jaxrt.render` binds the *module* to the attribute `jaxrt.render`, shadowing the package's
# lazy `__getattr__`; making the module callable keeps `jaxrt.render(scene)` working either way.
import sys as _sys
import types as _types


class _CallableModule(_types.ModuleType):
    def __call__(self, scene: Any, **kwargs):
        return render(scene, **kwargs)


_sys.modules[__name__].__class__ = _CallableModule
