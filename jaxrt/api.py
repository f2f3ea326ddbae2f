"""The top-level entry points: render a scene (a `Scene`, a scene file or a shipped scene's name),
or trace it once and re-shade it (fitting)."""

from __future__ import annotations

import os
from typing import Any

from jaxtyping import Array, Float

from jaxrt import glare, integrators, render_tiles
from jaxrt import scene as _scene


def _as_scene(scene: Any, overrides=None):
    if isinstance(scene, _scene.Scene):
        if overrides:
            raise TypeError("overrides apply only when rendering a scene file or name")
        return scene
    if isinstance(scene, (str, os.PathLike, dict)):
        return _scene.load(scene, overrides=overrides)
    raise TypeError(f"expected a Scene, a scene file path or a shipped scene name, got {type(scene).__name__}")


def render(scene: Any, *, aovs: bool = False, overrides: dict | None = None, memory: int | str | None = None,
           progress: bool = False, devices: Any = None):
    """Render a scene with its integrator.

    Args:
        scene: a `jaxrt.scene.Scene`, a scene file path, or a shipped scene name ("spheres").
        aovs: also return a dict of AOVs (depth, normal, albedo, object_id; see
            `jaxrt.shading.aovs`).
        overrides: for a path/name, values applied before validation, e.g. {"camera.width": 64}.
        memory: None renders the whole image as one compiled call (`integrators.frame`). A budget
            in bytes or as "2G", or "auto" (JAXRT_MEMORY, else the device's default), renders
            within it, in tiles of pixels and samples when the image does not fit in one piece
            (`jaxrt.render_tiles`; an InputError before any work when not even one tile fits).
        progress: with `memory` or `devices`, a progress bar over tiles on stderr.
        devices: the devices the tiles are spread over when rendering with `memory`: None (default)
            or "all" every device of `jax.devices()`, an int N the first N, or a list of devices
            (`jaxrt.render_tiles.plan`; the same pixels on any number of devices ≥ 2, within a few
            ulps of one device's, see `jaxrt._devices`). Given without `memory`, the render is tiled
            within the default budget ("auto"). An SPPM scene splits each pass's photons over the
            devices instead (`jaxrt._devices.sppm_program`). A bad value is an InputError.

    The scene's glare (`Scene.glare`, a scene file's [glare] table; `jaxrt.glare`) is applied to the
    finished image (not to the AOVs); without it, the image is the renderer's, untouched.

    Returns:
        (H, W, 3) float32 linear RGB radiance, or (image, aovs dict) with `aovs=True`. Without
        `memory` and `devices`: JAX arrays from one device, differentiable (reverse mode: jax.grad,
        jax.vjp) with respect to material parameters and light positions/intensities. With `memory`
        or `devices`: numpy arrays, not differentiable.
    """
    scene = _as_scene(scene, overrides)
    if memory is not None or devices is not None:
        return render_tiles.render(scene, memory="auto" if memory is None else memory, aovs=aovs,
                                   progress=progress, devices=devices)
    if scene.glare is None:
        return integrators.frame(scene, aovs=aovs)
    out = integrators.frame(scene.without_glare(), aovs=aovs)  # the renderer's program, unchanged
    if aovs:
        return glare.apply(out[0], scene.glare), out[1]
    return glare.apply(out, scene.glare)


def gbuffer(scene: Any) -> "integrators.GBuffer":
    """Trace once: the ray tree of `scene` for re-shading with `reshade` (fitting)."""
    return integrators.trace(_as_scene(scene))


def reshade(gb: "integrators.GBuffer", scene, *, aovs: bool = False) -> Float[Array, "H W 3"]:
    """Shade a cached G-buffer with the scene's current materials and lights (differentiable)."""
    return integrators.shade(gb, scene, aovs=aovs)
