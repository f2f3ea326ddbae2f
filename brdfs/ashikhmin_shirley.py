"""Ashikhmin-Shirley anisotropic Phong BRDF with its coupled diffuse term.

    f = f_s + f_d
    f_s(wi, wo) = sqrt((n_u + 1)(n_v + 1)) / (8 pi) (n·h)^e / ((h·wi) max(n·wi, n·wo)) F(h·wi)
        e = (n_u (h·x)^2 + n_v (h·y)^2) / (1 - (n·h)^2),   F(c) = rho_s + (1 - rho_s)(1 - c)^5
    f_d(wi, wo) = 28 rho_d / (23 pi) (1 - rho_s) (1 - (1 - n·wi/2)^5) (1 - (1 - n·wo/2)^5)

M. Ashikhmin and P. Shirley, "An anisotropic Phong BRDF model", Journal of Graphics Tools 5(2),
2000. (n·h)^e is evaluated as exp((n_u hx^2 + n_v hy^2) * log1p(-t) / (2t)), t = hx^2 + hy^2,
which is exact, accurate in float32 for n·h -> 1 and finite for the largest exponents.

Differences from the 2015 report: the report's diffuse term had n·wi in both Schlick-like
factors (instead of n·wi and n·wo, which breaks reciprocity) and the constant 28 rho_d/(23 rho_s)
instead of 28 rho_d/(23 pi); this module implements the paper.

Properties (measured by tests/test_brdf_energy.py; see the constants there):
- Reciprocal (both terms are symmetric in wi, wo; max(n·wi, n·wo) is symmetric).
- The diffuse term's albedo is exactly (31/32) rho_d (1 - rho_s) at normal incidence (the 28/23
  normalisation), and the diffuse/specular coupling through (1 - rho_s) and F keeps the sum
  bounded *for every* rho_d, rho_s in [0, 1] (no rho_d + rho_s <= 1 condition, unlike the other
  models). The specular normalisation sqrt((n_u+1)(n_v+1))/(8 pi) is approximate, but errs low:
  float64 quadrature over rho_d, rho_s in {0..1}, n_u, n_v in {1..1000} and view angles up to
  89.7 deg gives a maximum albedo of 0.996 (rho_d = 0, rho_s = 1, n = 1000, normal incidence),
  so `energy_conserving=True`. The tests assert albedo <= 1 over such a grid.

Sampling: mixture of cosine-weighted diffuse and the paper's half-vector sampling
phi = atan(sqrt((n_u+1)/(n_v+1)) tan(pi u1 / 2)) (extended to all four quadrants),
cos(theta_h) = (1 - u0)^(1 / (n_u cos^2 phi + n_v sin^2 phi + 1)), density
sqrt((n_u+1)(n_v+1)) / (2 pi) (n·h)^e / (4 wo·h). The specular lobe is chosen with probability
mean(rho_s) / (mean(rho_s) + mean(rho_d (1 - rho_s))), at least 0.1 because the specular
term's Fresnel factor is non-zero even for rho_s = 0.

Parameters: rho_d, rho_s (RGB, 0-1), n_u, n_v (1-10000, log) Phong-like exponents along the tangent
(+x) and bitangent (+y).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Model, Param, Params

SPEC = (
    Param("rho_d", 0.5, 0.0, 1.0, rgb=True, doc="diffuse reflectance"),
    Param("rho_s", 0.05, 0.0, 1.0, rgb=True, doc="specular reflectance at normal incidence"),
    Param("n_u", 100.0, 1.0, 10000.0, scale="log", doc="exponent along the tangent (+x)"),
    Param("n_v", 10.0, 1.0, 10000.0, scale="log", doc="exponent along the bitangent (+y)"),
)


def _pow_nh(h: Float[Array, "... 3"], nu: Float[Array, "..."], nv: Float[Array, "..."]) -> Float[Array, "..."]:
    """(n·h)^e for a unit half vector with h_z > 0 (see module docstring)."""
    hx2, hy2 = h[..., 0] ** 2, h[..., 1] ** 2
    t = hx2 + hy2
    small = t < 1e-4
    ts = jnp.where(small, 0.5, t)
    # log1p(-t)/t, with its Taylor series near t = 0 where the quotient is 0/0.
    g = jnp.where(small, -1.0 - t / 2.0 - t * t / 3.0, jnp.log1p(-jnp.minimum(ts, 1.0 - 1e-7)) / ts)
    ok = h[..., 2] > 0
    return jnp.where(ok, jnp.exp(0.5 * (nu * hx2 + nv * hy2) * g), 0.0)


def _norm(p: Params) -> Float[Array, "..."]:
    return jnp.sqrt((p["n_u"] + 1.0) * (p["n_v"] + 1.0))


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    ok = C.upper(wi, wo)
    ci = jnp.where(ok, wi[..., 2], 1.0)
    co = jnp.where(ok, wo[..., 2], 1.0)
    h = C.normalize(wi + wo)
    kh = jnp.where(ok, jnp.maximum(C.dot(wi, h), C.COS_EPS), 1.0)
    rho_s = p["rho_s"]
    fres = rho_s + (1.0 - rho_s) * C.rgb((1.0 - kh) ** 5)
    spec = C.rgb(_norm(p) / (8.0 * math.pi) * _pow_nh(h, p["n_u"], p["n_v"]) / (kh * jnp.maximum(ci, co))) * fres
    diff = (
        28.0 / (23.0 * math.pi) * p["rho_d"] * (1.0 - rho_s)
        * C.rgb((1.0 - (1.0 - ci / 2.0) ** 5) * (1.0 - (1.0 - co / 2.0) ** 5))
    )
    return jnp.where(ok[..., None], spec + diff, 0.0)


def _spec_sample(p: Params, wo, u):
    nu, nv = p["n_u"], p["n_v"]
    a = 2.0 * math.pi * u[..., 1]
    phi = jnp.arctan2(jnp.sqrt(nu + 1.0) * jnp.sin(a), jnp.sqrt(nv + 1.0) * jnp.cos(a))
    e = nu * jnp.cos(phi) ** 2 + nv * jnp.sin(phi) ** 2
    cos_h = jnp.exp(jnp.log1p(-u[..., 0]) / (e + 1.0))
    h = C.spherical(cos_h, phi)
    return C.reflect_about(wo, h)


def _spec_pdf(p: Params, wo, wi):
    h = C.normalize(wi + wo)
    return _norm(p) / (2.0 * math.pi) * _pow_nh(h, p["n_u"], p["n_v"]) * C.half_jacobian(wo, h)


def _ps(p: Params):
    return C.lobe_prob(C.lum(p["rho_s"]), C.lum(p["rho_d"] * (1.0 - p["rho_s"])), floor=0.1)


sample, pdf = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="ashikhmin_shirley",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    energy_conserving=True,
    reciprocal=True,
    extras={"lobe_prob": _ps, "sample_specular": _spec_sample},
    doc=__doc__,
)
