"""A fit-specific G-buffer: only the ray-tree nodes that see the fitted material.

With the fitted material opaque and its δ held fixed, the ray tree, every path throughput and
every other surface's contribution are constant during a fit. The image is therefore

    image = constant + Σ_nodes w_node · Σ_lights f(params; wi_l, wo) · cosθ_l · I_l / d_l² · V_l

over the tree nodes (any depth: seen directly or in mirrors/glass) whose surface has the fitted
material, with w_node = path throughput · (1 − δ) / spp. `build` gathers those nodes once (local
directions and light weights, from the same `jaxrt.shading` functions the renderer shades
with); `shade` is then one BRDF evaluation per node and light plus a segment sum — about as
little work as a fit iteration can do. `tests/test_fit_compact.py` checks it against the full
renderer's `shade` for random parameters.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

import brdfs
from jaxrt import integrators
from jaxrt.scene import edit
from jaxrt.shading.direct import direct_terms


class FitBuffer(eqx.Module):
    """Nodes of all K views that see the fitted material.

    pixel: (N,) flat index into the (K·H·W) images; weight: (N,) path throughput·(1 − δ)/spp;
    wi: (N, L, 3) local directions to the lights; wo: (N, 3) local direction to the viewer;
    light: (N, L, 3) cosθ·I/d²·V per light; constant: (K, H, W, 3) everything else.
    """

    pixel: Int[Array, "N"]
    weight: Float[Array, "N"]
    wi: Float[Array, "N L 3"]
    wo: Float[Array, "N 3"]
    light: Float[Array, "N L 3"]
    constant: Float[Array, "K H W 3"]


@jax.jit
def face_material(geometry, prim):
    """Material id of faces `prim` (one compiled call; eager, it would compile every op)."""
    return geometry.face_material(prim)


@jax.jit
def _node_terms(scene, prim, u, v, d, vis):
    return direct_terms(scene, scene.geometry.surface(prim, u, v), d, vis)


def _nodes(gb, scene, material: int):
    """Per-view node data (numpy) for the nodes whose hit has `material`."""
    st = scene.settings
    keep = np.asarray(gb.active) & (np.asarray(gb.prim) >= 0)
    mat = np.asarray(face_material(scene.geometry, gb.prim))
    sel = keep & (mat == material)
    d_idx, b_idx = np.nonzero(sel)
    prim, u, v, d, vis = (jax.device_put(np.asarray(x)[d_idx, b_idx])
                          for x in (gb.prim, gb.u, gb.v, gb.direction, gb.visible))
    wi, wo, light = _node_terms(scene, prim, u, v, d, vis)
    delta = np.asarray(scene.materials.delta)[material]
    weight = np.asarray(gb.weight)[d_idx, b_idx] * (1.0 - delta) / st.spp
    pixel = np.asarray(gb.pixel)[d_idx, b_idx]
    return pixel, weight, np.asarray(wi), np.asarray(wo)[:, 0], np.asarray(light)


def build(gbuffers, scenes, model_index: int, row: int, material: int, params0) -> FitBuffer:
    """Gather the fitted material's nodes from every view's G-buffer (done once per fit setup).

    `params0` is the parameter set the scenes currently hold for the material; the constant image
    is each view's full render minus that material's contribution at `params0`.
    """

    parts, consts = [], []
    for k, (gb, sc) in enumerate(zip(gbuffers, scenes)):
        pixel, weight, wi, wo, light = _nodes(gb, sc, material)
        parts.append((pixel + k * sc.camera.num_pixels, weight, wi, wo, light))
        consts.append(integrators.shade(gb, edit.set_material_row(sc, model_index, row, params0)))
    # Views may have different numbers of lights: pad with unlit, straight-up dummy lights.
    L = max(p[2].shape[1] for p in parts)
    up = np.array([0.0, 0.0, 1.0], np.float32)
    parts = [
        (px, w, np.concatenate([wi, np.broadcast_to(up, (len(px), L - wi.shape[1], 3))], 1), wo,
         np.concatenate([li, np.zeros((len(px), L - li.shape[1], 3), li.dtype)], 1))
        for px, w, wi, wo, li in parts
    ]
    cat = lambda i: np.concatenate([p[i] for p in parts])
    put = lambda x, dtype=None: jax.device_put(np.asarray(x, dtype))  # noqa: E731
    fb = FitBuffer(pixel=put(cat(0), np.int32), weight=put(cat(1), np.float32), wi=put(cat(2)), wo=put(cat(3)),
                   light=put(cat(4)), constant=jnp.zeros((len(consts),) + consts[0].shape, consts[0].dtype))
    model = brdfs.get(scenes[0].materials.models[model_index])
    return _with_constant(model, params0, fb, tuple(consts))


@functools.partial(jax.jit, static_argnums=0)
def _with_constant(model, params0, fb: FitBuffer, consts) -> FitBuffer:
    # the constant image: each view's full render minus the fitted material's share at params0
    return eqx.tree_at(lambda f: f.constant, fb, jnp.stack(consts) - contribution(model, params0, fb))


def contribution(model, params, fb: FitBuffer) -> Float[Array, "K H W 3"]:
    """The fitted material's share of the images for `params`."""
    p = {k: jnp.asarray(v)[None, None] if jnp.ndim(v) == 0 else jnp.asarray(v)[None, None, :] for k, v in params.items()}
    f = model.eval(p, fb.wi, fb.wo[:, None, :])  # (N, L, 3)
    per_node = fb.weight[:, None] * jnp.sum(f * fb.light, axis=1)
    shape = fb.constant.shape
    flat = jax.ops.segment_sum(per_node, fb.pixel, num_segments=shape[0] * shape[1] * shape[2])
    return flat.reshape(shape)


@functools.lru_cache(maxsize=None)
def shader(model_name: str):
    """`shade(params, fb) -> (K, H, W, 3)` for the solver; cached so the same function object (and
    so the same compiled solver) is reused."""
    model = brdfs.get(model_name)

    def shade(params, fb: FitBuffer):
        return fb.constant + contribution(model, params, fb)

    shade.program_key = f"fitting.compact.shader({model_name!r})"  # stable across processes
    return shade
