"""Cameras: pinhole and thin lens, generating one ray per pixel sample.

Every value of a `Camera` is a traced array (moving the camera never recompiles); only the
resolution is static. Image rows run top to bottom, columns left to right.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

from jaxrt import _random
from jaxrt.shading.surface import dot


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


class Window(eqx.Module):
    """A rectangle of an image's pixels and a run of each pixel's samples: the unit of tiled rendering.

    Rows row0 .. row0 + height - 1, columns col0 .. col0 + width - 1 and samples sample0 ..
    sample0 + spp - 1 of the image of `Camera.height` x `Camera.width` pixels; only the first `count`
    samples of the run are in use (a last batch of samples may be shorter than the others). The
    extents are static (they are a compiled program's shapes); the origin and count are traced, so
    one compiled program renders every tile of an image.
    """

    row0: Int[Array, ""]
    col0: Int[Array, ""]
    sample0: Int[Array, ""]
    count: Int[Array, ""]
    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    spp: int = eqx.field(static=True)

    @property
    def num_pixels(self) -> int:
        return self.height * self.width


def uniform_at(key, index: Int[Array, "..."], size: int) -> Float[Array, "..."]:
    """Elements `index` of ``jax.random.uniform(key, (size,), jnp.float32)``, computing only those.

    `jax.random.uniform` draws element i of its output from a Threefry-2x32 block (Salmon et al.,
    "Parallel random numbers: as easy as 1, 2, 3", SC 2011) whose counter is a function of i and the
    array's size: the 64-bit index (0, i) with JAX's default ``jax_threefry_partitionable``, else the
    pair (i, i + ⌈size/2⌉) of the original layout, which splits the counters into two halves. Both are
    reproduced here bit for bit (the mantissa construction is `jax.random.uniform`'s), so a tile of an
    image draws exactly the numbers the whole image's call gives its pixels. Other PRNG
    implementations fall back to drawing the whole array and gathering from it.
    """
    index = jnp.asarray(index)
    if str(jax.random.key_impl(key)) != "threefry2x32":  # pragma: no cover - a non-default PRNG
        return jax.random.uniform(key, (size,), jnp.float32)[index]
    k1, k2 = jax.random.key_data(key)
    return _threefry_uniform(k1, k2, index, size)


def _threefry_uniform(k1, k2, index, size: int):
    """`uniform_at` for Threefry key words k1, k2 that broadcast against `index` (one key per
    element, say), bit for bit."""
    i = jnp.asarray(index).astype(jnp.uint32)
    shape = jnp.broadcast_shapes(i.shape, jnp.shape(k1), jnp.shape(k2))
    i = jnp.broadcast_to(i, shape)
    k1, k2 = (jnp.broadcast_to(k, shape) for k in (k1, k2))
    if jax.config.jax_threefry_partitionable:
        b1, b2 = _random.threefry2x32(k1, k2, jnp.zeros_like(i), i)
        bits = b1 ^ b2
    else:
        half = (size + 1) // 2
        low = i < half
        x0 = jnp.where(low, i, i - half)
        x1 = jnp.where(low, jnp.where(i + half < size, i + half, jnp.uint32(0)), i)
        b1, b2 = _random.threefry2x32(k1, k2, x0, x1)
        bits = jnp.where(low, b1, b2)
    f = _random.unit_float(bits)
    return jnp.maximum(jnp.float32(0.0), f * jnp.float32(1.0) + jnp.float32(0.0))


def generate_rays(
    camera: Camera, spp: int = 1, seed: Int[Array, ""] | int = 0, jitter: bool | None = None,
    window: Window | None = None, subpixel: Float[Array, "h w spp 2"] | None = None,
    order: Int[Array, " n"] | np.ndarray | None = None,
) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
    """Primary rays for every pixel sample, N = height·width·spp, ordered (row, column, sample).

    With `jitter` (default: spp > 1) each sample's position in the pixel is uniform random;
    otherwise it is the pixel centre. A thin lens (aperture > 0) samples the lens disk uniformly.
    Random numbers are counter-based (`jax.random` keyed by `seed`, folded with the sample index),
    so a render is reproducible from its seed.

    With a `window` only the rays of its pixels and samples are made, N = window height·width·spp,
    ordered (row, column, sample) inside the window; each is bit for bit the ray of the same pixel
    and sample of the whole image (its random numbers come from the same counters, `uniform_at`).
    Window pixels outside the image and samples ≥ spp are made as well (they are never used).

    `subpixel` (no window): each sample's position in its pixel, in [0, 1)², instead of the
    jitter's uniforms (a low-discrepancy sequence over progressive passes, say).

    `order` (ints, with or without a window; `integrators.sample_order_arrays`): the indices, in the order above, of the
    rays to make, in the order to make them (an integrator's slot order: `integrators.sample_order`);
    each ray is the one made without `order` at that index, bit for bit where the compiler rounds
    both programs alike. Pixel-centre rays of a pinhole are made in that order directly; otherwise
    the random numbers are permuted, not the rays.

    Returns:
        origins (N, 3) and unit directions (N, 3), float32.
    """
    jitter = spp > 1 if jitter is None else jitter
    h, w = camera.height, camera.width
    key = jax.random.key(jnp.asarray(seed, jnp.uint32))

    def per_sample(samples, flat, c: int):
        # the first c of each sample's 4 numbers: element `flat` of jax.random.uniform(k, (h, w, 4))
        # of the sample's key k (bit for bit, without JAX's rolled loop over every ray of the pass on
        # the CPU, `jaxrt._random`), made directly as (rows, columns, samples, c): made per sample and
        # then transposed, XLA:CPU fused each number's Threefry hash into its own transposing loop (a
        # tenth of a 256² path-tracing pass)
        keys = jax.vmap(lambda s: jax.random.fold_in(key, s))(samples)
        flat = flat[:, :, None, :c]
        if str(jax.random.key_impl(key)) != "threefry2x32":  # pragma: no cover - a non-default PRNG
            return jnp.moveaxis(jax.vmap(lambda k: uniform_at(k, flat[:, :, 0], h * w * 4))(keys), 0, 2)
        kd = jax.random.key_data(keys)[None, None, :, None, :]  # (1, 1, spp, 1, 2)
        return _threefry_uniform(kd[..., 0], kd[..., 1], flat, h * w * 4)

    if window is None:
        def uniforms(c):
            flat = jnp.arange(h * w * 4, dtype=jnp.uint32).reshape(h, w, 4)
            return per_sample(jnp.arange(spp), flat, c)  # (h, w, spp, c)
        rows = jnp.arange(h, dtype=jnp.float32)[:, None, None]
        cols = jnp.arange(w, dtype=jnp.float32)[None, :, None]
        shape = (h, w, spp)
        if order is not None:
            pix = jnp.asarray(order) // spp
            rows, cols, shape = (pix // w).astype(np.float32), (pix % w).astype(np.float32), (len(pix),)
    else:
        ri = window.row0 + jnp.arange(window.height)
        ci = window.col0 + jnp.arange(window.width)
        # the flat index of (row, column, channel) in each sample's (h, w, 4) array of uniforms
        flat = (ri[:, None, None] * w + ci[None, :, None]) * 4 + jnp.arange(4)[None, None, :]

        def uniforms(c):
            return per_sample(window.sample0 + jnp.arange(window.spp), flat, c)  # (th, tw, spp, c)
        rows = ri.astype(jnp.float32)[:, None, None]
        cols = ci.astype(jnp.float32)[None, :, None]
        shape = (window.height, window.width, window.spp)
        if order is not None:
            pix = jnp.asarray(order) // window.spp
            rows = (window.row0 + pix // window.width).astype(jnp.float32)
            cols = (window.col0 + pix % window.width).astype(jnp.float32)
            shape = (len(pix),)
    tan_half = jnp.tan(jnp.deg2rad(camera.vfov) * 0.5)
    aspect = w / h
    r, up, f = basis(camera)

    def random(u):
        # (h, w, spp, c), or its rows at `order`
        return u if order is None else u.reshape(-1, u.shape[-1])[order]

    def rays(u):
        sub = u[..., :2] if jitter else jnp.full(shape + (2,), 0.5, jnp.float32)
        if subpixel is not None:
            sub = subpixel if order is None else subpixel.reshape(-1, 2)[order]
        x = (2.0 * (cols + sub[..., 0]) / w - 1.0) * tan_half * aspect
        y = (1.0 - 2.0 * (rows + sub[..., 1]) / h) * tan_half
        d = x[..., None] * r + y[..., None] * up + f  # (h, w, spp, 3) or (N, 3), unnormalised: f-component 1
        if u is None or u.shape[-1] < 4:
            # a pinhole: the lens point below with radius 0, the same for every ray, made once
            lens = jnp.float32(0.0) * r + jnp.float32(0.0) * up
        else:
            # thin lens: every ray through the lens point reaches the same point on the focus plane,
            # position + d·focus_distance; its direction is taken relative to the lens point, so it
            # keeps its precision far from the origin and at small focus distances
            lens_r = 0.5 * camera.aperture * jnp.sqrt(u[..., 2])
            phi = 2.0 * jnp.pi * u[..., 3]
            lens = (lens_r * jnp.cos(phi))[..., None] * r + (lens_r * jnp.sin(phi))[..., None] * up
        o = jnp.broadcast_to(camera.position + lens, shape + (3,))
        d = d * camera.focus_distance - lens
        # |d| from the written-out `dot`: jnp.linalg.norm's reduction over an axis of 3 is a library
        # (YNNPACK) fusion on XLA:CPU that took a quarter of a 512² direct frame (BENCHMARKS.md, "jaxrt
        # beside Mitsuba 3")
        d = d / jnp.sqrt(dot(d, d))[..., None]
        return o.reshape(-1, 3), d.reshape(-1, 3)

    # Pixel centres use no random numbers and a pinhole (aperture 0) needs no lens point: it is 0
    # whatever its numbers are. Skipping them and the per-ray lens (one threefry hash per number, a
    # sqrt, cos and sin per ray: ~4 % and more of a 512² direct frame on the CPU) leaves every ray bit
    # for bit the same. On a GPU the conditional would wait for the device to read the aperture, and
    # the numbers cost little there: a jittered pass makes all four.
    lensed = lambda: rays(random(uniforms(4)))  # noqa: E731
    if not jitter:
        return lax.cond(camera.aperture > 0, lensed, lambda: rays(None))
    if jax.default_backend() != "cpu":
        return lensed()
    return lax.cond(camera.aperture > 0, lensed, lambda: rays(random(uniforms(2))))
