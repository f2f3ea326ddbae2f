"""Numerically safe building blocks shared by the BRDF modules.

Everything here is a pure function on arrays with leading batch dimensions `...`; directions are
(..., 3) unit vectors in the local shading frame (normal +z, tangent +x) pointing away from the
surface. Guards use the "double where" pattern: the unsafe operation is fed a harmless value where
it would fail, so neither the value nor its gradient can become NaN/Inf.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

INV_PI = 1.0 / math.pi
# Cosines below this are treated as grazing/below the horizon: the BRDF is 0 there. It also keeps
# 1/cos factors finite in float32 for the (masked) evaluations of invalid directions.
COS_EPS = 1e-7


def safe_sqrt(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """sqrt(max(x, 0)) with a finite gradient everywhere (0 at and below 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def safe_div(a: Float[Array, "..."], b: Float[Array, "..."], eps: float = 1e-30) -> Float[Array, "..."]:
    """a / b where |b| > eps, else 0; gradient-safe."""
    ok = jnp.abs(b) > eps
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def dot(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "..."]:
    return jnp.sum(a * b, axis=-1)


def normalize(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """v / |v|; the zero vector maps to +z (a safe, arbitrary unit vector) with zero gradient."""
    n2 = dot(v, v)
    ok = n2 > 1e-30
    inv = jax.lax.rsqrt(jnp.where(ok, n2, 1.0))
    z = jnp.zeros_like(v).at[..., 2].set(1.0)
    return jnp.where(ok[..., None], v * inv[..., None], z)


def cos_theta(w: Float[Array, "... 3"]) -> Float[Array, "..."]:
    return w[..., 2]


def reflect_z(w: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Mirror reflection about the normal +z: (x, y, z) -> (-x, -y, z)."""
    return w * jnp.array([-1.0, -1.0, 1.0], dtype=w.dtype)


def reflect_about(w: Float[Array, "... 3"], h: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Reflect w about the unit vector h: 2(w·h)h - w."""
    return 2.0 * dot(w, h)[..., None] * h - w


def upper(wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """True where both directions are strictly above the horizon (where a BRDF is non-zero)."""
    return (wi[..., 2] > COS_EPS) & (wo[..., 2] > COS_EPS)


def spherical(cos_t: Float[Array, "..."], phi: Float[Array, "..."]) -> Float[Array, "... 3"]:
    """Unit vector from cos(theta) and phi (radians)."""
    sin_t = safe_sqrt(1.0 - cos_t * cos_t)
    return jnp.stack([sin_t * jnp.cos(phi), sin_t * jnp.sin(phi), cos_t], axis=-1)


def cosine_sample(u: Float[Array, "... 2"]) -> Float[Array, "... 3"]:
    """Cosine-weighted hemisphere sample (Malley's method), density cos(theta)/pi [1/sr]."""
    return spherical(jnp.sqrt(1.0 - u[..., 0]), 2.0 * math.pi * u[..., 1])


def cosine_pdf(wi: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Density of `cosine_sample` [1/sr]; 0 below the horizon."""
    return jnp.maximum(wi[..., 2], 0.0) * INV_PI


def rgb(x: Float[Array, "..."]) -> Float[Array, "... 1"]:
    """Scalar per-pixel parameter (...,) -> (..., 1) so that it multiplies RGB values."""
    return jnp.asarray(x)[..., None]


def lum(x: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Channel mean of an RGB parameter; used only to choose lobe-selection probabilities."""
    return jnp.mean(x, axis=-1)


def rho_lobe_prob(p) -> Float[Array, "..."]:
    """Specular-lobe probability from the luminances of rho_s and rho_d (the usual choice)."""
    return lobe_prob(lum(p["rho_s"]), lum(p["rho_d"]))


def lobe_prob(w_spec: Float[Array, "..."], w_diff: Float[Array, "..."], floor: float = 0.0) -> Float[Array, "..."]:
    """pbrt-style probability of sampling the specular lobe: w_spec / (w_spec + w_diff).

    With both weights 0 the specular lobe is chosen (the diffuse term is then 0 too). `floor`
    keeps a minimum probability for a specular lobe that is non-zero even when its weight is 0
    (Ashikhmin-Shirley's Fresnel term), so the mixture density stays positive wherever f > 0.
    """
    tot = w_spec + w_diff
    ps = jnp.where(tot > 0, w_spec / jnp.where(tot > 0, tot, 1.0), 1.0)
    return jnp.clip(ps, floor, 1.0)


def half_jacobian(wo: Float[Array, "... 3"], h: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """d(omega_h)/d(omega_i) = 1 / (4 |wo·h|) for wi = reflect(wo, h); 0 where wo·h <= 0."""
    return safe_div(1.0, 4.0 * jnp.maximum(dot(wo, h), 0.0), 1e-12)


def mixture(
    ps_fn: Callable,
    spec_sample: Callable,
    spec_pdf: Callable,
    eval_fn: Callable,
) -> tuple[Callable, Callable]:
    """Build `sample` and `pdf` for a one-sample mixture of a cosine-weighted diffuse lobe and a
    specular lobe (pbrt style).

    Args:
        ps_fn(p) -> (...,): probability of choosing the specular lobe.
        spec_sample(p, wo, u) -> wi: (..., 3) sample of the specular lobe from u in [0,1)^2.
        spec_pdf(p, wo, wi) -> (...,): its density [1/sr] (may be > 0 below the horizon).
        eval_fn(p, wi, wo) -> (..., 3): the BRDF.

    The returned pdf is (1 - ps) cos/pi + ps spec_pdf for wi above the horizon and 0 below it
    (samples below the horizon are failures: weight 0, pdf 0). The lobe is chosen by u[..., 0] < ps
    and u[..., 0] is then rescaled to [0, 1), as in pbrt.
    """

    def pdf(p, wo, wi):
        ps = ps_fn(p)
        d = (1.0 - ps) * cosine_pdf(wi) + ps * spec_pdf(p, wo, wi)
        ok = upper(wi, wo)
        return jnp.where(ok, d, 0.0)

    def sample(p, wo, u):
        ps = ps_fn(p)
        u0, u1 = u[..., 0], u[..., 1]
        pick_spec = u0 < ps
        # Re-use u0 after the lobe choice: rescale each branch back to [0, 1).
        us = jnp.clip(safe_div(u0, ps), 0.0, 1.0 - 1e-7)
        ud = jnp.clip(safe_div(u0 - ps, 1.0 - ps), 0.0, 1.0 - 1e-7)
        # ps may carry per-pixel batch dims that u does not (and vice versa): broadcast first.
        us, ud, u1 = jnp.broadcast_arrays(us, ud, u1)
        wi_s = spec_sample(p, wo, jnp.stack([us, u1], axis=-1))
        wi_d = cosine_sample(jnp.stack([ud, u1], axis=-1))
        wi = jnp.where(pick_spec[..., None], wi_s, wi_d)
        pd = pdf(p, wo, wi)
        f = eval_fn(p, wi, wo)
        ok = pd > 0
        weight = jnp.where(ok[..., None], f * safe_div(jnp.maximum(wi[..., 2], 0.0), pd)[..., None], 0.0)
        return wi, weight, pd

    return sample, pdf


# cos(alpha) below this contributes < 1e-6 * (s+2)/(2 pi) even for s = 1; treating it as 0 keeps
# log(cos) finite for the gradient.
COS_MIN = 1e-6


def cos_power(cos_a: Float[Array, "..."], s: Float[Array, "..."]) -> Float[Array, "..."]:
    """max(0, cos_a)^s with finite value and gradient everywhere (the Phong and Blinn-Phong lobes)."""
    ok = cos_a > COS_MIN
    c = jnp.where(ok, cos_a, 1.0)
    return jnp.where(ok, jnp.exp(s * jnp.log(c)), 0.0)
