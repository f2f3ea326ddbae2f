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
from jaxtyping import Array, Bool, Float

from brdfs.base import Component

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
    # written out: XLA:CPU runs a reduction over an axis of 3 as a slow library (YNNPACK) fusion
    if jnp.shape(a)[-1] != 3 or jnp.shape(b)[-1] != 3:
        return jnp.sum(a * b, axis=-1)
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def norm2(v: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """|v|^2 where it is > 1e-12, else 1 (a harmless stand-in for the near-zero vectors wi + wo of
    opposite directions, which callers mask): dividing by it keeps values and gradients finite
    (a floor like max(|v|^2, tiny) would not: d(x/y)/dy = -x/y^2 underflows y^2 to 0 in float32)."""
    n2 = dot(v, v)
    return jnp.where(n2 > 1e-12, n2, 1.0)


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
    """Unit vector from cos(theta) and phi (radians); sin(theta) = sqrt(1 - cos^2), which loses
    relative accuracy for theta -> 0: samplers of sharp lobes use `spherical_tan2` or
    `spherical_log_cos` instead."""
    return spherical_cs(cos_t, safe_sqrt(1.0 - cos_t * cos_t), phi)


def spherical_cs(cos_t: Float[Array, "..."], sin_t: Float[Array, "..."], phi: Float[Array, "..."]) -> Float[Array, "... 3"]:
    """Unit vector (sin cos phi, sin sin phi, cos) from cos(theta), sin(theta) and phi (radians)."""
    return jnp.stack([sin_t * jnp.cos(phi), sin_t * jnp.sin(phi), cos_t], axis=-1)


def spherical_tan2(tan2: Float[Array, "..."], phi: Float[Array, "..."]) -> Float[Array, "... 3"]:
    """Unit vector at polar angle theta with tan^2(theta) = tan2 >= 0 (Beckmann-type samplers):
    cos = 1/sqrt(1 + tan2), sin = sqrt(tan2 / (1 + tan2)), both to full relative precision, so a
    lobe of width 1e-3 rad is sampled as accurately in float32 as a wide one."""
    inv = jax.lax.rsqrt(1.0 + tan2)
    return spherical_cs(inv, safe_sqrt(tan2) * inv, phi)


def spherical_log_cos(log_cos: Float[Array, "..."], phi: Float[Array, "..."]) -> Float[Array, "... 3"]:
    """Unit vector at polar angle theta with log(cos theta) = log_cos <= 0 (power-cosine samplers,
    cos = (1 - u)^(1/(s+1))): sin^2 = 1 - cos^2 = -expm1(2 log_cos), exact for large exponents."""
    return spherical_cs(jnp.exp(log_cos), safe_sqrt(-jnp.expm1(2.0 * log_cos)), phi)


def cosine_sample(u: Float[Array, "... 2"]) -> Float[Array, "... 3"]:
    """Cosine-weighted hemisphere sample (Malley's method), density cos(theta)/pi [1/sr]."""
    return spherical_cs(safe_sqrt(1.0 - u[..., 0]), safe_sqrt(u[..., 0]), 2.0 * math.pi * u[..., 1])


def cosine_pdf(wi: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Density of `cosine_sample` [1/sr]; 0 below the horizon."""
    return jnp.maximum(wi[..., 2], 0.0) * INV_PI


def half_cos(wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """wi·h = wo·h for the unit half vector h = (wi + wo)/|wi + wo| of unit wi, wo, computed as
    |wi + wo| / 2. The dot product wi·h loses all its digits in float32 when wi and wo are both
    grazing and nearly opposite in azimuth (near the mirror configuration at a grazing view, where
    wi·h ~ cos(theta_o) ~ 1e-4 comes from cancelling terms ~1); |wi + wo| does not (each component
    sum is exact there, by Sterbenz's lemma)."""
    h = wi + wo
    return 0.5 * safe_sqrt(dot(h, h))


def pow_cos(log_cos: Float[Array, "..."], s: Float[Array, "..."], ok: Bool[Array, "..."]) -> Float[Array, "..."]:
    """cos^s = exp(s log cos) where `ok`, 0 elsewhere, with finite value and gradient everywhere."""
    return jnp.where(ok, jnp.exp(s * jnp.where(ok, log_cos, 0.0)), 0.0)


def log_cos_between(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """(log cos(angle between a and b), cos) for non-zero a, b, accurate near angle 0: with
    d = 1 - cos = |a - b|^2 / (2 |a| |b|) - (|a| - |b|)^2 / (2 |a| |b|), the first term is computed
    without cancellation and the second is ~1e-15 for float32 unit vectors (dropped), so
    log cos = log1p(-d) keeps its relative accuracy for the largest Phong exponents."""
    diff = a - b
    na = jnp.sqrt(norm2(a))
    nb = jnp.sqrt(norm2(b))
    d = dot(diff, diff) / (2.0 * na * nb)
    c = 1.0 - d
    return jnp.log1p(-jnp.minimum(d, 1.0 - 1e-7)), c


def log_cos_z(h: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """log(h_z / |h|) for a (possibly un-normalised) h with h_z > 0 (0 elsewhere, to be masked by the
    caller): near +z from h's tangential part, 0.5 log1p(-(h_x^2 + h_y^2) / |h|^2), which keeps full
    relative accuracy as h -> +z (cos^s of the half vector for exponents up to 1e6 in float32);
    elsewhere log(h_z) - log|h|."""
    hh = norm2(h)
    t = (h[..., 0] ** 2 + h[..., 1] ** 2) / hh
    near = t < 0.5
    hz = jnp.where(h[..., 2] > 0, h[..., 2], 1.0)
    return jnp.where(near, 0.5 * jnp.log1p(-jnp.where(near, t, 0.0)), jnp.log(hz) - 0.5 * jnp.log(hh))


def one_minus_pow5(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """1 - (1 - x)^5 for x in [0, 1], accurate for x -> 0 (= -expm1(5 log1p(-x)))."""
    x = jnp.clip(x, 0.0, 1.0)
    return -jnp.expm1(5.0 * jnp.log1p(-jnp.minimum(x, 1.0 - 1e-7)))


def rgb(x: Float[Array, "..."]) -> Float[Array, "... 1"]:
    """Scalar per-pixel parameter (...,) -> (..., 1) so that it multiplies RGB values."""
    return jnp.asarray(x)[..., None]


def lum(x: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Channel mean of an RGB parameter; used only to choose lobe-selection probabilities."""
    x = jnp.asarray(x)
    if x.shape[-1:] != (3,):
        return jnp.mean(x, axis=-1)
    # written out, as `dot`: a reduction over an axis of 3 that XLA:CPU does not fuse into its
    # consumers (inside a conditional) runs as a slow library (YNNPACK) fusion; the same sum, in the
    # same order, and jnp.mean's division
    return (x[..., 0] + x[..., 1] + x[..., 2]) / 3.0


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


def half_vector_jacobian(wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """d(omega_h)/d(omega_i) = 1 / (4 wo·h) for wi = reflect(wo, h), with wo·h = |wi + wo|/2
    (`half_cos`); 0 where wi = -wo."""
    return safe_div(1.0, 4.0 * half_cos(wi, wo), 1e-20)


def diffuse_component(p, wo: Float[Array, "... 3"], u: Float[Array, "... 2"]) -> Float[Array, "... 3"]:
    """`cosine_sample(u)` broadcast against wo's leading dims (the sampler of a diffuse `Component`)."""
    wi = cosine_sample(u)
    return jnp.broadcast_to(wi, jnp.broadcast_shapes(wi.shape, wo.shape))


def mixture(
    ps_fn: Callable,
    spec_sample: Callable,
    spec_pdf: Callable,
    eval_fn: Callable,
) -> tuple[Callable, Callable, tuple[Component, Component]]:
    """Build `sample`, `pdf` and the `Component`s of a one-sample mixture of a cosine-weighted
    diffuse lobe and a specular lobe (pbrt style).

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

    components = (Component(lambda p, wo: 1.0 - ps_fn(p), diffuse_component), Component(lambda p, wo: ps_fn(p), spec_sample))
    return sample, pdf, components
