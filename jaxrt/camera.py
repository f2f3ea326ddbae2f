"""Cameras: pinhole and thin lens, generating one ray per pixel sample.

Every value of a `Camera` is a traced array (moving the camera never recompiles); only the
resolution is static. Image rows run top to bottom, columns left to right.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


class Camera(eqx.Module):
    """A look-at camera.

    Attributes:
        position, look_at, up: (3,) world-space points / direction [scene units].
        vfov: () full vertical field of view [degrees].
        aperture: () lens diameter [scene units]; 0 is a pinhole.
        focus_distance: () distance from the lens to the plane in focus along the view axis.
        width, height: static resolution [pixels].
    """

    position: Float[Array, "3"]
    look_at: Float[Array, "3"]
    up: Float[Array, "3"]
    vfov: Float[Array, ""]
    aperture: Float[Array, ""]
    focus_distance: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    @property
    def num_pixels(self) -> int:
        return self.width * self.height


def basis(camera: Camera) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, "3"]]:
    """(right, up, forward) orthonormal camera axes in world space."""
    f = camera.look_at - camera.position
    f = f / jnp.linalg.norm(f)
    r = jnp.cross(f, camera.up)
    r = r / jnp.linalg.norm(r)
    u = jnp.cross(r, f)
    return r, u, f


def generate_rays(
    camera: Camera, spp: int = 1, seed: Int[Array, ""] | int = 0, jitter: bool | None = None
) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
    """Primary rays for every pixel sample, N = height·width·spp, ordered (row, column, sample).

    With `jitter` (default: spp > 1) each sample's position in the pixel is uniform random;
    otherwise it is the pixel centre. A thin lens (aperture > 0) samples the lens disk uniformly.
    Random numbers are counter-based (`jax.random` keyed by `seed`, folded with the sample index),
    so a render is reproducible from its seed.

    Returns:
        origins (N, 3) and unit directions (N, 3), float32.
    """
    jitter = spp > 1 if jitter is None else jitter
    h, w = camera.height, camera.width
    key = jax.random.key(jnp.asarray(seed, jnp.uint32))
    keys = jax.vmap(lambda s: jax.random.fold_in(key, s))(jnp.arange(spp))
    u = jax.vmap(lambda k: jax.random.uniform(k, (h, w, 4), jnp.float32))(keys)  # (spp, h, w, 4)
    u = jnp.moveaxis(u, 0, 2)  # (h, w, spp, 4)
    sub = u[..., :2] if jitter else jnp.full((h, w, spp, 2), 0.5, jnp.float32)
    rows = jnp.arange(h, dtype=jnp.float32)[:, None, None]
    cols = jnp.arange(w, dtype=jnp.float32)[None, :, None]
    tan_half = jnp.tan(jnp.deg2rad(camera.vfov) * 0.5)
    aspect = w / h
    x = (2.0 * (cols + sub[..., 0]) / w - 1.0) * tan_half * aspect
    y = (1.0 - 2.0 * (rows + sub[..., 1]) / h) * tan_half
    r, up, f = basis(camera)
    d = x[..., None] * r + y[..., None] * up + f  # (h, w, spp, 3), unnormalised: f-component is 1
    # thin lens: every ray through the lens point reaches the same point on the focus plane,
    # position + d·focus_distance; its direction is taken relative to the lens point, so it keeps
    # its precision far from the origin and at small focus distances
    lens_r = 0.5 * camera.aperture * jnp.sqrt(u[..., 2])
    phi = 2.0 * jnp.pi * u[..., 3]
    lens = (lens_r * jnp.cos(phi))[..., None] * r + (lens_r * jnp.sin(phi))[..., None] * up
    o = camera.position + lens
    d = d * camera.focus_distance - lens
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    return o.reshape(-1, 3), d.reshape(-1, 3)
