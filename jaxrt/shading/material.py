"""Materials at hit points: parameter gathering (with textures), glass, and per-hit model masks.

A scene's materials are grouped by model (`jaxrt.scene.Materials`): per hit, the model is a
gather of `model_id` and the parameters a gather of that model's table row, so shading a batch of
hits with several models is one evaluation per model plus a select.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

import brdfs
from jaxrt.shading import textures as _tx
from jaxrt.shading.surface import Surface, from_local, glass_frame, to_local


def gather_params(materials, mat: Int[Array, "B"], k: int, uv: Float[Array, "B 2"] | None = None) -> dict:
    """Model k's parameters for every slot (rows of other models' materials point at row 0).

    With `uv`, a textured parameter (`materials.bindings`) takes its texture's value at the slot's
    uv (jaxrt.shading.textures.lookup) instead of the table's constant; uv=None gives the constants.
    """
    row = jnp.where(materials.model_id[mat] == k, materials.row[mat], 0)
    out = {name: table[row] for name, table in materials.params[k].items()}
    if uv is not None:
        model = brdfs.get(materials.models[k])
        for mk, r, name, t in getattr(materials, "bindings", ()):
            if mk != k:
                continue
            sel = (materials.model_id[mat] == k) & (materials.row[mat] == r)
            val = _tx.value(materials.textures[t], uv, model.param(name).rgb)
            out[name] = jnp.where(sel[:, None] if val.ndim == 2 else sel, val, out[name])
    return out



def glass_split(materials, s: Surface, d, k: int):
    """(R, reflected dir, transmitted dir, transmission valid) for glass (model k) at every slot."""
    glass = brdfs.get(materials.models[k])
    p = gather_params(materials, s.material, k)
    frame = glass_frame(s, d)
    wo = to_local(-d, frame)
    entering = wo[:, 2] > 0
    d_ = glass.dielectric
    r = d_.fresnel(p, jnp.abs(wo[:, 2]), entering)
    wt, ok = d_.refract(p, wo)
    wr = d_.reflect(wo)
    return r, from_local(wr, frame), from_local(wt, frame), ok & (r < 1.0)



def model_masks(materials, mat):
    mid = materials.model_id[mat]
    return [(mid == k) for k in range(len(materials.models))]



def is_glass(materials, mat):
    out = jnp.zeros(mat.shape, bool)
    for k, name in enumerate(materials.models):
        if brdfs.get(name).delta:
            out = out | (materials.model_id[mat] == k)
    return out



def delta_and_glass(mats, s: Surface, found: Bool[Array, "B"]):
    """(δ of opaque hits, 0 elsewhere; glass hit mask), each (B,): the branch coefficients trace and
    shade both derive the ray tree's throughput from."""
    glass = found & is_glass(mats, s.material)
    return jnp.where(found & ~glass, mats.delta[s.material], 0.0), glass


def surface_albedo(materials, s: Surface) -> Float[Array, "B 3"]:
    """The diffuse colour of each hit's material (the albedo AOV): each model's `diffuse_albedo` hook
    (rho_d, Disney's base_color, 1 for delta materials, 0 for models without a diffuse lobe)."""
    albedo = jnp.zeros(s.p.shape)
    for k, name in enumerate(materials.models):
        sel = materials.model_id[s.material] == k
        p = gather_params(materials, s.material, k, s.uv)
        albedo = jnp.where(sel[:, None], brdfs.get(name).diffuse_albedo(p).astype(albedo.dtype), albedo)
    return albedo
