"""Normalised Blinn-Phong.

    f(wi, wo) = rho_d / pi + rho_s (s + 8) / (8 pi) (n·h)^s,        h = (wi + wo) / |wi + wo|

J. F. Blinn, "Models of light reflection for computer synthesized pictures", SIGGRAPH 1977; the
(s+8)/(8 pi) normalisation is the approximation popularised by Akenine-Moller, Haines & Hoffman,
*Real-Time Rendering* (3rd ed., 2008), section 7.6.

Properties (measured by tests/test_brdf_energy.py):
- Reciprocal (h is symmetric in wi, wo).
- NOT energy conserving in general: (s+8)/(8 pi) is only an approximate normalisation. At normal
  incidence the specular albedo is, in closed form (wi = 2 theta_h),
  rho_s (s+8) [2 (1 - 2^(-(s+4)/2)) / (s+4) - (1 - 2^(-(s+2)/2)) / (s+2)],
  which exceeds rho_s for every s > 1: +2.4 % at s = 1, a maximum of +7.5 % at s = 8, +1.8 % at
  s = 100, +0.2 % at s = 1000. The excess is confined to near-normal incidence (at 30 deg and
  beyond the lobe loses more than that below the horizon). Hence `energy_conserving=False`; the
  tests assert this closed form.

Sampling: mixture of cosine-weighted diffuse and the half-vector lobe cos(theta_h) = u^(1/(s+1))
(density (s+1)/(2 pi) cos^s(theta_h) / (4 wo·h) in wi), specular chosen with probability
mean(rho_s) / (mean(rho_d) + mean(rho_s)).

float32 at large exponents: (n·h)^s is evaluated from the un-normalised half vector's tangential
part, cos(theta_h) = sqrt(1 - t), t = (h_x^2 + h_y^2) / |h|^2, as exp(s/2 log1p(-t)), and the
sampler builds sin(theta_h) from log cos(theta_h); the half-vector Jacobian uses wo·h = |wi + wo|/2.
Values, gradients and the sampling distribution stay accurate up to s = 1e6
(tests/test_brdf_grad.py, tests/test_brdf_sampling.py).

Parameters: rho_d, rho_s (RGB, 0-1), s (1-1e6, log scale). Published fits of measured materials
need Blinn-Phong exponents above 1000 (Ngan, Durand & Matusik, "Experimental analysis of BRDF
models", EGSR 2005); (n·h)^s matches a Beckmann lobe of slope m at its peak for s ~ 2/m^2, so the
m ~ 0.007 of the sharpest MERL metals is s ~ 4e4, and the bound 1e6 is m ~ 0.0014.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Lobe, Model, Param, Params

SPEC = (
    Param("rho_d", 0.5, 0.0, 1.0, rgb=True, doc="diffuse albedo"),
    Param("rho_s", 0.5, 0.0, 1.0, rgb=True, doc="specular scale"),
    Param("s", 50.0, 1.0, 1e6, scale="log", doc="Blinn-Phong exponent (sharpness)", typical=(1.0, 1000.0)),
)


def lobe(h: Float[Array, "... 3"], s: Float[Array, "..."]) -> Float[Array, "..."]:
    """(n·ĥ)^s for a (possibly un-normalised) half vector h, 0 for h_z <= 0; log(n·ĥ) from h's
    tangential part (`_common.log_cos_z`), so exponents up to 1e6 stay accurate in float32."""
    return C.pow_cos(C.log_cos_z(h), s, h[..., 2] > C.COS_EPS * jnp.sqrt(C.norm2(h)))


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    s = p["s"]
    spec = (s + 8.0) / (8.0 * math.pi) * lobe(wi + wo, s)
    f = p["rho_d"] * C.INV_PI + p["rho_s"] * C.rgb(spec)
    return jnp.where(C.upper(wi, wo)[..., None], f, 0.0)


def _spec_sample(p: Params, wo, u):
    # cos(theta_h) = (1 - u0)^(1/(s+1))
    h = C.spherical_log_cos(jnp.log1p(-u[..., 0]) / (p["s"] + 1.0), 2.0 * math.pi * u[..., 1])
    return C.reflect_about(wo, h)


def _spec_pdf(p: Params, wo, wi):
    s = p["s"]
    return (s + 1.0) / (2.0 * math.pi) * lobe(wi + wo, s) * C.half_vector_jacobian(wi, wo)


_ps = C.rho_lobe_prob

sample, pdf, _components = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="blinn_phong",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    flags=Lobe.REFLECTION | Lobe.DIFFUSE | Lobe.GLOSSY,
    energy_conserving=False,
    reciprocal=True,
    diffuse=lambda p: p["rho_d"],
    mixture=_components,
    doc=__doc__,
)
