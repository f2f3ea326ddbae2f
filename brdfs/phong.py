"""Energy-normalised (modified) Phong.

    f(wi, wo) = rho_d / pi + rho_s (s + 2) / (2 pi) max(0, wi·r)^s,    r = reflect(wo) = (-wo_x, -wo_y, wo_z)

B. T. Phong, "Illumination for computer generated pictures", CACM 1975; normalisation from
E. Lafortune and Y. Willems, "Using the modified Phong reflectance model for physically based
rendering", Tech. Rep. CW197, KU Leuven 1994. The lobe is around the mirror direction of wo.

Properties (measured by tests/test_brdf_energy.py, not just claimed):
- Reciprocal: wi·reflect(wo) = wo·reflect(wi), so f(wi, wo) = f(wo, wi).
- Energy: the (s+2)/(2 pi) factor makes the specular albedo exactly rho_s at normal incidence;
  at oblique incidence part of the lobe falls below the horizon and is clipped, so the specular
  albedo decreases. Hence albedo <= 1 whenever rho_d + rho_s <= 1 (per channel).
  `Model.params` allows rho_d + rho_s > 1 (as the seed's sliders did); such configurations do not
  conserve energy. `energy_conserving=True` means "for rho_d + rho_s <= 1".

Sampling: one-sample mixture (pbrt style) of cosine-weighted diffuse and the specular lobe
cos(alpha) = u^(1/(s+1)) around r (density (s+1)/(2 pi) cos^s(alpha)), with the specular lobe
chosen with probability mean(rho_s) / (mean(rho_d) + mean(rho_s)). Lobe samples below the
horizon are failures (weight 0, pdf 0).

Parameters: rho_d, rho_s (RGB, 0-1), s (1-1000, log scale) the Phong exponent.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Model, Param, Params

SPEC = (
    Param("rho_d", 0.5, 0.0, 1.0, rgb=True, doc="diffuse albedo"),
    Param("rho_s", 0.5, 0.0, 1.0, rgb=True, doc="specular albedo at normal incidence"),
    Param("s", 50.0, 1.0, 1000.0, scale="log", doc="Phong exponent (sharpness)"),
)


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    s = p["s"]
    cos_a = C.dot(wi, C.reflect_z(wo))
    spec = (s + 2.0) / (2.0 * math.pi) * C.cos_power(cos_a, s)
    f = p["rho_d"] * C.INV_PI + p["rho_s"] * C.rgb(spec)
    return jnp.where(C.upper(wi, wo)[..., None], f, 0.0)


def _frame(r: Float[Array, "... 3"]):
    """An orthonormal basis (t, b) around unit r (Duff et al. 2017, branchless)."""
    sign = jnp.where(r[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + r[..., 2])
    b = r[..., 0] * r[..., 1] * a
    t = jnp.stack([1.0 + sign * r[..., 0] ** 2 * a, sign * b, -sign * r[..., 0]], axis=-1)
    bb = jnp.stack([b, sign + r[..., 1] ** 2 * a, -r[..., 1]], axis=-1)
    return t, bb


def _spec_sample(p: Params, wo, u):
    s = p["s"]
    cos_a = jnp.power(1.0 - u[..., 0], 1.0 / (s + 1.0))
    local = C.spherical(cos_a, 2.0 * math.pi * u[..., 1])
    r = C.reflect_z(wo)
    t, b = _frame(r)
    return local[..., :1] * t + local[..., 1:2] * b + local[..., 2:] * r


def _spec_pdf(p: Params, wo, wi):
    s = p["s"]
    return (s + 1.0) / (2.0 * math.pi) * C.cos_power(C.dot(wi, C.reflect_z(wo)), s)


_ps = C.rho_lobe_prob

sample, pdf = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="phong",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    energy_conserving=True,
    reciprocal=True,
    extras={"lobe_prob": _ps, "sample_specular": _spec_sample},
    doc=__doc__,
)
