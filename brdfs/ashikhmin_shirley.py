"""Ashikhmin-Shirley anisotropic Phong BRDF with its coupled diffuse term.

    f = f_s + f_d
    f_s(wi, wo) = k_s sqrt((n_u + 1)(n_v + 1)) / (8 pi) (n·h)^e / ((h·wi) max(n·wi, n·wo)) F(h·wi)
        e = (n_u (h·x)^2 + n_v (h·y)^2) / (1 - (n·h)^2),   F(c) = rho_s + (1 - rho_s)(1 - c)^5
    f_d(wi, wo) = 28 rho_d / (23 pi) (1 - rho_s) (1 - (1 - n·wi/2)^5) (1 - (1 - n·wo/2)^5)

M. Ashikhmin and P. Shirley, "An anisotropic Phong BRDF model", Journal of Graphics Tools 5(2),
2000. (n·h)^e is evaluated as exp((n_u hx^2 + n_v hy^2) * log1p(-t) / (2t)), t = hx^2 + hy^2
(h normalised), which is exact, accurate in float32 for n·h -> 1 and finite for the largest
exponents; h·wi is evaluated as |wi + wo| / 2, which unlike the dot product keeps its digits in
float32 near the mirror configuration of a grazing view, where it is ~cos(theta_o) and the
specular term ~1/(h·wi cos(theta_o)) is largest; 1 - (1 - c/2)^5 as -expm1(5 log1p(-c/2)).

Differences from Größler & Zettwitz, "An interactive ray tracing system based on Nvidia OptiX"
(2015): the report's diffuse term had n·wi in both Schlick-like
factors (instead of n·wi and n·wo, which breaks reciprocity) and the constant 28 rho_d/(23 rho_s)
instead of 28 rho_d/(23 pi); this module implements the paper.

The specular scale k_s (default 1: the paper's model, bit for bit) is not in the paper. There F0 =
rho_s sets the lobe's strength at normal incidence, while F -> 1 at grazing h·wi ties its strength
at grazing angles to the exponent alone: at the lobe's peak (θh = 0) f_s = (n + 1)/(8 pi)
F(cos θd) / cos² θd, whose grazing part (1 - rho_s)(1 - cos θd)^5 (n + 1)/(8 pi cos² θd) does not
depend on rho_s. For a measured material with a sharp but weak highlight (a plastic or a paint)
every exponent that matches the highlight's width makes that part alone brighter than the
measurement at large θd (in BRDF space, at n = 1e4, the best non-negative fit of rho_s and rho_d is
worse than the Lambertian term alone), so least-squares fits to MERL materials end at rho_s = 0
with a lobe far too wide (n ~ 50-1000), hardly better than the Lambertian term (0.190 against 0.193
/sr for blue-acrylic on the fit grid of fitting.brdf_space). Every lobe in Ngan, Durand & Matusik's
fits ("Experimental analysis of BRDF models", EGSR 2005) has a free specular coefficient, and
their Cook-Torrance a Fresnel F0 beside it, as jaxrt's has (rho_s beside eta); k_s is that
coefficient, per channel. With it the fits are in line with Cook-Torrance's (BENCHMARKS.md,
"BRDF-space study").

Properties (measured by tests/test_brdf_energy.py; see the constants there):
- Reciprocal (both terms are symmetric in wi, wo; max(n·wi, n·wo) is symmetric).
- The diffuse term's albedo is exactly (31/32) rho_d (1 - rho_s) at normal incidence (the 28/23
  normalisation), and the diffuse/specular coupling through (1 - rho_s) and F keeps the sum
  bounded *for every* rho_d, rho_s in [0, 1] (no rho_d + rho_s <= 1 condition, unlike the other
  models); k_s <= 1 only lowers the specular term, so the bound holds for every k_s in [0, 1].
  The specular normalisation sqrt((n_u+1)(n_v+1))/(8 pi) is approximate, but errs low:
  the float64 albedo over rho_d in {0, 0.5, 1}, rho_s in {0, 0.3, 1}, n_u, n_v in
  {1, 10, ..., 1e6} and view angles up to 89.9 deg has its maximum 0.999996 at rho_d = 0,
  rho_s = 1, n_u = n_v = 1e6, normal incidence (there it is 1 - 4/n: 0.9960 at n = 1000), so
  `energy_conserving=True`. The tests assert albedo <= 1 over such a grid.

Sampling: mixture of cosine-weighted diffuse and the paper's half-vector sampling
phi = atan(sqrt((n_u+1)/(n_v+1)) tan(pi u1 / 2)) (extended to all four quadrants),
cos(theta_h) = (1 - u0)^(1 / (n_u cos^2 phi + n_v sin^2 phi + 1)), density
sqrt((n_u+1)(n_v+1)) / (2 pi) (n·h)^e / (4 wo·h). The specular lobe is chosen with probability
mean(k_s rho_s) / (mean(k_s rho_s) + mean(rho_d (1 - rho_s))), at least 0.1 because the specular
term's Fresnel factor is non-zero even for rho_s = 0.

Parameters: rho_d, rho_s, k_s (RGB, 0-1), n_u, n_v (1-1e6, log) Phong-like exponents along the tangent
(+x) and bitangent (+y). (n·h)^n matches a Beckmann lobe of slope m at its peak for n ~ 2/m^2,
so the m ~ 0.007 that published fits of the sharpest MERL metals need is n ~ 4e4; the bound 1e6
(half-vector width sqrt(2/n) ~ 1.4e-3 rad) matches the other models' sharpest bounds. float32
values, gradients and samples stay accurate up to it (tests/test_brdf_grad.py,
tests/test_brdf_sampling.py).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Lobe, Model, Param, Params

SPEC = (
    Param("rho_d", 0.5, 0.0, 1.0, rgb=True, doc="diffuse reflectance"),
    Param("rho_s", 0.05, 0.0, 1.0, rgb=True, doc="specular reflectance at normal incidence"),
    # fits start at k_s = 0.5: the default 1 is on the bound, where the fit's transform is flat
    Param("k_s", 1.0, 0.0, 1.0, rgb=True, doc="specular scale (1: the paper's model)", start=0.5),
    Param("n_u", 100.0, 1.0, 1e6, scale="log", doc="exponent along the tangent (+x)", typical=(1.0, 1e4)),
    Param("n_v", 10.0, 1.0, 1e6, scale="log", doc="exponent along the bitangent (+y)", typical=(1.0, 1e4)),
)


def pow_nh(h: Float[Array, "... 3"], nu: Float[Array, "..."], nv: Float[Array, "..."]) -> Float[Array, "..."]:
    """(n·ĥ)^e for a (possibly un-normalised) half vector h, 0 for h_z <= 0 (see module docstring)."""
    hh = C.norm2(h)
    hx2, hy2 = h[..., 0] ** 2 / hh, h[..., 1] ** 2 / hh
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
    h = wi + wo
    # h·wi = |wi + wo| / 2: exact in float32 near the grazing mirror configuration, unlike the dot product
    kh = jnp.where(ok, jnp.maximum(C.half_cos(wi, wo), C.COS_EPS), 1.0)
    rho_s = p["rho_s"]
    fres = rho_s + (1.0 - rho_s) * C.rgb((1.0 - kh) ** 5)
    # k_s scales the Fresnel factor (not the product), so that k_s = 1 gives the paper's values bit for bit
    fres = p["k_s"] * fres
    spec = C.rgb(_norm(p) / (8.0 * math.pi) * pow_nh(h, p["n_u"], p["n_v"]) / (kh * jnp.maximum(ci, co))) * fres
    # 1 - (1 - c/2)^5 without cancellation for grazing c
    diff = (
        28.0 / (23.0 * math.pi) * p["rho_d"] * (1.0 - rho_s)
        * C.rgb(C.one_minus_pow5(ci / 2.0) * C.one_minus_pow5(co / 2.0))
    )
    return jnp.where(ok[..., None], spec + diff, 0.0)


def _spec_sample(p: Params, wo, u):
    nu, nv = p["n_u"], p["n_v"]
    a = 2.0 * math.pi * u[..., 1]
    phi = jnp.arctan2(jnp.sqrt(nu + 1.0) * jnp.sin(a), jnp.sqrt(nv + 1.0) * jnp.cos(a))
    e = nu * jnp.cos(phi) ** 2 + nv * jnp.sin(phi) ** 2
    # cos(theta_h) = (1 - u0)^(1/(e+1)), sin(theta_h) from log cos to full precision
    h = C.spherical_log_cos(jnp.log1p(-u[..., 0]) / (e + 1.0), phi)
    return C.reflect_about(wo, h)


def _spec_pdf(p: Params, wo, wi):
    return _norm(p) / (2.0 * math.pi) * pow_nh(wi + wo, p["n_u"], p["n_v"]) * C.half_vector_jacobian(wi, wo)


def _ps(p: Params):
    return C.lobe_prob(C.lum(p["k_s"] * p["rho_s"]), C.lum(p["rho_d"] * (1.0 - p["rho_s"])), floor=0.1)


sample, pdf, _components = C.mixture(_ps, _spec_sample, _spec_pdf, eval)

MODEL = Model(
    name="ashikhmin_shirley",
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
