"""Lambertian (ideal diffuse) reflection.

    f(wi, wo) = rho_d / pi                       for cos(theta_i), cos(theta_o) > 0, else 0

J. H. Lambert, *Photometria*, 1760. Albedo is exactly rho_d at every view angle, so the model is
energy conserving for rho_d <= 1 and trivially reciprocal. Sampling is cosine-weighted
(density cos(theta_i)/pi), which makes every sample's weight exactly rho_d.

Parameters: rho_d (RGB, 0-1) diffuse albedo.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Lobe, Model, Param, Params

SPEC = (Param("rho_d", 0.8, 0.0, 1.0, rgb=True, doc="diffuse albedo"),)


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    ok = C.upper(wi, wo)
    return jnp.where(ok[..., None], p["rho_d"] * C.INV_PI, 0.0)


def _ps(p: Params) -> Float[Array, "..."]:
    return jnp.zeros_like(p["rho_d"][..., 0])


_mixture_sample, pdf, _components = C.mixture(_ps, C.diffuse_component, lambda p, wo, wi: C.cosine_pdf(wi), eval)


def sample(p: Params, wo: Float[Array, "... 3"], u: Float[Array, "... 2"]):
    """(wi, weight, pdf): the mixture's sampler with its specular probability 0 written out, so that
    the never-chosen branch's direction (trigonometry per sample) is not computed. Same numbers as
    the mixture's: its lobe choice rescales u0 by (u0 - 0) / (1 - 0) = u0 exactly."""
    ud = jnp.clip(u[..., 0], 0.0, 1.0 - 1e-7)
    ud, u1 = jnp.broadcast_arrays(ud, u[..., 1], jnp.zeros_like(p["rho_d"][..., 0]))[:2]
    wi = C.diffuse_component(p, wo, jnp.stack([ud, u1], axis=-1))
    pd = jnp.where(C.upper(wi, wo), C.cosine_pdf(wi), 0.0)
    f = eval(p, wi, wo)
    weight = jnp.where((pd > 0)[..., None], f * C.safe_div(jnp.maximum(wi[..., 2], 0.0), pd)[..., None], 0.0)
    return wi, weight, pd

MODEL = Model(
    name="lambert",
    spec=SPEC,
    eval=eval,
    sample=sample,
    pdf=pdf,
    flags=Lobe.REFLECTION | Lobe.DIFFUSE,
    energy_conserving=True,
    reciprocal=True,
    diffuse=lambda p: p["rho_d"],
    mixture=_components[:1],  # the "specular" branch is never chosen (ps = 0)
    doc=__doc__,
)
