"""Arbitrary output variables (AOVs): per-pixel depth, normal, albedo and object id.

One builder for every integrator, from the camera-ray hit of each pixel's first sample:

    depth      (H, W)     distance along the primary ray [scene units]; 0 where nothing was hit
    normal     (H, W, 3)  world shading normal facing the camera; 0 on misses
    albedo     (H, W, 3)  the material's diffuse albedo (`brdfs` model's diffuse colour; 1 for
                          delta materials); 0 on misses
    object_id  (H, W)     int32 scene-object id (`Scene.geometry.object_names`); -1 on misses
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxrt.shading.material import surface_albedo
from jaxrt.shading.surface import oriented

NAMES = ("depth", "normal", "albedo", "object_id")


def build_aovs(scene, prim: Int[Array, " P"], u: Float[Array, " P"], v: Float[Array, " P"], t: Float[Array, " P"],
               d: Float[Array, "P 3"], shape: tuple[int, int] | None = None) -> dict[str, Array]:
    """The AOVs of every pixel from the camera-ray hit (prim, u, v, t along direction d) of its first
    sample, each input (H·W, ...) in row-major pixel order. Every integrator returns these.
    `shape` is (H, W): the camera's resolution unless given (a tile's)."""
    cam = scene.camera
    found = prim >= 0
    s = scene.geometry.surface(prim, u, v)
    albedo = surface_albedo(scene.materials, s)
    _, ns, _ = oriented(s, d)
    hw = (cam.height, cam.width) if shape is None else tuple(shape)
    return {
        "depth": jnp.where(found, t, 0.0).reshape(hw),
        "normal": jnp.where(found[:, None], ns, 0.0).reshape(hw + (3,)),
        "albedo": jnp.where(found[:, None], albedo, 0.0).reshape(hw + (3,)),
        "object_id": jnp.where(found, scene.geometry.face_object(prim), -1).reshape(hw),
    }
