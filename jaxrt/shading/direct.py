"""Direct lighting from point lights, and the radiance of escaping rays.

The Whitted model of Größler & Zettwitz ("An interactive ray tracing system based on Nvidia OptiX",
2015), for a hit on an opaque material with mirror coefficient δ:

    L(x, wo) = L_e(x, wo) + δ·L(x, ω_r) + (1 − δ)·Σ_lights f_r(wi, wo)·I·cosθ_i / d² · V(x, light)

where L_e is the emission of the hit material (scene-file `emission`; one-sided: towards the side
the triangle's winding normal points to, as the path tracer's emitters), so emitters are seen
directly and in mirrors and glass, as by the path tracer's camera rays and delta bounces. Whitted
does not light other surfaces with emitters (point lights only); the path tracer does.
`direct_lighting` is the sum over lights, `local_radiance` what one ray collects at its own hit
before its path throughput. The path tracer's next-event estimation for point lights uses the same
`direct_terms`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

import brdfs
from jaxrt import envmap
from jaxrt import lights as _lights
from jaxrt.shading.material import at_hits, hit_params
from jaxrt.shading.surface import Surface, dot, local_frame, oriented, to_local


def local_radiance(scene, s: Surface, d, visible, found, delta, glass) -> Float[Array, "B 3"]:
    """Radiance a ray (B,) collects at its own hit, before its path throughput: L_e + (1 − δ)·direct
    on opaque hits, 0 on glass (all of it is carried by the children), the escaped radiance on misses."""
    direct = (1.0 - delta)[:, None] * direct_lighting(scene, s, d, visible)
    direct = direct + emitted_radiance(scene, s, d)
    local = jnp.where(found[:, None], direct, escaped_radiance(scene, d))
    return jnp.where(glass[:, None], 0.0, local)


def emitted_radiance(scene, s: Surface, d: Float[Array, "B 3"]) -> Float[Array, "B 3"]:
    """L_e of the hit surfaces seen along d: the material's emission on the side the geometric
    normal (winding) points to, 0 behind it and for scenes without emitters, (B, 3)."""
    al = scene.area_lights
    if al is None or al.count == 0:
        return jnp.zeros(s.p.shape)
    front = dot(d, s.ng) < 0
    return jnp.where(front[:, None], al.emission[s.material], 0.0)



def direct_terms(scene, s: Surface, d: Float[Array, "B 3"], visible: Bool[Array, "B L"]):
    """What the direct-lighting sum needs besides the BRDF, for hits `s` seen along rays `d`.

    Returns:
        wi: (B, L, 3) local-frame directions to the lights; wo: (B, 1, 3) local direction to the
        viewer; light: (B, L, 3) cosθ_i·I/d²·V per light (0 behind the geometric surface or shadowed;
        `visible` is bool, or a float transmittance V in [0, 1]).
        Σ_l f(wi, wo)·light is the direct term of the Whitted model above, without its (1 − δ).
    """
    ng, ns, _ = oriented(s, d)
    frame = local_frame(ns, s.tangent)
    wi, _, scale = _lights.incident(scene.lights, s.p)  # (B, L, 3), (B, L, 3)
    frame = tuple(x[:, None, :] for x in frame)
    # wo made (B, 1, 3) before its local components are stacked, not after: a model that reads only
    # cosines (wo_l[..., 2]: Lambert) then slices the stack itself, which XLA simplifies, so the
    # tangent, bitangent and the dot products with them are never computed (a reshape between the
    # stack and the slice kept all of them on the CPU: gathers and a cross product per hit)
    wo_l = to_local(-d[:, None, :], frame)
    wi_l = to_local(wi, frame)
    cos = jnp.maximum(wi_l[..., 2], 0.0)
    above = dot(wi, ng[:, None, :]) > 0
    if visible.dtype == bool:
        light = jnp.where(visible & above, cos, 0.0)[..., None] * scale
    else:  # a transmittance in [0, 1] (shadow rays through glass: jaxrt.shading.shadows)
        light = jnp.where(above, visible * cos, 0.0)[..., None] * scale
    return wi_l, wo_l, light



def direct_lighting(scene, s: Surface, d: Float[Array, "B 3"], visible: Bool[Array, "B L"]) -> Float[Array, "B 3"]:
    """Σ_l f_r·I·cosθ/d²·V over the point lights for opaque models (without the 1 − δ), (B, 3);
    0 on delta materials."""
    mats = scene.materials
    wi_l, wo_l, weight = direct_terms(scene, s, d, visible)
    out = jnp.zeros(s.p.shape)
    for k, name in enumerate(mats.models):
        model = brdfs.get(name)
        if model.delta:
            continue
        sel = mats.model_id[s.material] == k
        p = hit_params(mats, s.material, k, s.uv)
        f = at_hits(p, lambda q, model=model: model.eval(q, wi_l, wo_l), extra_dims=1)  # (B, L, 3)
        # the sum over the (few) lights written out: XLA:CPU runs a reduction over a short axis as a
        # slow library (YNNPACK) fusion
        fw = f * weight
        if fw.shape[1] == 0:  # no point lights (area lights only: their light is the path tracer's)
            total = jnp.zeros(fw.shape[:1] + fw.shape[2:], fw.dtype)
        else:
            total = fw[:, 0]
            for l in range(1, fw.shape[1]):
                total = total + fw[:, l]
        out = jnp.where(sel[:, None], total, out)
    return out



def escaped_radiance(scene, d: Float[Array, "B 3"]) -> Float[Array, "B 3"]:
    """Radiance of rays that leave the scene along d: the environment if the scene has one, else
    the background."""
    if scene.environment is None:
        return jnp.broadcast_to(scene.settings.background, d.shape)
    return envmap.radiance(scene.environment, d)
