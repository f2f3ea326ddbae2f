"""Materials at hit points: parameter gathering (with textures), glass, and per-hit model masks.

A scene's materials are grouped by model (`jaxrt.scene.Materials`): per hit, the model is a
gather of `model_id` and the parameters a gather of that model's table row, so shading a batch of
hits with several models is one evaluation per model plus a select.

Measured models (`brdfs.is_measured`: a neural BRDF's weights, a MERL table) are the exception:
their parameter rows are data, kilobytes to megabytes each (a MERL table is 17.5 MB), so gathering
a row per hit is out of the question. `hit_params` gives them as `MeasuredRows` (the table and each
hit's row) and `at_hits` evaluates such a model once per row, on every hit, with that row's
unbatched pytree (which broadcasts against the hits' directions like any parameter pytree), keeping
each hit's own row: a scene with R measured materials of one model costs R evaluations per hit.
"""

from __future__ import annotations

import jax.numpy as jnp
from typing import NamedTuple

import jax
from jaxtyping import Array, Bool, Float, Int

import brdfs
from jaxrt.shading import textures as _tx
from jaxrt.shading.surface import Surface, from_local, glass_frame, to_local


__all__ = [
    "MeasuredRows", "gather_params", "hit_params", "at_hits", "glass_fresnel", "glass_split", "model_masks", "is_glass",
    "delta_and_glass", "surface_albedo",
]


class MeasuredRows(NamedTuple):
    """A measured model's parameters at a batch of hits: `table` its parameter table (name -> (R, ...)),
    `row` (B,) each hit's row in it (see the module docstring)."""

    table: dict
    row: Int[Array, "B"]


def hit_params(materials, mat: Int[Array, "B"], k: int, uv: Float[Array, "B 2"] | None = None):
    """Model k's parameters at every slot, for `at_hits`: the gathered pytree (`gather_params`) of an
    analytic model, `MeasuredRows` of a measured one."""
    if brdfs.is_measured(materials.models[k]):
        return MeasuredRows(materials.params[k], jnp.where(materials.model_id[mat] == k, materials.row[mat], 0))
    return gather_params(materials, mat, k, uv)


def at_hits(params, fn, extra_dims: int = 0):
    """fn(p) for every slot of a batch of hits, p being each slot's parameters (from `hit_params`).

    fn returns a pytree of arrays with the slots' leading dimension B. `extra_dims` inserts that many
    axes after B in a gathered pytree so that it broadcasts against directions of shape (B, L, 3),
    say; a measured model's unbatched row broadcasts against them as it is.
    """
    if not isinstance(params, MeasuredRows):
        return fn({n: x.reshape(x.shape[:1] + (1,) * extra_dims + x.shape[1:]) for n, x in params.items()})
    rows = next(iter(params.table.values())).shape[0]
    out = fn({n: t[0] for n, t in params.table.items()})
    for r in range(1, rows):
        here = params.row == r
        y = fn({n: t[r] for n, t in params.table.items()})
        out = jax.tree.map(lambda a, b: jnp.where(here.reshape(here.shape + (1,) * (a.ndim - 1)), a, b), y, out)
    return out


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



def glass_fresnel(materials, mat: Int[Array, "..."], k: int, p, cos_i, entering):
    """Dielectric reflectance R of glass model k for materials `mat`, with each material's Fresnel
    choice: Schlick's approximation (C. Schlick, Computer Graphics Forum 13(3), 1994) or the exact
    unpolarised Fresnel equations (Born & Wolf, *Principles of Optics*, sec. 1.5), `brdfs.glass.fresnel`.
    When all of a scene's glass materials make one choice (static: `materials.fresnel`) only that one
    is evaluated, so Schlick-only scenes run the very arithmetic they ran before the choice existed;
    mixed scenes evaluate both and select per slot."""
    f = brdfs.get(materials.models[k]).dielectric.fresnel
    used = {c for c in materials.fresnel if c}  # "" marks opaque materials
    if used <= {"schlick"}:
        return f(p, cos_i, entering)
    if used == {"exact"}:
        return f(p, cos_i, entering, exact=True)
    exact = jnp.asarray([c == "exact" for c in materials.fresnel])[mat]
    return jnp.where(exact, f(p, cos_i, entering, exact=True), f(p, cos_i, entering))


def glass_split(materials, s: Surface, d, k: int):
    """(R, reflected dir, transmitted dir, transmission valid) for glass (model k) at every slot."""
    glass = brdfs.get(materials.models[k])
    p = gather_params(materials, s.material, k)
    frame = glass_frame(s, d)
    wo = to_local(-d, frame)
    entering = wo[:, 2] > 0
    d_ = glass.dielectric
    r = glass_fresnel(materials, s.material, k, p, jnp.abs(wo[:, 2]), entering)
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
        model = brdfs.get(name)
        p = hit_params(materials, s.material, k, s.uv)
        a = at_hits(p, lambda q, model=model: jnp.broadcast_to(model.diffuse_albedo(q), albedo.shape))
        albedo = jnp.where(sel[:, None], a.astype(albedo.dtype), albedo)
    return albedo
