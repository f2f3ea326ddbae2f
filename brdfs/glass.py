"""Smooth dielectric (glass): a delta BSDF with Fresnel reflection and Snell refraction.

The outside medium has index 1, the inside `n_t`. In the local frame the normal +z points to the
outside, so wo.z > 0 means the viewer is outside (the path enters the glass) and wo.z < 0 means
it is inside (the path leaves it, where total internal reflection can happen).

`MODEL.flags` is REFLECTION | TRANSMISSION | DELTA. The interface functions are in the typed record
`MODEL.dielectric` (a `brdfs.base.Dielectric`; all pure, leading batch dims broadcast):

    fresnel(p, cos_i, entering, exact=False) -> R (...,)
        Unpolarised reflectance for a ray arriving with cosine cos_i >= 0 on its own side;
        entering: bool (...,) True when arriving from outside (eta = n_t / 1), False from inside
        (eta = 1 / n_t). Default: Schlick, F0 = ((n_t - 1)/(n_t + 1))^2, evaluated with the cosine
        on the *less dense* (outside) side -- cos_i when entering, cos_t when leaving -- which is
        what makes Schlick symmetric under reversal; R = 1 under total internal reflection.
        exact=True: the full dielectric Fresnel equations (mean of s and p polarisations).
    reflect(wo) -> wi (..., 3)                 mirror direction (-wo_x, -wo_y, wo_z)
    refract(p, wo) -> (wt (..., 3), valid (...,) bool)
        Snell refraction of wo through the interface with the correct IOR ratio for the side wo
        is on; valid is False under total internal reflection (wt is then the mirror direction).
    split(p, wo) -> (R, wr, wt, transmits)    all of the above at once for a view direction wo
                                               (transmits: valid and R < 1)

    MODEL.sample(p, wo, u, exact=False) -> (wi, weight, pdf)
        Chooses reflection with probability R (u[..., 0] < R) and transmission otherwise; weight is
        1 (RGB ones): R / R or (1 - R) / (1 - R); pdf is the discrete probability of the chosen
        branch (R or 1 - R), as pbrt's specular BSDFs report it -- it is not a solid-angle density.
    MODEL.pdf(p, wo, wi) -> 0                  a delta distribution has no density w.r.t. solid angle
    MODEL.eval is None; MODEL.diffuse_albedo(p) is 1 (white, for an albedo AOV).

Radiance scaling on transmission: the (eta_t/eta_i)^2 factor of non-symmetric radiance transport
is *omitted* (weight 1), as in Whitted-style renderers (and in Größler & Zettwitz, "An interactive
ray tracing system based on Nvidia OptiX", 2015). For a closed object seen
from outside with lights outside, every path enters and leaves the glass equally often, so the
factors cancel exactly; only paths that start or end inside would differ.

References: the dielectric conventions of pbrt-v4 (Pharr, Jakob, Humphreys,
*Physically Based Rendering*, 4th ed., sec. 9.3-9.5); C. Schlick, "An inexpensive BRDF model for
physically-based rendering", Computer Graphics Forum 13(3), 1994.

Parameters: n_t (1-3) index of refraction of the inside medium.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from brdfs import _common as C
from brdfs.base import Dielectric, Lobe, Model, Param, Params

SPEC = (Param("n_t", 1.5, 1.0, 3.0, doc="index of refraction inside the object (outside is 1)"),)


def _cos_t(eta, cos_i):
    """(cos of the transmitted angle, TIR flag) for relative index eta = eta_t / eta_i."""
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    tir = sin2_t >= 1.0
    return C.safe_sqrt(1.0 - sin2_t), tir


def fresnel(
    p: Params, cos_i: Float[Array, "..."], entering: Bool[Array, "..."], exact: bool = False
) -> Float[Array, "..."]:
    """Dielectric reflectance R in [0, 1] (see module docstring); cos_i >= 0."""
    n_t = p["n_t"]
    cos_i = jnp.clip(cos_i, 0.0, 1.0)
    eta = jnp.where(entering, n_t, 1.0 / n_t)
    cos_t, tir = _cos_t(eta, cos_i)
    if exact:
        r_par = C.safe_div(eta * cos_i - cos_t, eta * cos_i + cos_t)
        r_perp = C.safe_div(cos_i - eta * cos_t, cos_i + eta * cos_t)
        r = 0.5 * (r_par**2 + r_perp**2)
        # cos_i = 0 (grazing) is total reflection as well.
        r = jnp.where(cos_i + cos_t > 0, r, 1.0)
    else:
        f0 = ((n_t - 1.0) / (n_t + 1.0)) ** 2
        c = jnp.where(entering, cos_i, cos_t)
        r = f0 + (1.0 - f0) * (1.0 - c) ** 5
    return jnp.where(tir, 1.0, r)


def reflect(wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    return C.reflect_z(wo)


def refract(p: Params, wo: Float[Array, "... 3"]) -> tuple[Float[Array, "... 3"], Bool[Array, "..."]]:
    """Refracted direction (unit, on the other side of the interface) and a not-TIR flag."""
    entering = wo[..., 2] > 0
    eta = jnp.where(entering, p["n_t"], 1.0 / p["n_t"])
    cos_i = jnp.abs(wo[..., 2])
    cos_t, tir = _cos_t(eta, cos_i)
    side = jnp.where(entering, 1.0, -1.0)  # normal on wo's side
    n = jnp.zeros_like(wo).at[..., 2].set(side)
    wt = -wo / eta[..., None] + (cos_i / eta - cos_t)[..., None] * n
    return jnp.where(tir[..., None], reflect(wo), wt), ~tir


def sample(p: Params, wo: Float[Array, "... 3"], u: Float[Array, "... 2"], exact: bool = False):
    """(wi, weight (..., 3), pdf (...,)): reflection with probability R, else transmission."""
    entering = wo[..., 2] > 0
    r = fresnel(p, jnp.abs(wo[..., 2]), entering, exact=exact)
    wt, _ = refract(p, wo)
    pick_r = u[..., 0] < r
    wi = jnp.where(pick_r[..., None], reflect(wo), wt)
    prob = jnp.where(pick_r, r, 1.0 - r)
    weight = jnp.ones(wi.shape, wi.dtype)
    return wi, weight, prob


def pdf(p: Params, wo: Float[Array, "... 3"], wi: Float[Array, "... 3"]) -> Float[Array, "..."]:
    return jnp.zeros(jnp.broadcast_shapes(wo.shape, wi.shape)[:-1], wo.dtype)


MODEL = Model(
    name="glass",
    spec=SPEC,
    eval=None,
    sample=sample,
    pdf=pdf,
    flags=Lobe.REFLECTION | Lobe.TRANSMISSION | Lobe.DELTA,
    energy_conserving=True,
    reciprocal=True,
    dielectric=Dielectric(fresnel=fresnel, reflect=reflect, refract=refract),
    doc=__doc__,
)
