"""Stackless BVH traversal and watertight ray/triangle intersection (jit-able, device-agnostic).

Per-ray state is five scalars: the current node, the closest t so far, the best triangle (leaf
order) and its barycentrics. One traversal step tests the current node's box; a hit on a leaf also
tests the leaf's (up to `leaf_size`) triangles; the next node is `links[class, node, hit ? 0 : 1]`
(see builder). A batch runs in a `lax.while_loop` whose body does `steps_per_iter` such steps,
so the loop predicate (a device->host round trip on GPU) is paid once per several steps; rays
that finish early idle (node = -1) until the slowest ray of their chunk ends. Rays are traced in
chunks (`lax.map`) so that one slow ray only holds back its own chunk; callers that order rays
coherently (image tiles) get chunks of similar length.

Ray/triangle test: Woop, Benthin & Wald, "Watertight Ray/Triangle Intersection", JCGT 2013 —
translate to the ray origin, permute so the dominant direction axis is z, shear, and evaluate the
three 2D edge functions. Their signs are computed exactly in float32: for U = a*b - c*d, if the
rounded products differ their order is the exact order (rounding is monotonic); if they are equal,
the sign is that of the difference of the two products' exact rounding errors (Dekker's
TwoProduct with a bit-mask split, exact whatever the compiler does with FMA contraction). This is
the paper's double-precision fallback done in float32, so edges and vertices shared by two
triangles are never missed by both.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt.accel.predicates import (
    FAR_SCALE,
    df_add,
    df_mul,
    df_neg,
    edge_products,
    edge_sign,
    opaque,
    opaque_zero,
    ray_constants,
    two_sum,
)


# --- double-float (float32 pair) arithmetic, for re-evaluating t of the final hit -------------------
# Error-free transforms that hold under FMA contraction (products of split halves are exact).


def refine_t(tri, o, d, t32):
    """t of the ray/plane intersection of each ray with its hit triangle, in double-float (~1e-13).

    tri (N, 9) float32, o/d (N, 3), t32 (N,) the float32 t from traversal (kept where the
    double-float evaluation is not finite). The plane equation is evaluated as
    t = n.(v0 - o) / n.d with n = (v1 - v0) x (v2 - v0), all differences exact (TwoSum) and
    products via Dekker's TwoProduct: float32 alone loses ~eps/cos(angle) relative accuracy for
    grazing rays.
    """
    v0, v1, v2 = tri[:, 0:3], tri[:, 3:6], tri[:, 6:9]
    zero = opaque_zero(jnp.argmax(jnp.abs(d), axis=-1))
    mul = lambda x, y: df_mul(x, y, zero)  # noqa: E731
    a = two_sum(v0, -o)
    e1 = two_sum(v1, -v0)
    e2 = two_sum(v2, -v0)
    comp = lambda x, i: (x[0][:, i], x[1][:, i])  # noqa: E731

    def cross(i, j):
        return df_add(mul(comp(e1, i), comp(e2, j)), df_neg(mul(comp(e1, j), comp(e2, i))))

    n = [cross(1, 2), cross(2, 0), cross(0, 1)]
    num = df_add(df_add(mul(n[0], comp(a, 0)), mul(n[1], comp(a, 1))), mul(n[2], comp(a, 2)))
    z = jnp.zeros_like(t32)
    den = df_add(df_add(mul(n[0], (d[:, 0], z)), mul(n[1], (d[:, 1], z))), mul(n[2], (d[:, 2], z)))
    q1 = num[0] / den[0]
    r = df_add(num, df_neg(mul((q1, z), den)))
    t = q1 + r[0] / den[0]
    good = jnp.isfinite(t) & (den[0] != 0) & (jnp.abs(t - t32) <= 1e-2 * jnp.abs(t32) + 1e-30)
    return jnp.where(good, t, t32)


def precompute(origins, directions):
    """Per-ray constants: slab inverse directions, ray class, and the Woop shear/permutation."""
    inv, shear, kx, ky, kz, ray_class = ray_constants(*(directions[:, i] for i in range(3)))
    zero = opaque_zero(kz)
    return dict(o=origins, inv=jnp.stack(inv, axis=-1), kx=kx, ky=ky, kz=kz, shear=jnp.stack(shear, axis=-1),
                ray_class=ray_class, zero=zero)


def _pick(a, k):
    """a[..., k] for per-ray k (leading axis matches), by exact selects."""
    k = k.reshape(k.shape + (1,) * (a.ndim - 1 - k.ndim))
    return jnp.where(k == 0, a[..., 0], jnp.where(k == 1, a[..., 1], a[..., 2]))


def intersect_triangles(ray, tri, tmin, tmax, valid, exact: bool | None = None):
    """Watertight test of each ray against L triangles.

    ray: precompute() dict over N rays; tri (N, L, 9) float32 [v0, v1, v2] (or (1, L, 9), the same
    triangles for every ray); tmin, tmax (N,); valid (N, L) bool: which pairs to test. exact: None
    runs the exact-sign path only if a valid pair needs it (a conditional); True always runs it
    (4x the edge arithmetic, no conditional: for a few triangles on a GPU, where a conditional waits
    for the device); False never (a tie counts as on the edge: inside).
    Returns hit (N, L) bool (tmin <= t <= tmax), t, u, v (N, L) with p = (1-u-v) v0 + u v1 + v v2.
    """
    p = tri.reshape(tri.shape[:-1] + (3, 3)) - ray["o"][:, None, None, :]  # (N, L, 3 verts, 3)
    kx, ky, kz = (ray[k][:, None, None] for k in ("kx", "ky", "kz"))
    px, py, pz = _pick(p, kx), _pick(p, ky), _pick(p, kz)  # (N, L, 3)
    sx, sy, sz = (ray["shear"][:, None, None, i] for i in range(3))
    zero = ray["zero"][:, None, None]
    # A vertex shared by two triangles must shear to the same 2D point in both: the products are
    # made opaque so that no fusion computes px - sx*pz as a single FMA.
    x = px - opaque(sx * pz, zero)
    y = py - opaque(sy * pz, zero)
    z = sz * pz
    (ax, bx, cx), (ay, by, cy), (az, bz, cz) = ([w[..., i] for i in range(3)] for w in (x, y, z))
    edges = ((cx, cy, bx, by), (ax, ay, cx, cy), (bx, by, ax, ay))
    zero = zero[..., 0]
    prods = [edge_products(*e, zero) for e in edges]
    # Rounded products that tie leave the sign open; that is rare, so the exact path (4x the
    # arithmetic) runs only for batches where some valid ray/triangle pair needs it.
    if exact is not None:
        signs = [edge_sign(*e, *p, exact=exact) for e, p in zip(edges, prods)]
    else:
        need_exact = jnp.any(valid & ((prods[0][0] == prods[0][1]) | (prods[1][0] == prods[1][1])
                                      | (prods[2][0] == prods[2][1])))
        signs = lax.cond(need_exact,
                         lambda: [edge_sign(*e, *p, exact=True) for e, p in zip(edges, prods)],
                         lambda: [edge_sign(*e, *p, exact=False) for e, p in zip(edges, prods)])
    su, sv, sw = signs
    # |p1 - p2| carries the magnitude; the sign comes from the exact test (the subtraction may be
    # FMA-contracted or round to zero).
    U, V, W = (jnp.abs(p1 - p2) * sg for (p1, p2), sg in zip(prods, signs))
    inside = ((su >= 0) & (sv >= 0) & (sw >= 0)) | ((su <= 0) & (sv <= 0) & (sw <= 0))
    det = U + V + W
    ok = inside & (det != 0)
    det_safe = jnp.where(ok, det, 1.0)
    t = (U * az + V * bz + W * cz) / det_safe
    hit = valid & ok & (t >= tmin[:, None]) & (t <= tmax[:, None])
    return hit, t, V / det_safe, W / det_safe


def node_step(ray, node_box, node_leaf, tris, n, active, hit, ar, leaf_ok=True):
    """One traversal step's tests for lanes at nodes n (B,): the box (slab test, far distance
    widened by FAR_SCALE, clipped to the best t) and, where it is hit and is a leaf (and leaf_ok),
    the leaf's triangles, keeping the closest hit.

    ray: precompute() dict plus "tmin" (B,); hit: (t_best, best, bu, bv) (B,) each; ar: arange of
    the leaf size. Returns box_hit (B,), leaf_hit (B,) (before leaf_ok), any_h (B,), better (B,)
    (the best hit changed) and the updated hit.
    """
    t_best, best, bu, bv = hit
    t_lo = ray["tmin"]
    nf = tris.shape[0]
    box = node_box[n]
    t0 = (box[:, :3] - ray["o"]) * ray["inv"]
    t1 = (box[:, 3:] - ray["o"]) * ray["inv"]
    t_near = jnp.maximum(jnp.max(jnp.minimum(t0, t1), axis=-1), t_lo)
    t_far = jnp.minimum(jnp.min(jnp.maximum(t0, t1), axis=-1) * FAR_SCALE, t_best)
    box_hit = active & (t_near <= t_far)
    leaf = node_leaf[n]
    leaf_hit = box_hit & (leaf[:, 1] > 0)
    test = leaf_hit & leaf_ok
    # Lanes not testing a leaf all read triangle 0, which stays in cache.
    first = jnp.where(test, leaf[:, 0], 0)
    idx = jnp.minimum(first[:, None] + ar, nf - 1)
    valid = test[:, None] & (ar < leaf[:, 1:2])
    h, t, u, v = intersect_triangles(ray, tris[idx], t_lo, t_best, valid)
    t_m = jnp.where(h, t, jnp.inf)
    j = jnp.argmin(t_m, axis=-1)[:, None]
    any_h = jnp.any(h, axis=-1)
    t_j = jnp.take_along_axis(t_m, j, axis=-1)[:, 0]
    # Strict < keeps the earlier triangle on exact ties; a first hit at t == tmax still counts.
    better = any_h & ((t_j < t_best) | (best < 0))
    t_best = jnp.where(better, t_j, t_best)
    best = jnp.where(better, jnp.take_along_axis(idx, j, axis=-1)[:, 0], best)
    bu = jnp.where(better, jnp.take_along_axis(u, j, axis=-1)[:, 0], bu)
    bv = jnp.where(better, jnp.take_along_axis(v, j, axis=-1)[:, 0], bv)
    return box_hit, leaf_hit, any_h, better, (t_best, best, bu, bv)


def traverse(arrays, origins, directions, tmin, tmax, *, any_hit: bool, leaf_size: int, steps_per_iter: int,
             lanes: int, count_steps: bool = False):
    """Trace N rays with a pool of `lanes` lanes that refill from the ray queue.

    Returns (found, t, tri_index_in_leaf_order, u, v, steps), each (N,).

    A plain vmapped while loop runs every ray until the slowest one ends (measured: primary rays
    on the bunny average 17 steps but the slowest take ~200, so >90% of lane-steps were idle).
    Here a lane whose ray has finished writes its result and takes the next ray of the queue at
    the end of each iteration (a prefix sum assigns queue positions), so lanes stay busy until the
    queue runs dry and only the last `lanes` rays see the tail.
    """
    node_box, node_leaf, links, tris = (arrays[k] for k in ("node_box", "node_leaf", "links", "triangles"))
    nn = node_box.shape[0]
    n_rays = origins.shape[0]
    w = min(lanes, n_rays)
    ar = jnp.arange(leaf_size, dtype=jnp.int32)

    def load(ray_idx):
        i = jnp.minimum(ray_idx, n_rays - 1)
        ray = precompute(origins[i], directions[i])
        ray["base"] = ray.pop("ray_class") * nn
        ray["tmin"] = tmin[i]
        return ray

    def step(ray, st):
        node, t_best, best, bu, bv, steps = st
        active = node >= 0
        n = jnp.maximum(node, 0)
        box_hit, _, any_h, _, (t_best, best, bu, bv) = node_step(ray, node_box, node_leaf, tris, n, active,
                                                                 (t_best, best, bu, bv), ar)
        nxt = links[ray["base"] + n]
        nxt = jnp.where(box_hit, nxt[:, 0], nxt[:, 1])
        if any_hit:
            nxt = jnp.where(any_h, -1, nxt)
        node = jnp.where(active, nxt, -1)
        if count_steps:
            steps = steps + active.astype(jnp.int32)
        return node, t_best, best, bu, bv, steps

    def fresh(ray_idx):
        ok = ray_idx < n_rays
        i = jnp.minimum(ray_idx, n_rays - 1)
        return (jnp.where(ok, 0, -1).astype(jnp.int32), tmax[i], jnp.full(ray_idx.shape, -1, jnp.int32),
                jnp.zeros(ray_idx.shape, jnp.float32), jnp.zeros(ray_idx.shape, jnp.float32),
                jnp.zeros(ray_idx.shape, jnp.int32))

    def body(carry):
        lane_ray, nxt_ray, ray, st, out = carry
        for _ in range(steps_per_iter):
            st = step(ray, st)
        free = st[0] < 0
        # Finished lanes write their ray's result (lanes without a ray write out of bounds: dropped).
        dst = jnp.where(free, lane_ray, n_rays)
        out = tuple(o_.at[dst].set(x, mode="drop") for o_, x in zip(out, st[1:]))
        rank = jnp.cumsum(free.astype(jnp.int32)) - 1
        new = jnp.where(free, jnp.minimum(nxt_ray + rank, n_rays), lane_ray)
        nxt_ray = jnp.minimum(nxt_ray + jnp.sum(free.astype(jnp.int32)), n_rays)
        new_ray = load(new)
        ray = jax.tree.map(lambda a, b: jnp.where(free.reshape(free.shape + (1,) * (a.ndim - 1)), b, a), ray, new_ray)
        st = jax.tree.map(lambda a, b: jnp.where(free, b, a), st, fresh(new))
        return new, nxt_ray, ray, st, out

    lane_ray = jnp.arange(w, dtype=jnp.int32)
    out = (jnp.zeros(n_rays, jnp.float32), jnp.full(n_rays, -1, jnp.int32), jnp.zeros(n_rays, jnp.float32),
           jnp.zeros(n_rays, jnp.float32), jnp.zeros(n_rays, jnp.int32))
    carry = (lane_ray, jnp.int32(w), load(lane_ray), fresh(lane_ray), out)
    carry = lax.while_loop(lambda c: jnp.any(c[0] < n_rays), body, carry)
    t_best, best, bu, bv, steps = carry[4]
    return best >= 0, t_best, best, bu, bv, steps
