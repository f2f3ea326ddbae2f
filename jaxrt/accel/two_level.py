"""Two-level BVH for instanced geometry: a top-level tree over instances, one bottom-level tree
per prototype (shared by all its instances), stackless traversal in one lane pool.

    tree = two_level.build(prototypes, inst_proto, object_to_world)
    hit = two_level.intersect(tree, origins, directions, tmin, tmax)   # Hit(t, prim, u, v)
    blocked = two_level.occluded(tree, origins, directions, tmax)

Layout. All node arrays of the top level (TLAS) and of every prototype's tree (BLAS) are
concatenated: nodes [0, num_tlas_nodes) are the TLAS (root 0), prototype p's nodes start at
`proto_root[p]`. Links are offset to global node ids (-1 stays -1, so each BLAS's threading still
ends at -1). A TLAS leaf holds one instance: node_leaf = [instance index, 1]. Triangles of all
prototypes are stored once, in object (prototype) space; instances hold only a 3x4
object-to-world affine map, its inverse and a prototype id, so N instances cost O(N) memory.

Traversal. Per-ray state adds three things to the single-level state of `traverse_xla`: the
current instance (-1 in the TLAS), the TLAS node to resume at when the instance's BLAS is done,
and the ray constants (Woop shear, slab inverses, ray class) of the ray currently traversed. On
reaching a TLAS leaf whose box is hit, the ray is mapped into the instance's object space
(o' = W2O·o, d' = W2O_lin·d, direction NOT normalised), its constants are recomputed, the resume
node becomes the leaf's threaded successor (the threaded links give it: no stack), and traversal
goes to the prototype's root. When the BLAS threading ends (-1) the world ray's constants come
back and traversal resumes in the TLAS. Because d' is not renormalised, o' + t·d' = W2O(o + t·d):
t is the same number in both spaces, so closest-hit t values compare across instances directly
and tmin/tmax/t_best need no rescaling. Within an instance every triangle is tested against the
same transformed ray with the watertight test of `traverse_xla`, so watertightness holds per
instance (across instances, surfaces only meet where the scene author placed them).

Hit identity. `prim` is a global "virtual" face id: inst_face_offset[instance] + local face index
in the prototype; no per-face array is ever replicated per instance. `decode` inverts it.

Accuracy. The reported t is recomputed once per ray in double-float (as `bvh.intersect` does),
against the hit triangle mapped to world space with exact double-float products of the float32
matrix and vertices: the instance's geometry is DEFINED as object_to_world (float32) applied
exactly to the float32 prototype vertices. Which triangle is hit is decided in float32 object space.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from jaxrt.accel import builder
from jaxrt.accel.bvh import Hit, default_lanes, default_steps
from jaxrt.accel.predicates import df_add, df_mul, df_neg, opaque_zero
from jaxrt.accel.traverse_xla import node_step, precompute
from jaxrt.errors import InputError

# Outward padding of instance world boxes, relative to the box's magnitude: the TLAS test uses the
# world ray, the BLAS the rounded object-space ray; the pad keeps the TLAS from culling a ray that
# the object-space test would hit.
_BOX_PAD = 2.0**-16


class InstancedBVH(eqx.Module):
    """Two-level BVH arrays (see module docstring). nn = TLAS + all BLAS nodes, F = prototype faces
    (all prototypes, stored once), I = instances, P = prototypes.

    node_box (nn, 6) float32; node_leaf (nn, 2) int32 [first triangle or instance, count];
    links (6*nn, 2) int32; triangles (F, 9) float32 object space, leaf order; prim_ids (F,) int32
    local face index within its prototype; proto_root (P,) int32 global root node per prototype;
    inst_proto (I,) int32; object_to_world, world_to_object (I, 3, 4) float32 [A | b] with
    p_world = A p_object + b; inst_face_offset (I,) int32 first virtual face id of each instance.
    """

    node_box: Float[Array, "nn 6"]
    node_leaf: Int[Array, "nn 2"]
    links: Int[Array, "nn6 2"]
    triangles: Float[Array, "F 9"]
    prim_ids: Int[Array, " F"]
    proto_root: Int[Array, " P"]
    inst_proto: Int[Array, " I"]
    object_to_world: Float[Array, "I 3 4"]
    world_to_object: Float[Array, "I 3 4"]
    inst_face_offset: Int[Array, " I"]
    num_tlas_nodes: int = eqx.field(static=True)
    leaf_size: int = eqx.field(static=True)


def affine_inverse(m: np.ndarray) -> np.ndarray:
    """(..., 3, 4) [A | b] -> [A^-1 | -A^-1 b], in float64."""
    m = np.asarray(m, np.float64)
    a_inv = np.linalg.inv(m[..., :3])
    return np.concatenate([a_inv, -(a_inv @ m[..., 3:])], axis=-1)


def build(prototypes, inst_proto, object_to_world) -> InstancedBVH:
    """Build the two-level BVH (host numpy).

    prototypes: sequence of (vertices (V_p, 3), faces (F_p, 3)) in object space; inst_proto (I,)
    int prototype of each instance; object_to_world (I, 3, 4) affine maps whose linear part has a
    positive determinant. Raises InputError on bad input (see `bvh.build`) or a singular, mirroring
    or non-finite transform.
    """
    inst_proto = np.asarray(inst_proto, np.int64)
    xf = np.asarray(object_to_world, np.float32)
    n_inst = len(inst_proto)
    if n_inst == 0 or xf.shape != (n_inst, 3, 4):
        raise InputError(f"instancing: need one (3,4) transform per instance; got {xf.shape} for {n_inst} instances")
    if inst_proto.min() < 0 or inst_proto.max() >= len(prototypes):
        raise InputError("instancing: prototype index out of range")
    if not np.all(np.isfinite(xf)):
        raise InputError("instancing: instance transforms must be finite")
    det = np.linalg.det(xf[:, :, :3].astype(np.float64))
    if np.any(~(np.abs(det) > 1e-30)):
        raise InputError(f"instancing: instance {int(np.argmin(np.abs(det)))} has a singular transform")
    if np.any(det < 0):  # as mesh.transformed: a mirror would flip the winding (and glass's inside)
        raise InputError(f"instancing: instance {int(np.argmin(det))} has a negative-determinant (mirroring) "
                         "transform")
    inv = affine_inverse(xf).astype(np.float32)

    blas = [builder.build_arrays(v, f, leaf_size=1) for v, f in prototypes]
    face_counts = np.array([len(np.asarray(f)) for _, f in prototypes], np.int64)
    offsets = np.concatenate([[0], np.cumsum(face_counts[inst_proto])])
    if offsets[-1] > 2**31 - 1:
        raise InputError(f"instancing: {offsets[-1]} instanced triangles exceed the int32 face id range")

    # instance world boxes: the 8 corners of the prototype's (unpadded) root box, mapped in float64
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)
    root_box = np.stack([b["unpadded_box"][0] for b in blas]).astype(np.float64)  # (P, 6)
    lo_p, hi_p = root_box[:, :3], root_box[:, 3:]
    pts = lo_p[inst_proto][:, None] + corners[None] * (hi_p - lo_p)[inst_proto][:, None]  # (I, 8, 3)
    xf64 = xf.astype(np.float64)
    w = np.einsum("ijk,ick->icj", xf64[:, :, :3], pts) + xf64[:, None, :, 3]
    lo, hi = w.min(1), w.max(1)
    pad = _BOX_PAD * (np.abs(w).max(1) + (hi - lo).max(1, keepdims=True)) + 1e-30
    lo, hi = lo - pad, hi + pad
    # An LBVH over boxes: the "triangle" (lo, hi, hi) has exactly the box [lo, hi] as its bounds.
    top = builder.build_arrays(np.concatenate([lo, hi]), np.stack(
        [np.arange(n_inst), np.arange(n_inst) + n_inst, np.arange(n_inst) + n_inst], 1), leaf_size=1)
    nt = top["node_box"].shape[0]
    t_leaf = top["node_leaf"].copy()
    is_leaf = t_leaf[:, 1] > 0
    t_leaf[is_leaf, 0] = top["prim_ids"][t_leaf[is_leaf, 0]]  # leaf-order slot -> instance index

    nodes = [nt]
    for b in blas:
        nodes.append(b["node_box"].shape[0])
    node_off = np.cumsum([0] + nodes)[:-1]
    tri_off = np.cumsum([0] + [len(b["prim_ids"]) for b in blas])[:-1]
    n_all = int(sum(nodes))
    k = builder.NUM_RAY_CLASSES

    def shifted_links(a, off, n):
        lk = a["links"].reshape(k, n, 2).astype(np.int64)
        return np.where(lk >= 0, lk + off, -1)

    links = np.concatenate([shifted_links(top, 0, nt)] + [shifted_links(b, o, b["node_box"].shape[0])
                                                          for b, o in zip(blas, node_off[1:])], axis=1)
    leafs = [t_leaf] + [b["node_leaf"] + np.array([[o, 0]], np.int32) for b, o in zip(blas, tri_off)]
    if n_all > 2**31 - 1:
        raise InputError("instancing: too many BVH nodes")
    put = jax.device_put
    return InstancedBVH(
        node_box=put(np.concatenate([top["node_box"]] + [b["node_box"] for b in blas]).astype(np.float32)),
        node_leaf=put(np.concatenate(leafs).astype(np.int32)),
        links=put(links.reshape(k * n_all, 2).astype(np.int32)),
        triangles=put(np.concatenate([b["triangles"] for b in blas]).astype(np.float32)),
        prim_ids=put(np.concatenate([b["prim_ids"] for b in blas]).astype(np.int32)),
        proto_root=put(node_off[1:].astype(np.int32)),
        inst_proto=put(inst_proto.astype(np.int32)),
        object_to_world=put(xf),
        world_to_object=put(inv),
        inst_face_offset=put(offsets[:-1].astype(np.int32)),
        num_tlas_nodes=int(nt),
        leaf_size=1,
    )


def _apply(m, p):
    """Affine map [A | b] (N, 3, 4) of points p (N, 3)."""
    return jnp.einsum("nij,nj->ni", m[:, :, :3], p) + m[:, :, 3]


def _linear(m, d):
    return jnp.einsum("nij,nj->ni", m[:, :, :3], d)


def _traverse(tree: InstancedBVH, origins, directions, tmin, tmax, *, any_hit, lanes, steps_per_iter):
    """Lane-pool traversal (as `traverse_xla.traverse`) of the two-level tree.

    Returns (found, t, triangle (leaf order, global), instance, u, v), each (N,)."""
    node_box, node_leaf, links, tris = tree.node_box, tree.node_leaf, tree.links, tree.triangles
    nn = node_box.shape[0]
    nt = tree.num_tlas_nodes
    n_rays = origins.shape[0]
    w = min(lanes, n_rays)
    ar = jnp.arange(tree.leaf_size, dtype=jnp.int32)

    def consts(o, d):
        c = precompute(o, d)
        c["base"] = c.pop("ray_class") * nn
        return c

    def load(ray_idx):
        i = jnp.minimum(ray_idx, n_rays - 1)
        return dict(wo=origins[i], wd=directions[i], tmin=tmin[i], world=consts(origins[i], directions[i]))

    def step(ray, st):
        node, t_best, best, best_inst, bu, bv, inst, resume, cur = st
        active = node >= 0
        n = jnp.maximum(node, 0)
        in_top = n < nt
        cur_t = dict(cur, tmin=ray["tmin"])
        box_hit, leaf_hit, any_h, better, (t_best, best, bu, bv) = node_step(
            cur_t, node_box, node_leaf, tris, n, active, (t_best, best, bu, bv), ar, leaf_ok=~in_top)
        enter = leaf_hit & in_top
        best_inst = jnp.where(better, inst, best_inst)
        nxt = links[cur["base"] + n]
        nxt = jnp.where(box_hit, nxt[:, 0], nxt[:, 1])
        # the BLAS threading ended: back to the world ray and the TLAS node after the instance's leaf
        leave = active & ~in_top & (nxt < 0)
        new_inst = jnp.where(enter, node_leaf[n, 0], 0)
        node_new = jnp.where(enter, tree.proto_root[tree.inst_proto[new_inst]], jnp.where(leave, resume, nxt))
        if any_hit:
            node_new = jnp.where(any_h, -1, node_new)
        node_new = jnp.where(active, node_new, -1)
        resume = jnp.where(enter, nxt, resume)
        inst = jnp.where(enter, new_inst, jnp.where(leave, -1, inst))
        m = tree.world_to_object[new_inst]
        obj = consts(_apply(m, ray["wo"]), _linear(m, ray["wd"]))
        cur = jax.tree.map(
            lambda c, o_, w_: jnp.where(_b(enter, c), o_, jnp.where(_b(leave, c), w_, c)), cur, obj, ray["world"])
        return node_new, t_best, best, best_inst, bu, bv, inst, resume, cur

    def fresh(ray_idx, ray):
        ok = ray_idx < n_rays
        i = jnp.minimum(ray_idx, n_rays - 1)
        z = jnp.zeros(ray_idx.shape, jnp.float32)
        m1 = jnp.full(ray_idx.shape, -1, jnp.int32)
        return (jnp.where(ok, 0, -1).astype(jnp.int32), tmax[i], m1, m1, z, z, m1, m1, ray["world"])

    def body(carry):
        lane_ray, nxt_ray, ray, st, out = carry
        for _ in range(steps_per_iter):
            st = step(ray, st)
        free = st[0] < 0
        dst = jnp.where(free, lane_ray, n_rays)
        out = tuple(o_.at[dst].set(x, mode="drop") for o_, x in zip(out, st[1:6]))
        rank = jnp.cumsum(free.astype(jnp.int32)) - 1
        new = jnp.where(free, jnp.minimum(nxt_ray + rank, n_rays), lane_ray)
        nxt_ray = jnp.minimum(nxt_ray + jnp.sum(free.astype(jnp.int32)), n_rays)
        new_ray = load(new)
        ray = jax.tree.map(lambda a, b: jnp.where(_b(free, a), b, a), ray, new_ray)
        st = jax.tree.map(lambda a, b: jnp.where(_b(free, a), b, a), st, fresh(new, new_ray))
        return new, nxt_ray, ray, st, out

    lane_ray = jnp.arange(w, dtype=jnp.int32)
    out = (jnp.zeros(n_rays, jnp.float32), jnp.full(n_rays, -1, jnp.int32), jnp.full(n_rays, -1, jnp.int32),
           jnp.zeros(n_rays, jnp.float32), jnp.zeros(n_rays, jnp.float32))
    ray0 = load(lane_ray)
    carry = (lane_ray, jnp.int32(w), ray0, fresh(lane_ray, ray0), out)
    carry = lax.while_loop(lambda c: jnp.any(c[0] < n_rays), body, carry)
    t_best, best, best_inst, bu, bv = carry[4]
    return best >= 0, t_best, best, best_inst, bu, bv


def _b(mask, like):
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


def _run(tree, origins, directions, tmin, tmax, *, any_hit, lanes, steps_per_iter):
    origins = lax.stop_gradient(jnp.asarray(origins, jnp.float32))
    directions = lax.stop_gradient(jnp.asarray(directions, jnp.float32))
    if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
        raise InputError(f"bvh: origins and directions must both be (N,3); got {origins.shape} and {directions.shape}")
    n = origins.shape[0]
    tmin = jnp.broadcast_to(lax.stop_gradient(jnp.asarray(tmin, jnp.float32)), (n,))
    tmax = jnp.broadcast_to(lax.stop_gradient(jnp.asarray(tmax, jnp.float32)), (n,))
    if n == 0:
        z = jnp.zeros(0, jnp.float32)
        zi = jnp.zeros(0, jnp.int32)
        return jnp.zeros(0, bool), z, zi, zi, z, z, tmin, tmax
    res = _traverse(tree, origins, directions, tmin, tmax, any_hit=any_hit, lanes=lanes or default_lanes(),
                    steps_per_iter=steps_per_iter or default_steps())
    return res + (tmin, tmax)


def _df_affine(m, p, zero):
    """[A | b] p in double-float (hi, lo) pairs: products exact, sums to ~1e-14 relative."""
    z = jnp.zeros_like(p[:, 0])
    rows = []
    for i in range(3):
        acc = (m[:, i, 3], z)
        for j in range(3):
            acc = df_add(acc, df_mul((m[:, i, j], z), (p[:, j], z), zero))
        rows.append(acc)
    return rows  # [(hi, lo)] per component


def _refine_world_t(tree, inst, tri_idx, o, d, t32):
    """t of the world ray against the hit triangle mapped exactly (double-float) to world space."""
    m = tree.object_to_world[inst]
    tri = tree.triangles[tri_idx]
    zero = opaque_zero(jnp.argmax(jnp.abs(d), axis=-1))
    mul = lambda x, y: df_mul(x, y, zero)  # noqa: E731
    v0, v1, v2 = (_df_affine(m, tri[:, 3 * k:3 * k + 3], zero) for k in range(3))
    z = jnp.zeros_like(t32)
    sub = lambda x, y: df_add(x, df_neg(y))  # noqa: E731
    a = [sub(v0[i], (o[:, i], z)) for i in range(3)]
    e1 = [sub(v1[i], v0[i]) for i in range(3)]
    e2 = [sub(v2[i], v0[i]) for i in range(3)]

    def cross(i, j):
        return sub(mul(e1[i], e2[j]), mul(e1[j], e2[i]))

    nrm = [cross(1, 2), cross(2, 0), cross(0, 1)]
    num = df_add(df_add(mul(nrm[0], a[0]), mul(nrm[1], a[1])), mul(nrm[2], a[2]))
    den = df_add(df_add(mul(nrm[0], (d[:, 0], z)), mul(nrm[1], (d[:, 1], z))), mul(nrm[2], (d[:, 2], z)))
    q1 = num[0] / den[0]
    r = df_add(num, df_neg(mul((q1, z), den)))
    t = q1 + r[0] / den[0]
    # No closeness test against t32 (unlike traverse_xla.refine_t): for grazing rays the float32
    # object-space t also carries the rounding of the transformed ray and can be off by percents;
    # the plane intersection of the chosen triangle is the right answer whenever it is finite.
    good = jnp.isfinite(t) & (den[0] != 0)
    return jnp.where(good, t, t32)


def intersect(
    tree: InstancedBVH,
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmin: Float[Array, " N"] | float = 0.0,
    tmax: Float[Array, " N"] | float = jnp.inf,
    *,
    lanes: int | None = None,
    steps_per_iter: int | None = None,
) -> Hit:
    """Closest hit, as `jaxrt.accel.bvh.intersect`; prim is the virtual face id (see `decode`)."""
    found, t, best, inst, u, v, tmin_b, tmax_b = _run(tree, origins, directions, tmin, tmax, any_hit=False,
                                                      lanes=lanes, steps_per_iter=steps_per_iter)
    best = jnp.maximum(best, 0)
    inst = jnp.maximum(inst, 0)
    prim = jnp.where(found, tree.inst_face_offset[inst] + tree.prim_ids[best], -1)
    o32 = lax.stop_gradient(jnp.asarray(origins, jnp.float32))
    d32 = lax.stop_gradient(jnp.asarray(directions, jnp.float32))
    t = _refine_world_t(tree, inst, best, o32, d32, t)
    t = jnp.clip(t, tmin_b, tmax_b)
    return Hit(t=jnp.where(found, t, jnp.inf), prim=prim, u=jnp.where(found, u, 0.0), v=jnp.where(found, v, 0.0))


def occluded(
    tree: InstancedBVH,
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmax: Float[Array, " N"] | float = jnp.inf,
    tmin: Float[Array, " N"] | float = 0.0,
    *,
    lanes: int | None = None,
    steps_per_iter: int | None = None,
) -> Bool[Array, " N"]:
    """Any hit with t in [tmin, tmax] (early exit), as `jaxrt.accel.bvh.occluded`."""
    found, *_ = _run(tree, origins, directions, tmin, tmax, any_hit=True, lanes=lanes, steps_per_iter=steps_per_iter)
    return found


def decode(tree: InstancedBVH, prim: Int[Array, " B"]) -> tuple[Int[Array, " B"], Int[Array, " B"]]:
    """Virtual face id -> (instance, local face index in the instance's prototype); -1 gives (0, 0)."""
    p = jnp.maximum(prim, 0)
    # unrolled: a loop's every step is a host round trip on a GPU (`jaxrt.integrators.common.SEARCH`)
    inst = jnp.searchsorted(tree.inst_face_offset, p, side="right", method="scan_unrolled").astype(jnp.int32) - 1
    inst = jnp.clip(inst, 0, tree.inst_face_offset.shape[0] - 1)
    return inst, p - tree.inst_face_offset[inst]
