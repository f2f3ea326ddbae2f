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
  `Model.params` allows rho_d + rho_s > 1 (as the sliders of Größler & Zettwitz, "An interactive
  ray tracing system based on Nvidia OptiX", 2015, did); such configurations do not
  conserve energy. `energy_conserving=True` means "for rho_d + rho_s <= 1".

Sampling: one-sample mixture (pbrt style) of cosine-weighted diffuse and the specular lobe
cos(alpha) = u^(1/(s+1)) around r (density (s+1)/(2 pi) cos^s(alpha)), with the specular lobe
chosen with probability mean(rho_s) / (mean(rho_d) + mean(rho_s)). Lobe samples below the
horizon are failures (weight 0, pdf 0).

float32 at large exponents: cos^s(alpha) is evaluated as exp(s log1p(-d)) with
d = 1 - cos(alpha) = |wi - r|^2 / (2 |wi| |r|), which has no cancellation as wi -> r, and the
sampler builds sin(alpha) from log cos(alpha) (`_common.spherical_log_cos`) rather than from
sqrt(1 - cos^2); values, gradients and the sampling distribution then stay accurate up to s = 1e6
(tests/test_brdf_grad.py, tests/test_brdf_sampling.py).

Parameters: rho_d, rho_s (RGB, 0-1), s (1-1e6, log scale) the Phong exponent. Published fits of
measured materials need exponents above 1000 (Ngan, Durand & Matusik, "Experimental analysis of
BRDF models", EGSR 2005); the bound 1e6 (lobe width sqrt(2/s) ~ 1.4e-3 rad) matches the other
models' sharpest bounds (Beckmann m = 0.001 reflects into a lobe ~2e-3 rad wide).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Lobe, Model, Param, Params

SPEC = (
    Param("rho_d", 0.5, 0.0, 1.0, rgb=True, doc="diffuse albedo"),
    Param("rho_s", 0.5, 0.0, 1.0, rgb=True, doc="specular albedo at normal incidence"),
    Param("s", 50.0, 1.0, 1e6, scale="log", doc="Phong exponent (sharpness)", typical=(1.0, 1000.0)),
)

# cos(alpha) below this contributes < 1e-6 * (s+2)/(2 pi) even for s = 1; treating it as 0 keeps
# log(cos) finite for the gradient.
_COS_MIN = 1e-6


def lobe(wi: Float[Array, "... 3"], r: Float[Array, "... 3"], s: Float[Array, "..."]) -> Float[Array, "..."]:
    """max(0, cos(wi, r))^s with finite value and gradient everywhere, accurate for the largest s
    (log cos from |wi - r|, see `_common.log_cos_between`)."""
    log_c, c = C.log_cos_between(wi, r)
    return C.pow_cos(log_c, s, c > _COS_MIN)


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    s = p["s"]
    spec = (s + 2.0) / (2.0 * math.pi) * lobe(wi, C.reflect_z(wo), s)
    f = p["rho_d"] * C.INV_PI + p["rho_s"] * C.rgb(spec)
    return jnp.where(C.upper(wi, wo)[..., None], f, 0.0)


def frame(r: Float[Array, "... 3"]):
    """An orthonormal basis (t, b) around unit r (Duff et al. 2017, "Building an orthonormal basis,
    revisited", JCGT 6(1); branchless)."""
    sign = jnp.where(r[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + r[..., 2])
    b = r[..., 0] * r[..., 1] * a
    t = jnp.stack([1.0 + sign * r[..., 0] ** 2 * a, sign * b, -sign * r[..., 0]], axis=-1)
    bb = jnp.stack([b, sign + r[..., 1] ** 2 * a, -r[..., 1]], axis=-1)
    return t, bb


def _spec_sample(p: Params, wo, u):
    # cos(alpha) = (1 - u0)^(1/(s+1)), with sin(alpha) from log cos to full precision for large s
    log_c = jnp.log1p(-u[..., 0]) / (p["s"] + 1.0)
    local = C.spherical_log_cos(log_c, 2.0 * math.pi * u[..., 1])
    r = C.reflect_z(wo)
    t, b = frame(r)
    return local[..., :1] * t + local[..., 1:2] * b + local[..., 2:] * r


def _spec_pdf(p: Params, wo, wi):
    s = p["s"]
    return (s + 1.0) / (2.0 * math.pi) * lobe(wi, C.reflect_z(wo), s)


_ps = C.rho_lobe_prob

sample, pdf, _components = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="phong",
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
