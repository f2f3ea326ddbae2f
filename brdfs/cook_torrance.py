"""Cook-Torrance microfacet BRDF with a Beckmann distribution.

    f(wi, wo) = rho_d / pi + rho_s D(h) F(wi·h) G(wi, wo) / (4 (n·wi)(n·wo))

    D(h)  = exp(-tan^2(theta_h) / m^2) / (pi m^2 cos^4(theta_h))          Beckmann, ∫ D cos(theta_h) dω_h = 1
    F(c)  = F0 + (1 - F0)(1 - c)^5,   F0 = ((eta - 1) / (eta + 1))^2      Schlick 1994
    G     = min(1, 2(n·h)(n·wo)/(wo·h), 2(n·h)(n·wi)/(wo·h))              Torrance-Sparrow V-cavities

R. L. Cook and K. E. Torrance, "A reflectance model for computer graphics", ACM TOG 1(1), 1982
(with Schlick's approximation to the Fresnel term, C. Schlick, Computer Graphics Forum 13(3),
1994, in place of the full Fresnel equations). G/(4 (n·wi)(n·wo)) is evaluated in the equivalent
form min(1/(4 ci co), (n·h)/(2 (wo·h) ci), (n·h)/(2 (wo·h) co)), finite at grazing angles.

Properties (measured by tests): reciprocal; the V-cavity G satisfies Heitz's (2014) masking
normalisation, so the specular albedo is <= rho_s and the model conserves energy for
rho_d + rho_s <= 1 (no diffuse/specular energy coupling; `energy_conserving=True` means that).

Sampling: mixture of cosine-weighted diffuse and Beckmann half-vector sampling
tan^2(theta_h) = -m^2 ln(1-u0), phi = 2 pi u1 (density D cos(theta_h) / (4 wo·h) in wi);
specular chosen with probability mean(rho_s) / (mean(rho_d) + mean(rho_s)).

float32 at small m: D is evaluated from the half vector's components (tan^2 = (h_x^2 + h_y^2)/h_z^2),
the sampler builds the half vector from tan^2(theta_h) directly (`_common.spherical_tan2`; the
usual cos = 1/sqrt(1 + tan^2), sin = sqrt(1 - cos^2) loses 6 % of sin^2 at m = 0.001 in float32),
and wo·h = |wi + wo|/2 (the dot product loses its digits near the mirror direction of a grazing
view). Values, gradients and the sampling distribution stay accurate down to m = 0.001
(tests/test_brdf_grad.py, tests/test_brdf_sampling.py).

Parameters: rho_d, rho_s (RGB, 0-1), m (0.001-1, log) RMS microfacet slope, eta (1-1000, log)
relative index of refraction for F0 = ((eta - 1)/(eta + 1))^2. Published fits of measured
materials need m < 0.01 (about 0.007 for the sharpest MERL metals) and Schlick F0 above the
0.669 of eta = 10 (e.g. F0 ~ 0.73 for nickel); F0 = 0.9 is eta = 38.0, 0.96 is eta = 98 and the
bound eta = 1000 gives F0 = 0.996. eta enters only through F0 (a scalar Schlick Fresnel tinted by
rho_s, not a complex metal IOR).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Lobe, Model, Param, Params

SPEC = (
    Param("rho_d", 0.2, 0.0, 1.0, rgb=True, doc="diffuse albedo"),
    Param("rho_s", 0.8, 0.0, 1.0, rgb=True, doc="specular scale"),
    Param("m", 0.3, 0.001, 1.0, scale="log", doc="Beckmann RMS slope (roughness)", typical=(0.01, 1.0)),
    Param("eta", 1.5, 1.0, 1000.0, scale="log", doc="index of refraction for the Fresnel term (F0 = ((eta-1)/(eta+1))^2)",
          typical=(1.0, 10.0)),
)


def beckmann_d(h: Float[Array, "... 3"], m: Float[Array, "..."]) -> Float[Array, "..."]:
    """Beckmann NDF D(h) [1/sr] for a unit (or un-normalised, positive-z) half vector; 0 for h_z <= 0."""
    hz = h[..., 2]
    ok = hz > C.COS_EPS
    hz_s = jnp.where(ok, hz, 1.0)
    hh = C.dot(h, h)
    # tan^2 and cos^4 from the components, invariant to |h|: tan^2 = (hx^2 + hy^2) / hz^2.
    tan2 = (h[..., 0] ** 2 + h[..., 1] ** 2) / hz_s**2
    m2 = m * m
    log_d = -tan2 / m2 - jnp.log(math.pi * m2) - 2.0 * jnp.log(hz_s**2 / jnp.where(ok, hh, 1.0))
    return jnp.where(ok, jnp.exp(log_d), 0.0)


def schlick_f0(eta: Float[Array, "..."]) -> Float[Array, "..."]:
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def schlick(f0: Float[Array, "..."], c: Float[Array, "..."]) -> Float[Array, "..."]:
    return f0 + (1.0 - f0) * (1.0 - jnp.clip(c, 0.0, 1.0)) ** 5


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    ok = C.upper(wi, wo)
    ci = jnp.where(ok, wi[..., 2], 1.0)
    co = jnp.where(ok, wo[..., 2], 1.0)
    h = C.normalize(wi + wo)
    nh = h[..., 2]
    oh = jnp.where(ok, jnp.maximum(C.half_cos(wi, wo), C.COS_EPS), 1.0)  # wo·h, accurate at grazing views
    g_over = jnp.minimum(1.0 / (4.0 * ci * co), jnp.minimum(nh / (2.0 * oh * ci), nh / (2.0 * oh * co)))
    spec = beckmann_d(h, p["m"]) * schlick(schlick_f0(p["eta"]), oh) * g_over
    f = p["rho_d"] * C.INV_PI + p["rho_s"] * C.rgb(spec)
    return jnp.where(ok[..., None], f, 0.0)


def _spec_sample(p: Params, wo, u):
    m = p["m"]
    tan2 = -(m * m) * jnp.log1p(-u[..., 0])
    h = C.spherical_tan2(tan2, 2.0 * math.pi * u[..., 1])
    return C.reflect_about(wo, h)


def _spec_pdf(p: Params, wo, wi):
    h = C.normalize(wi + wo)
    return beckmann_d(h, p["m"]) * jnp.maximum(h[..., 2], 0.0) * C.half_vector_jacobian(wi, wo)


_ps = C.rho_lobe_prob

sample, pdf, _components = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="cook_torrance",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    flags=Lobe.REFLECTION | Lobe.DIFFUSE | Lobe.GLOSSY,
    energy_conserving=True,
    reciprocal=True,
    diffuse=lambda p: p["rho_d"],
    mixture=_components,
    doc=__doc__,
)
