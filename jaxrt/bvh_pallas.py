"""BVH traversal as one Pallas kernel (Triton backend on GPU; interpret mode anywhere, for tests).

The pure-XLA traversal (`jaxrt.bvh_traverse.traverse`) keeps every lane's state in HBM arrays and
pays a device->host round trip for the while-loop predicate every `steps_per_iter` steps. Here each
program instance takes a block of `block` consecutive rays (image tiles: coherent), keeps their
state in registers and loops on the GPU until all of the block's rays end; the GPU's block
scheduler starts the next block on a free multiprocessor, which is the lane refill of the XLA path
done by hardware.

Results are the XLA path's: the same stackless links, node order, box test (same slab formula and
far-distance widening) and watertight triangle test with exact edge signs (as there, the exact
path runs only where some tested pair's rounded products tie: here a branch per program of 32
rays). With one triangle per leaf, a leaf's node row holds its triangle instead of its box, so a
traversal step makes one round of dependent loads; the box test a leaf skips is implied by a
triangle hit (the boxes are padded outward) and a leaf's hit and miss links are the same node. The hit distance is float32 and may differ from
the XLA path's in the last ulp where the compiler contracts a multiply-add differently, so two
triangles at the same distance to within an ulp may be chosen differently (ties); `bvh.intersect`
then refines t of the chosen triangle in double-float in XLA for both paths.

Tables are read with vector gathers from flat row-major arrays (`ref[index_vector]`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl
from jaxtyping import Array, Float

from jaxrt import bvh_traverse

_FAR_SCALE = bvh_traverse._FAR_SCALE
_ROW = 12  # words per node row with inline leaves: 9 (box or triangle), first, count, pad
_HI_MASK = -4096  # 0xFFFFF000 as int32: keeps sign, exponent and the top 11 mantissa bits


def _opaque(x, zero):
    # As bvh_traverse._opaque (int32 here): stops FMA contraction of the rounded product.
    return lax.bitcast_convert_type(lax.bitcast_convert_type(x, jnp.int32) ^ zero, jnp.float32)


def _split(a):
    hi = lax.bitcast_convert_type(lax.bitcast_convert_type(a, jnp.int32) & jnp.int32(_HI_MASK), jnp.float32)
    return hi, a - hi


def _product_error(a, b, p):
    ah, al = _split(a)
    bh, bl = _split(b)
    return ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _edge_products(ax, ay, bx, by, zero):
    """Rounded products (p1, p2) of the edge function ax*by - ay*bx."""
    return _opaque(ax * by, zero), _opaque(ay * bx, zero)


def _sign(x):
    return jnp.where(x > 0, 1.0, jnp.where(x < 0, -1.0, 0.0)).astype(jnp.float32)


def _edge_sign(ax, ay, bx, by, p1, p2, exact: bool):
    """Sign of ax*by - ay*bx as in bvh_traverse._edge_sign: exact, or from the rounded products."""
    s = jnp.where(p1 > p2, 1.0, jnp.where(p1 < p2, -1.0, 0.0)).astype(jnp.float32)
    if exact:
        s = jnp.where(p1 == p2, _sign(_product_error(ax, by, p1) - _product_error(ay, bx, p2)), s)
    return s


def _pick(k, x, y, z):
    return jnp.where(k == 0, x, jnp.where(k == 1, y, z))


def _load_row(ref, idx, width):
    """Columns of rows `idx` of a flat (rows*width,) table, as one (block, width) gather (vector loads)."""
    x = ref[idx[:, None] * width + lax.broadcasted_iota(jnp.int32, (1, width), 1)]
    return [c.reshape(idx.shape) for c in jnp.split(x, width, axis=1)]


def _kernel(ox_r, oy_r, oz_r, ix_r, iy_r, iz_r, sx_r, sy_r, sz_r, kx_r, ky_r, kz_r, base_r, tmin_r, tmax_r,
            box_r, leaf_r, links_r, tri_r,
            t_o, best_o, u_o, v_o,
            *, any_hit: bool, leaf_size: int, steps_per_iter: int, nf: int, vec_nodes: bool, vec_tris: bool,
            inline: bool, gate_exact: bool):
    ox, oy, oz = ox_r[...], oy_r[...], oz_r[...]
    ix, iy, iz = ix_r[...], iy_r[...], iz_r[...]
    sx, sy, sz = sx_r[...], sy_r[...], sz_r[...]
    kx, ky, kz = kx_r[...], ky_r[...], kz_r[...]
    base = base_r[...]
    t_lo = tmin_r[...]
    zero = lax.shift_right_logical(kz, jnp.int32(8))  # 0, unknown to the compiler

    def tri_load(idx):
        if vec_tris:
            return _load_row(tri_r, idx, 16)[:9]
        i9 = idx * 9
        return [tri_r[i9 + k] for k in range(9)]

    def tri_test(vs, valid, t_best):
        px, py, pz = [], [], []
        for j in range(3):
            qx, qy, qz = vs[3 * j] - ox, vs[3 * j + 1] - oy, vs[3 * j + 2] - oz
            px.append(_pick(kx, qx, qy, qz))
            py.append(_pick(ky, qx, qy, qz))
            pz.append(_pick(kz, qx, qy, qz))
        x = [px[j] - _opaque(sx * pz[j], zero) for j in range(3)]
        y = [py[j] - _opaque(sy * pz[j], zero) for j in range(3)]
        z = [sz * pz[j] for j in range(3)]
        (ax, bx, cx), (ay, by, cy), (az, bz, cz) = x, y, z
        edges = ((cx, cy, bx, by), (ax, ay, cx, cy), (bx, by, ax, ay))
        prods = [_edge_products(*e, zero) for e in edges]
        if gate_exact:
            # Tied rounded products are rare: the exact-sign arithmetic runs only for programs where
            # some tested ray/triangle pair needs it (a warp-uniform branch), as the XLA path's cond.
            tie = valid & ((prods[0][0] == prods[0][1]) | (prods[1][0] == prods[1][1]) | (prods[2][0] == prods[2][1]))
            su, sv, sw = lax.cond(jnp.max(tie.astype(jnp.int32)) > 0,
                                  lambda: tuple(_edge_sign(*e, *p, exact=True) for e, p in zip(edges, prods)),
                                  lambda: tuple(_edge_sign(*e, *p, exact=False) for e, p in zip(edges, prods)))
        else:
            su, sv, sw = (_edge_sign(*e, *p, exact=True) for e, p in zip(edges, prods))
        U, V, W = (jnp.abs(p1 - p2) * sg for (p1, p2), sg in zip(prods, (su, sv, sw)))
        inside = ((su >= 0) & (sv >= 0) & (sw >= 0)) | ((su <= 0) & (sv <= 0) & (sw <= 0))
        det = U + V + W
        ok = inside & (det != 0)
        det_safe = jnp.where(ok, det, 1.0)
        t = (U * az + V * bz + W * cz) / det_safe
        hit = valid & ok & (t >= t_lo) & (t <= t_best)
        return hit, t, V / det_safe, W / det_safe

    def step(st):
        node, t_best, best, bu, bv = st
        active = node >= 0
        n = jnp.maximum(node, 0)
        if inline:
            r12 = n * _ROW
            w = [box_r[r12 + k] for k in range(9)]
            bb = w[:6]
            first = lax.bitcast_convert_type(box_r[r12 + 9], jnp.int32)
            count = lax.bitcast_convert_type(box_r[r12 + 10], jnp.int32)
        elif vec_nodes:
            row = _load_row(box_r, n, 8)
            bb = row[:6]
            first = lax.bitcast_convert_type(row[6], jnp.int32)
            count = lax.bitcast_convert_type(row[7], jnp.int32)
        else:
            b6 = n * 6
            bb = [box_r[b6 + k] for k in range(6)]
            first = leaf_r[n * 2]
            count = leaf_r[n * 2 + 1]
        t0x = (bb[0] - ox) * ix
        t0y = (bb[1] - oy) * iy
        t0z = (bb[2] - oz) * iz
        t1x = (bb[3] - ox) * ix
        t1y = (bb[4] - oy) * iy
        t1z = (bb[5] - oz) * iz
        t_near = jnp.maximum(jnp.maximum(jnp.maximum(jnp.minimum(t0x, t1x), jnp.minimum(t0y, t1y)),
                                         jnp.minimum(t0z, t1z)), t_lo)
        t_far = jnp.minimum(jnp.minimum(jnp.maximum(t0x, t1x), jnp.maximum(t0y, t1y)), jnp.maximum(t0z, t1z))
        t_far = jnp.minimum(t_far * _FAR_SCALE, t_best)
        if inline:
            # A leaf's row holds its triangle, not its box: the triangle test alone decides (the
            # padded box test is implied by a hit in [tmin, t_best]) and a leaf's hit and miss links
            # are the same node, so box_hit only matters for interior nodes.
            box_hit = active & ((count > 0) | (t_near <= t_far))
        else:
            box_hit = active & (t_near <= t_far)
        leaf_hit = box_hit & (count > 0)
        first = jnp.where(leaf_hit, first, 0)  # lanes not testing a leaf read triangle 0 (cached)
        any_h = jnp.zeros_like(active)
        for j in range(leaf_size):
            idx = jnp.minimum(first + j, nf - 1)
            vs = w if inline else tri_load(idx)
            h, t, u, v = tri_test(vs, leaf_hit & (count > j), t_best)
            # Strict < keeps the earlier triangle on exact ties (the XLA path's argmin).
            better = h & ((t < t_best) | (best < 0))
            t_best = jnp.where(better, t, t_best)
            best = jnp.where(better, idx, best)
            bu = jnp.where(better, u, bu)
            bv = jnp.where(better, v, bv)
            any_h = any_h | h
        row = (base + n) * 2
        nxt = jnp.where(box_hit, links_r[row], links_r[row + 1])
        if any_hit:
            nxt = jnp.where(any_h, -1, nxt)
        node = jnp.where(active, nxt, -1)
        return node, t_best, best, bu, bv

    def body(st):
        for _ in range(steps_per_iter):
            st = step(st)
        return st

    shape = ox.shape
    st = (jnp.zeros(shape, jnp.int32), tmax_r[...], jnp.full(shape, -1, jnp.int32),
          jnp.zeros(shape, jnp.float32), jnp.zeros(shape, jnp.float32))
    st = lax.while_loop(lambda s: jnp.max(s[0]) >= 0, body, st)
    _, t_best, best, bu, bv = st
    t_o[...] = t_best
    best_o[...] = best
    u_o[...] = bu
    v_o[...] = bv


@functools.partial(jax.jit, static_argnames=("any_hit", "leaf_size", "block", "steps_per_iter", "num_warps",
                                             "interpret", "vec_nodes", "vec_tris", "inline", "gate_exact"))
def traverse(arrays: dict, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"], tmin: Float[Array, " N"],
             tmax: Float[Array, " N"], *, any_hit: bool, leaf_size: int, block: int = 32,
             steps_per_iter: int = 2, num_warps: int = 1, interpret: bool = False, vec_nodes: bool = False,
             vec_tris: bool = False, inline: bool | None = None, gate_exact: bool = True):
    """Trace N rays; returns (found, t, tri_index_in_leaf_order, u, v), each (N,), as
    `bvh_traverse.traverse` (without the step counts).

    arrays: node_box (nn,6), node_leaf (nn,2), links (6nn,2), triangles (F,9) (see bvh.BVH);
    origins, directions (N,3) float32; tmin, tmax (N,) float32. block: rays per program instance
    (a power of 2); steps_per_iter: traversal steps between two checks of the block's loop
    predicate; num_warps: Triton warps per program; interpret: run the kernel with the Pallas
    interpreter (any backend; slow, for tests). vec_nodes / vec_tris: read each node as one
    8-word row (box + leaf) / each triangle as one 16-word row, repacked per call (layout
    experiments; results are the same). inline (default: leaf_size == 1): one 12-word row per node
    holding an interior node's box or a leaf's triangle, so a step makes one round of dependent
    loads instead of two (node, then triangle); repacked per call. gate_exact: evaluate the
    exact edge signs only in programs where a rounded-product tie occurs (else always).
    """
    if inline is None:
        inline = leaf_size == 1 and not (vec_nodes or vec_tris)
    if inline and leaf_size != 1:
        raise ValueError("bvh_pallas: inline rows need leaf_size 1")
    nn = arrays["node_box"].shape[0]
    nf = arrays["triangles"].shape[0]
    n = origins.shape[0]
    n_pad = -(-n // block) * block
    ray = bvh_traverse.precompute(origins, directions)
    pad = n_pad - n

    def col(x, fill):
        return jnp.pad(x, (0, pad), constant_values=fill)

    # Padding rays have an empty interval (tmin 1 > tmax 0): they miss the root box and end.
    per_ray = [col(ray["o"][:, i], 0.0) for i in range(3)] + [col(ray["inv"][:, i], 1.0) for i in range(3)]
    per_ray += [col(ray["shear"][:, i], 0.0) for i in range(3)]
    per_ray += [col(ray[k], 0) for k in ("kx", "ky", "kz")] + [col(ray["ray_class"] * nn, 0)]
    per_ray += [col(tmin.astype(jnp.float32), 1.0), col(tmax.astype(jnp.float32), 0.0)]
    box, leaf, tri = arrays["node_box"], arrays["node_leaf"], arrays["triangles"]
    if inline:
        is_leaf = (leaf[:, 1] > 0)[:, None]
        body = jnp.where(is_leaf, tri[jnp.where(is_leaf[:, 0], leaf[:, 0], 0)],
                         jnp.pad(box, ((0, 0), (0, 3))))
        box = jnp.concatenate([body, lax.bitcast_convert_type(leaf, jnp.float32), jnp.zeros((nn, 1), jnp.float32)],
                              axis=1)
    elif vec_nodes:
        box = jnp.concatenate([box, lax.bitcast_convert_type(leaf, jnp.float32)], axis=1)
    if vec_tris:
        tri = jnp.pad(tri, ((0, 0), (0, 7)))
    tables = [box.reshape(-1), leaf.reshape(-1), arrays["links"].reshape(-1), tri.reshape(-1)]
    ray_spec = pl.BlockSpec((block,), lambda i: (i,))
    in_specs = [ray_spec] * len(per_ray) + [pl.BlockSpec(tb.shape, lambda i: (0,)) for tb in tables]
    f32 = jax.ShapeDtypeStruct((n_pad,), jnp.float32)
    i32 = jax.ShapeDtypeStruct((n_pad,), jnp.int32)
    kw = {}
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        kw["compiler_params"] = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
    t, best, u, v = pl.pallas_call(
        functools.partial(_kernel, any_hit=any_hit, leaf_size=leaf_size, steps_per_iter=steps_per_iter, nf=nf,
                          vec_nodes=vec_nodes, vec_tris=vec_tris, inline=inline, gate_exact=gate_exact),
        out_shape=(f32, i32, f32, f32),
        grid=(n_pad // block,),
        in_specs=in_specs,
        out_specs=(ray_spec,) * 4,
        interpret=interpret,
        name="bvh_any_hit" if any_hit else "bvh_closest_hit",
        **kw,
    )(*per_ray, *tables)
    t, best, u, v = t[:n], best[:n], u[:n], v[:n]
    return best >= 0, t, best, u, v
