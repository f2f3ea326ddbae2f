"""Shadow rays that pass through glass: the Fresnel transmittance of the glass surfaces they cross.

Whitted's shadow rays (Größler & Zettwitz, "An interactive ray tracing system based on Nvidia
OptiX", 2015) are blocked by any surface, so glass casts the shadow of an opaque object. Here a
shadow ray towards a point light carries instead

    V = Π over the glass surfaces it crosses (1 − F(θ))          (0 if it meets an opaque surface)

with F the crossed material's Fresnel reflectance (Schlick or the exact Fresnel equations, as the
material chooses: `jaxrt.shading.material.glass_fresnel`) and θ the angle between the shadow ray
and the surface normal.

The approximation: the shadow ray is *not refracted* -- it stays the straight segment from the hit
point to the light -- and every crossing is weighted as if the ray arrived from outside at θ
(so there is no total internal reflection on shadow rays). For a slab with parallel faces this is
the transmittance of the real refracted path, which leaves at the angle it entered, so the
transmitted fraction is T(θ)² (Fresnel's reflectance is the same for a ray and its reverse); what it
ignores is the lateral shift and the change of convergence of the refracted light (no caustics:
light focused by a glass sphere arrives as a plain, dimmed shadow). There is no absorption inside
the glass (the glass model is clear).

The crossings are found by closest-hit steps in static shapes: the shadow rays first take the
existing any-hit test (`occluded`), and only the blocked ones step from hit to hit, at most
`MAX_CROSSINGS` glass surfaces, each step a closest-hit query over what is left of the segment; a
ray still inside its budget after them is tested once more for any hit and counts as blocked if it
has one. Unblocked rays keep V = 1 exactly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

import brdfs
from jaxrt.shading.material import gather_params, glass_fresnel, is_glass
from jaxrt.shading.surface import dot, normalize, offset_scale

__all__ = ["MAX_CROSSINGS", "transmittance"]

# glass surfaces a shadow ray may cross before it counts as blocked: two glass objects in a row
# (each entered and left), enough for the scenes this renderer ships
MAX_CROSSINGS = 4


def transmittance(scene, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
                  tmax: Float[Array, " N"]) -> Float[Array, " N"]:
    """V in [0, 1] of each shadow segment origins + t·directions, t in [0, tmax] (unit directions;
    tmax < 0 for no ray, V = 0). See the module docstring."""
    geo, mats = scene.geometry, scene.materials
    live = tmax >= 0
    occ = geo.occluded(origins, directions, tmax, from_end=True) & live
    wdtype = jnp.result_type(mats.delta.dtype, jnp.float32)
    v0 = jnp.where(live & ~occ, 1.0, 0.0).astype(wdtype)
    glass_models = [k for k, name in enumerate(mats.models) if brdfs.get(name).delta]

    def cond(carry):
        i, _, _, going = carry
        return (i < MAX_CROSSINGS) & jnp.any(going)

    def body(carry):
        i, v, tmin, going = carry
        hit = geo.intersect(origins, directions, tmin, jnp.where(going, tmax, -1.0))
        found = going & (hit.prim >= 0)
        prim = jnp.where(found, hit.prim, -1)
        s = geo.surface(prim, hit.u, hit.v)
        glass = found & is_glass(mats, s.material)
        # the normal `glass_frame` gives the camera rays (shading normal unless it disagrees about
        # the side), so a shadow ray and a camera ray along the same line see the same F
        wo = -directions
        agree = jnp.sign(dot(wo, s.ns)) == jnp.sign(dot(wo, s.ng))
        n = normalize(jnp.where(agree[:, None], s.ns, s.ng))
        cos = jnp.abs(dot(directions, n))
        outside = jnp.ones(cos.shape, bool)  # as if arriving from outside (module docstring)
        f = jnp.zeros(cos.shape, wdtype)
        for k in glass_models:
            fk = glass_fresnel(mats, s.material, k, gather_params(mats, s.material, k), cos, outside)
            f = jnp.where(glass & (mats.model_id[s.material] == k), fk.astype(wdtype), f)
        # opaque: blocked. Nothing hit: the light is reached -- except on the first step, where the
        # any-hit test saw something the closest-hit query misses (float rounding at an edge), which
        # stays blocked as before glass let light through
        blocked = (found & ~glass) | (going & ~found & (i == 0))
        v = jnp.where(glass, v * (1.0 - f), jnp.where(blocked, 0.0, v))
        tmin = jnp.where(glass, hit.t + 2.0 * offset_scale(s.p)[:, 0], tmin)
        return i + 1, v, tmin, glass

    if not glass_models:
        return v0
    start = (jnp.asarray(0), jnp.where(occ, 1.0, v0).astype(wdtype), jnp.zeros_like(tmax), occ)
    _, v, tmin, going = jax.lax.while_loop(cond, body, start)
    # still crossing glass after MAX_CROSSINGS: blocked if anything is left on the segment
    rest = geo.occluded(origins + tmin[:, None] * directions, directions, jnp.where(going, tmax - tmin, -1.0))
    rest = rest & going
    return jnp.where(rest, 0.0, v)
