"""Disney principled BRDF (Burley 2012), the reflection-only ("BRDF") version.

    f = (1 - metallic) [ C_d / pi  lerp(F_d, F_ss, subsurface)  +  F_sheen ]          diffuse + sheen
      + D_s(h) F_s(wi·h) G_s(wi, wo) / (4 (n·wi)(n·wo))                               specular (GGX)
      + clearcoat / 4  D_c(h) F_c(wi·h) G_c(wi, wo) / (4 (n·wi)(n·wo))                clearcoat (GTR1)

  diffuse     F_d = (1 + (F_D90 - 1) S(n·wi)) (1 + (F_D90 - 1) S(n·wo)),   F_D90 = 0.5 + 2 roughness (wi·h)^2,
              S(c) = (1 - c)^5 (Schlick's weight); retro-reflection rises at grazing angles for rough surfaces
  subsurface  F_ss = 1.25 (F'(1 / (n·wi + n·wo) - 0.5) + 0.5),  F' = the same product with F_SS90 = roughness (wi·h)^2
              (Burley's Hanrahan-Krueger-like flattening)
  tint        C_tint = C_d / lum(C_d)  (lum = 0.3 R + 0.6 G + 0.1 B; white where lum = 0)
  specular    C_s0 = lerp(0.08 specular lerp(1, C_tint, specular_tint), C_d, metallic),
              F_s = C_s0 + (1 - C_s0) S(wi·h)                                         Schlick towards white
              D_s = 1 / (pi a_x a_y ((h_x/a_x)^2 + (h_y/a_y)^2 + h_z^2)^2)            anisotropic GGX = GTR2
              a_x = max(0.001, roughness^2 / aspect), a_y = max(0.001, roughness^2 aspect),
              aspect = sqrt(1 - 0.9 anisotropic)                                      (tangent +x = a_x)
              G_s = G1(wi) G1(wo),  G1(w) = 2 w_z / (w_z + sqrt((a_x w_x)^2 + (a_y w_y)^2 + w_z^2))   separable Smith
  sheen       F_sheen = sheen lerp(1, C_tint, sheen_tint) S(wi·h)
  clearcoat   D_c = GTR1 = (a^2 - 1) / (pi ln(a^2) (1 + (a^2 - 1)(n·h)^2)),  a = lerp(0.1, 0.001, clearcoat_gloss),
              F_c = 0.04 + 0.96 S(wi·h)  (IOR 1.5),  G_c = separable Smith GGX with a fixed a = 0.25

B. Burley, "Physically-Based Shading at Disney", SIGGRAPH 2012 course: Practical Physically Based
Shading in Film and Game Production (with its Appendix B: GTR1/GTR2 sampling), as implemented in
Disney's BRDF Explorer (`brdfs/disney.brdf`), except that base_color is taken as linear RGB (the
explorer's mon2lin gamma is not applied; scene colours are linear here). The specular G uses a_x, a_y themselves
(Burley's 2015 course notes removed the 2012 paper's (0.5 + roughness/2)^2 remapping of G),
and the clearcoat weight is clearcoat/4.

Properties (measured by tests/test_disney.py over a parameter grid with `brdfs.albedo`):
- Reciprocal: every factor is symmetric in wi and wo (wi·h = wo·h; F_d, F_ss, G are products of a
  wi and a wo factor). float64 checks agree to 1e-10.
- NOT energy conserving (`energy_conserving=False`): Burley's diffuse is a fit to measured data,
  not a normalised lobe — with roughness 1 its grazing retro-reflection F_D90 = 2.5 lifts the
  diffuse albedo above base_color, the subsurface term's 1/(n·wi + n·wo) grows at grazing views,
  and the diffuse, sheen and clearcoat lobes are added on top of the specular lobe with no energy
  taken from them. The maximum directional albedo measured over the corner grid in
  tests/test_disney.py (base_color, metallic, subsurface, specular, anisotropic, sheen, clearcoat
  in {0, 1}, roughness in {0, 0.5, 1}, clearcoat_gloss 1, view 0/30/60/80 deg; the same maximum
  with clearcoat_gloss in {0, 1}) is 1.72
  (`MAX_ALBEDO_MEASURED`: base_color = 1, metallic = 0, subsurface = 1, specular = 1, sheen = 1,
  clearcoat = 1, roughness = 0, view 80 deg). The metallic lobe alone (metallic = 1, no sheen or
  clearcoat) stays <= 1 on that grid (max 1.000 at roughness 0, where it is almost a mirror; GGX
  with uncorrelated Smith masking loses energy at higher roughness).

Sampling: a one-sample mixture of three lobes (pbrt style; the lobe is chosen with u[..., 0] and
u[..., 0] is rescaled): cosine-weighted hemisphere for diffuse and sheen; GGX visible normals
(Heitz 2018, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4)) for the specular lobe,
density G1(wo) D_s(h) / (4 n·wo) in wi; Burley's GTR1 half-vector sampling
cos^2(theta_h) = (1 - a^(2 (1 - u0))) / (1 - a^2) for the clearcoat, density D_c cos(theta_h) / (4 wo·h).
Lobe weights: diffuse (1 - metallic)(lum(C_d) + sheen/4), specular the hemispherical mean of the
Schlick Fresnel mean(C_s0) + (1 - mean(C_s0))/21 (> 0, so the mixture density covers the whole
hemisphere wherever f > 0), clearcoat clearcoat/4 (0.04 + 0.96/21); probabilities are the
weights over their sum.

Parameters (all dimensionless, [0, 1], Burley's ranges; defaults from the BRDF Explorer except the
grey base colour): base_color (RGB), metallic, subsurface, specular, specular_tint, roughness,
anisotropic, sheen, sheen_tint, clearcoat, clearcoat_gloss.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Component, Lobe, Model, Param, Params

SPEC = (
    Param("base_color", 0.8, 0.0, 1.0, rgb=True, doc="base colour: diffuse albedo, metal's specular colour"),
    Param("metallic", 0.0, 0.0, 1.0, doc="0 dielectric, 1 metal (linear blend)"),
    Param("subsurface", 0.0, 0.0, 1.0, doc="blend of the diffuse towards Burley's subsurface approximation"),
    Param("specular", 0.5, 0.0, 1.0, doc="dielectric specular amount: F0 = 0.08 specular (0.5 = IOR 1.5)"),
    Param("specular_tint", 0.0, 0.0, 1.0, doc="tints the dielectric specular towards the base colour"),
    Param("roughness", 0.5, 0.0, 1.0, doc="roughness; GGX alpha = roughness^2"),
    Param("anisotropic", 0.0, 0.0, 1.0, doc="anisotropy; stretches the specular lobe along the tangent (+x)"),
    Param("sheen", 0.0, 0.0, 1.0, doc="grazing sheen amount (cloth)"),
    Param("sheen_tint", 0.5, 0.0, 1.0, doc="tints the sheen towards the base colour"),
    Param("clearcoat", 0.0, 0.0, 1.0, doc="clearcoat (second, GTR1 specular) lobe amount"),
    Param("clearcoat_gloss", 1.0, 0.0, 1.0, doc="clearcoat glossiness: GTR1 alpha from 0.1 (0) to 0.001 (1)"),
)

# Measured by tests/test_disney.py::test_albedo_grid_and_documented_maximum (see the docstring).
MAX_ALBEDO_MEASURED = 1.72
CLEARCOAT_ALPHA_G = 0.25
_LUM = (0.3, 0.6, 0.1)


def schlick_weight(c: Float[Array, "..."]) -> Float[Array, "..."]:
    """S(c) = (1 - c)^5 for c clipped to [0, 1]."""
    return (1.0 - jnp.clip(c, 0.0, 1.0)) ** 5


def _lerp(a, b, t):
    return a + (b - a) * t


def _tint(base_color: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """C_d / lum(C_d), white where lum(C_d) = 0."""
    lum = jnp.sum(base_color * jnp.asarray(_LUM, base_color.dtype), axis=-1, keepdims=True)
    return jnp.where(lum > 0, base_color / jnp.where(lum > 0, lum, 1.0), 1.0)


def alphas(p: Params) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """GGX (a_x, a_y) along tangent and bitangent from roughness and anisotropic."""
    aspect = jnp.sqrt(1.0 - 0.9 * p["anisotropic"])
    r2 = p["roughness"] ** 2
    return jnp.maximum(0.001, r2 / aspect), jnp.maximum(0.001, r2 * aspect)


def specular_f0(p: Params) -> Float[Array, "... 3"]:
    """C_s0: the specular colour at normal incidence."""
    cd = p["base_color"]
    dielectric = 0.08 * C.rgb(p["specular"]) * _lerp(1.0, _tint(cd), C.rgb(p["specular_tint"]))
    return _lerp(dielectric, cd, C.rgb(p["metallic"]))


def gtr2_aniso(h: Float[Array, "... 3"], ax: Float[Array, "..."], ay: Float[Array, "..."]) -> Float[Array, "..."]:
    """Anisotropic GGX (GTR2) NDF [1/sr] for a unit half vector; 0 for h_z <= 0."""
    s = (h[..., 0] / ax) ** 2 + (h[..., 1] / ay) ** 2 + h[..., 2] ** 2
    # s >= |h|^2 since a_x, a_y <= 1: the floor only guards the zero vector.
    d = 1.0 / (math.pi * ax * ay * jnp.maximum(s, 1e-6) ** 2)
    return jnp.where(h[..., 2] > 0, d, 0.0)


def gtr1(cos_h: Float[Array, "..."], a: Float[Array, "..."]) -> Float[Array, "..."]:
    """Burley's GTR1 NDF [1/sr] (gamma = 1, normalised: ∫ D cos(theta_h) dω_h = 1) for a < 1."""
    a2 = a * a
    t = 1.0 + (a2 - 1.0) * cos_h * cos_h
    return jnp.where(cos_h > 0, (a2 - 1.0) / (math.pi * jnp.log(a2) * t), 0.0)


def smith_g1_over_2cos(w: Float[Array, "... 3"], ax, ay) -> Float[Array, "..."]:
    """G1(w) / (2 w_z) = 1 / (w_z + sqrt((a_x w_x)^2 + (a_y w_y)^2 + w_z^2)), anisotropic Smith GGX."""
    root = jnp.sqrt((ax * w[..., 0]) ** 2 + (ay * w[..., 1]) ** 2 + w[..., 2] ** 2)
    return 1.0 / jnp.maximum(w[..., 2] + root, 1e-30)


def _clearcoat_alpha(p: Params):
    return _lerp(0.1, 0.001, p["clearcoat_gloss"])


def lobes(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> dict:
    """The four terms of f [1/sr] before the horizon mask: {'diffuse', 'sheen', 'specular', 'clearcoat'},
    each (..., 3); `eval` is their sum (diffuse and sheen already carry the (1 - metallic) weight)."""
    ok = C.upper(wi, wo)
    wi = jnp.where(ok[..., None], wi, jnp.array([0.0, 0.0, 1.0], wi.dtype))
    wo = jnp.where(ok[..., None], wo, jnp.array([0.0, 0.0, 1.0], wo.dtype))
    ci, co = wi[..., 2], wo[..., 2]
    h = C.normalize(wi + wo)
    ih = jnp.clip(C.half_cos(wi, wo), 0.0, 1.0)  # wi·h, accurate at grazing views
    s_i, s_o, s_h = schlick_weight(ci), schlick_weight(co), schlick_weight(ih)
    rough = p["roughness"]
    cd = p["base_color"]
    fd90 = 0.5 + 2.0 * rough * ih * ih
    fd = (1.0 + (fd90 - 1.0) * s_i) * (1.0 + (fd90 - 1.0) * s_o)
    fss90 = rough * ih * ih
    fss = (1.0 + (fss90 - 1.0) * s_i) * (1.0 + (fss90 - 1.0) * s_o)
    ss = 1.25 * (fss * (1.0 / (ci + co) - 0.5) + 0.5)
    dielectric = C.rgb(1.0 - p["metallic"])
    diffuse = dielectric * cd * C.rgb(C.INV_PI * _lerp(fd, ss, p["subsurface"]))
    sheen = dielectric * C.rgb(p["sheen"] * s_h) * _lerp(1.0, _tint(cd), C.rgb(p["sheen_tint"]))
    ax, ay = alphas(p)
    f0 = specular_f0(p)
    fs = f0 + (1.0 - f0) * C.rgb(s_h)
    gs = smith_g1_over_2cos(wi, ax, ay) * smith_g1_over_2cos(wo, ax, ay)  # = G / (4 ci co)
    specular = fs * C.rgb(gtr2_aniso(h, ax, ay) * gs)
    a_g = CLEARCOAT_ALPHA_G
    gc = smith_g1_over_2cos(wi, a_g, a_g) * smith_g1_over_2cos(wo, a_g, a_g)
    fc = 0.04 + 0.96 * s_h
    clearcoat = 0.25 * p["clearcoat"] * gtr1(h[..., 2], _clearcoat_alpha(p)) * fc * gc
    mask = ok[..., None]
    z = jnp.zeros(())
    return {
        "diffuse": jnp.where(mask, diffuse, z),
        "sheen": jnp.where(mask, sheen, z),
        "specular": jnp.where(mask, specular, z),
        "clearcoat": jnp.where(mask, jnp.broadcast_to(C.rgb(clearcoat), specular.shape), z),
    }


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    t = lobes(p, wi, wo)
    return t["diffuse"] + t["sheen"] + t["specular"] + t["clearcoat"]


# ---- sampling --------------------------------------------------------------------------------

def _lobe_probs(p: Params):
    """(p_diffuse, p_specular, p_clearcoat), each (...,), summing to 1 (see the module docstring)."""
    w_d = (1.0 - p["metallic"]) * (jnp.sum(p["base_color"] * jnp.asarray(_LUM), axis=-1) + 0.25 * p["sheen"])
    f0 = jnp.mean(specular_f0(p), axis=-1)
    w_s = f0 + (1.0 - f0) / 21.0
    w_c = 0.25 * p["clearcoat"] * (0.04 + 0.96 / 21.0)
    tot = w_d + w_s + w_c  # >= 1/21
    return w_d / tot, w_s / tot, w_c / tot


def _vec(x, y, z):
    """Stack three broadcastable arrays into (..., 3)."""
    return jnp.stack(jnp.broadcast_arrays(x, y, z), axis=-1)


_sample_diffuse = C.diffuse_component


def _sample_specular(p: Params, wo, u):
    """GGX visible-normal sampling (Heitz 2018), reflected about the sampled microfacet normal."""
    ax, ay = alphas(p)
    vh = C.normalize(_vec(ax * wo[..., 0], ay * wo[..., 1], jnp.maximum(wo[..., 2], 0.0)))
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    ok = lensq > 1e-14
    inv = 1.0 / jnp.sqrt(jnp.where(ok, lensq, 1.0))
    zero = jnp.zeros_like(lensq)
    t1 = jnp.where(ok[..., None], _vec(-vh[..., 1] * inv, vh[..., 0] * inv, zero), _vec(zero + 1.0, zero, zero))
    t2 = jnp.cross(vh, t1)
    r = C.safe_sqrt(u[..., 0])  # finite gradient at u0 = 0 (the rescaled u0 carries lobe-probability gradients)
    phi = 2.0 * math.pi * u[..., 1]
    p1 = r * jnp.cos(phi)
    p2 = r * jnp.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2])
    p2 = (1.0 - s) * C.safe_sqrt(1.0 - p1 * p1) + s * p2
    nh = p1[..., None] * t1 + p2[..., None] * t2 + C.safe_sqrt(1.0 - p1 * p1 - p2 * p2)[..., None] * vh
    h = C.normalize(_vec(ax * nh[..., 0], ay * nh[..., 1], jnp.maximum(nh[..., 2], 0.0)))
    return C.reflect_about(wo, h)


def _pdf_specular(p: Params, wo, wi):
    """G1(wo) D(h) / (4 n·wo) = D(h) G1(wo) / (2 n·wo) / 2, the VNDF density in wi [1/sr]."""
    ax, ay = alphas(p)
    h = C.normalize(wi + wo)
    return 0.5 * gtr2_aniso(h, ax, ay) * smith_g1_over_2cos(wo, ax, ay)


def _sample_clearcoat(p: Params, wo, u):
    a2 = _clearcoat_alpha(p) ** 2
    # cos^2(theta_h) = (1 - a2^(1 - u0)) / (1 - a2); sin^2 = a2 (a2^(-u0) - 1) / (1 - a2), both
    # without cancellation (the clearcoat lobe is as narrow as a = 0.001)
    log_a2 = jnp.log(a2)
    cos2 = -jnp.expm1((1.0 - u[..., 0]) * log_a2) / (1.0 - a2)
    sin2 = a2 * jnp.expm1(-u[..., 0] * log_a2) / (1.0 - a2)
    h = C.spherical_cs(C.safe_sqrt(cos2), C.safe_sqrt(sin2), 2.0 * math.pi * u[..., 1])
    return C.reflect_about(wo, h)


def _pdf_clearcoat(p: Params, wo, wi):
    h = C.normalize(wi + wo)
    return gtr1(h[..., 2], _clearcoat_alpha(p)) * jnp.maximum(h[..., 2], 0.0) * C.half_vector_jacobian(wi, wo)


def pdf(p: Params, wo: Float[Array, "... 3"], wi: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Mixture density of `sample` [1/sr], (...,); 0 unless both directions are above the horizon."""
    ok = C.upper(wi, wo)
    # Harmless directions where the density is 0 anyway, so no 1/0 reaches values or gradients.
    z = jnp.array([0.0, 0.0, 1.0], wi.dtype)
    wi = jnp.where(ok[..., None], wi, z)
    wo = jnp.where(ok[..., None], wo, z)
    pd, ps, pc = _lobe_probs(p)
    d = pd * C.cosine_pdf(wi) + ps * _pdf_specular(p, wo, wi) + pc * _pdf_clearcoat(p, wo, wi)
    return jnp.where(ok, d, 0.0)


def sample(p: Params, wo: Float[Array, "... 3"], u: Float[Array, "... 2"]):
    """(wi (..., 3), weight = f cos / pdf (..., 3), pdf (...,)); failed samples have weight 0, pdf 0."""
    pd, ps, pc = _lobe_probs(p)
    u0, u1 = u[..., 0], u[..., 1]
    c1 = pd
    c2 = pd + ps
    pick_d = u0 < c1
    pick_s = (~pick_d) & (u0 < c2)
    # Rescale u0 inside the chosen lobe's interval back to [0, 1).
    ud = jnp.clip(C.safe_div(u0, pd), 0.0, 1.0 - 1e-7)
    us = jnp.clip(C.safe_div(u0 - c1, ps), 0.0, 1.0 - 1e-7)
    uc = jnp.clip(C.safe_div(u0 - c2, pc), 0.0, 1.0 - 1e-7)
    ud, us, uc, u1 = jnp.broadcast_arrays(ud, us, uc, u1)
    wi_d = _sample_diffuse(p, wo, jnp.stack([ud, u1], axis=-1))
    wi_s = _sample_specular(p, wo, jnp.stack([us, u1], axis=-1))
    wi_c = _sample_clearcoat(p, wo, jnp.stack([uc, u1], axis=-1))
    wi = jnp.where(pick_d[..., None], wi_d, jnp.where(pick_s[..., None], wi_s, wi_c))
    dens = pdf(p, wo, wi)
    f = eval(p, wi, wo)
    ok = dens > 0
    weight = jnp.where(ok[..., None], f * C.safe_div(jnp.maximum(wi[..., 2], 0.0), dens)[..., None], 0.0)
    return wi, weight, dens


MODEL = Model(
    name="disney",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    flags=Lobe.REFLECTION | Lobe.DIFFUSE | Lobe.GLOSSY,
    energy_conserving=False,
    reciprocal=True,
    diffuse=lambda p: p["base_color"],
    mixture=(
        Component(lambda p, wo: _lobe_probs(p)[0], _sample_diffuse),
        Component(lambda p, wo: _lobe_probs(p)[1], _sample_specular),
        Component(lambda p, wo: _lobe_probs(p)[2], _sample_clearcoat),
    ),
    doc=__doc__,
)
