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

Parameters: rho_d, rho_s (RGB, 0-1), s (1-1000, log scale).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Model, Param, Params

SPEC = (
    Param("rho_d", 0.5, 0.0, 1.0, rgb=True, doc="diffuse albedo"),
    Param("rho_s", 0.5, 0.0, 1.0, rgb=True, doc="specular scale"),
    Param("s", 50.0, 1.0, 1000.0, scale="log", doc="Blinn-Phong exponent (sharpness)"),
)


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    s = p["s"]
    h = C.normalize(wi + wo)
    spec = (s + 8.0) / (8.0 * math.pi) * C.cos_power(h[..., 2], s)
    f = p["rho_d"] * C.INV_PI + p["rho_s"] * C.rgb(spec)
    return jnp.where(C.upper(wi, wo)[..., None], f, 0.0)


def _spec_sample(p: Params, wo, u):
    cos_h = jnp.power(1.0 - u[..., 0], 1.0 / (p["s"] + 1.0))
    h = C.spherical(cos_h, 2.0 * math.pi * u[..., 1])
    return C.reflect_about(wo, h)


def _spec_pdf(p: Params, wo, wi):
    s = p["s"]
    h = C.normalize(wi + wo)
    return (s + 1.0) / (2.0 * math.pi) * C.cos_power(h[..., 2], s) * C.half_jacobian(wo, h)


_ps = C.rho_lobe_prob

sample, pdf = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="blinn_phong",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    energy_conserving=False,
    reciprocal=True,
    extras={"lobe_prob": _ps, "sample_specular": _spec_sample},
    doc=__doc__,
)
