"""Bounding volume hierarchy: build (numpy, host) and stackless traversal (JAX, jit-able).

    tree = bvh.build(mesh.vertices, mesh.faces)          # BVH pytree of jnp arrays
    hit = bvh.intersect(tree, origins, directions, tmin=0.0, tmax=jnp.inf)
    hit.t (N,), hit.prim (N,) int32, hit.u (N,), hit.v (N,)
    blocked = bvh.occluded(tree, origins, directions, tmax)   # (N,) bool
    hit, p, ng = bvh.intersect_points(tree, origins, directions)   # also hit points, geometric normals
    bvh.stats(tree)  (or tree.stats)                     # node count, depth, SAH cost, leaf sizes

`intersect` returns the closest hit with t in [tmin, tmax]: `prim` indexes the ORIGINAL face order
(the `faces` given to `build`), a miss has prim -1, t = inf and u = v = 0. Barycentrics: the hit
point is (1-u-v)*v0 + u*v1 + v*v2 for face (v0, v1, v2). `occluded` is any-hit with early exit:
True where some triangle is hit with t in [tmin, tmax]. tmin/tmax are scalars or (N,) arrays;
origins/directions are (N,3) float32 (directions need not be unit; t is in units of |direction|).

Both work on CPU and GPU unchanged, can be called inside another jitted function with `tree` as a
traced argument, and are not differentiable: their inputs pass through `lax.stop_gradient`, and a
renderer recomputes the differentiable hit point from `prim` (trace once, shade many: docs/ARCHITECTURE.md).
Triangle tests are watertight (see `jaxrt.accel.traverse_xla`): a ray aimed at an edge or vertex shared
by two triangles of a closed mesh always hits one of them (Embree's test: at edges; a ray through a
vertex exactly can slip through, see `jaxrt.accel.traverse_embree`). Build and traversal details are in
`jaxrt.accel.builder` and `jaxrt.accel.traverse_xla` (pure JAX, portable), `jaxrt.accel.traverse_pallas` (one Pallas
kernel, the default where the computation is lowered for an NVIDIA GPU), `jaxrt.accel.traverse_embree`
(Embree's packet traversal through a C++ XLA FFI kernel, the default where the computation is lowered
for the CPU and Embree is installed) and `jaxrt.accel.traverse_cpu` (jaxrt's own C++ XLA FFI kernel,
the CPU default without Embree); both kernels are compiled on first use. `impl=` / JAXRT_TRAVERSAL
choose one.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int, UInt32

from jaxrt.accel.builder import NUM_RAY_CLASSES, build_arrays
from jaxrt.accel.sah import DEFAULT as SAH_DEFAULT
from jaxrt.accel.sah import SahSettings
from jaxrt import _config
from jaxrt.accel import traverse_cpu
from jaxrt.accel import traverse_embree
from jaxrt.accel import traverse_pallas
from jaxrt.accel import traverse_xla
from jaxrt.errors import InputError


class BVH(eqx.Module):
    """Flat BVH arrays (nn nodes, F triangles), ready for jit.

    node_box  (nn, 6) float32   [lo_x, lo_y, lo_z, hi_x, hi_y, hi_z], padded outward by a few ulps
    node_leaf (nn, 2) int32     [first triangle (leaf order), count]; count 0 for interior nodes
    links     (6*nn, 2) int32   per ray class c (dominant axis*2 + negative): row c*nn + node holds
                                (next node if the box is hit, next node if missed); -1 ends
    triangles (F, 9) float32    v0, v1, v2 of each triangle in leaf order
    prim_ids  (F,) int32        original face index of each leaf-order triangle
    rows      (nn, 16 or 32) float32  the GPU kernel's node table for `traverse_pallas.TREE_LAYOUT`
                                (`traverse_pallas.pack_tables`: children's boxes in each interior row, the
                                triangle in each leaf row), or None: packed once by `build` when the
                                default backend is a GPU and leaf_size is 1 (the full dragon's binary
                                rows: 111 MB), else per call by the kernel.
    skips     (6*nn,) int32     the same kernel's links: per class and node, the miss link and its
                                node's depth (`traverse_pallas.pack_tables`); None when rows is None
    table_key (2,) uint32       Embree's key of `triangles` (`with_table_key`), made inside the traced
                                program that traces the tree, or None (every Embree call hashes the table)
    leaf_size: static, the largest leaf
    """

    node_box: Float[Array, "nn 6"]
    node_leaf: Int[Array, "nn 2"]
    links: Int[Array, "nn6 2"]
    triangles: Float[Array, "F 9"]
    prim_ids: Int[Array, " F"]
    rows: Float[Array, "nn w"] | None
    skips: Int[Array, " nn6"] | None
    leaf_size: int = eqx.field(static=True)
    table_key: UInt32[Array, "2"] | None = None

    @property
    def stats(self) -> "BVHStats":
        return stats(self)


class Hit(NamedTuple):
    """Closest-hit result per ray: t (N,) float32 (inf on a miss), prim (N,) int32 (original face
    index, -1 on a miss), u, v (N,) float32 barycentrics of v1 and v2 (0 on a miss)."""

    t: Float[Array, " N"]
    prim: Int[Array, " N"]
    u: Float[Array, " N"]
    v: Float[Array, " N"]


@dataclasses.dataclass(frozen=True)
class BVHStats:
    """Build statistics. sah_cost uses C_trav = C_isect = 1 and surface areas relative to the root."""

    nodes: int
    leaves: int
    depth: int
    sah_cost: float
    leaf_size_min: int
    leaf_size_max: int
    leaf_size_mean: float
    triangles: int


# Scenes are built once and traced for every frame (and fit iteration), so they take the tree that
# traces fastest: the SAH tree in depth-first order gave the GPU's best shadow rays traced from the
# light (BENCHMARKS.md), at ~1.2-1.4x the LBVH's build time.
RENDER_TREE = {"builder": "sah", "layout": "dfs"}


def build(vertices: Float[np.ndarray, "V 3"], faces: Int[np.ndarray, "F 3"], *, leaf_size: int = 1,
          builder: str = "lbvh", layout: str = "bfs", sah_settings: SahSettings = SAH_DEFAULT) -> BVH:
    """Build a BVH over triangles `vertices[faces]` (host numpy, vectorised; see `jaxrt.accel.builder`).

    builder: "lbvh" (default: Morton-code splits, `jaxrt.accel.builder`; the full dragon in ~1–1.9 s
    on a 2-core CPU) or "sah" (binned SAH splits down to 16 triangles, Morton splits below,
    `jaxrt.accel.sah`: ~10 % fewer node visits per ray, ~1.2–1.4x the LBVH's build time). layout:
    node numbering, "bfs" (default: breadth-first) or "dfs" (depth-first: every subtree contiguous
    in memory). sah_settings: the SAH builder's `jaxrt.accel.sah.SahSettings`. All give the same
    array layout, so every traversal takes any of them.
    `RENDER_TREE` is what scenes use: built once, traced every frame. BENCHMARKS.md ("Tree
    quality") has the measurements.

    vertices (V,3) float, faces (F,3) int in [0, V). Raises InputError on NaN/Inf vertices,
    out-of-range indices or no faces. Zero-area faces are kept (they are never hit).
    """
    a = build_arrays(vertices, faces, leaf_size=leaf_size, builder=builder, layout=layout,
                     sah_settings=sah_settings)
    put = jax.device_put
    arrays = {k: put(a[k]) for k in ("node_box", "node_leaf", "links", "triangles")}
    rows = skips = None
    if leaf_size == 1 and jax.default_backend() == "gpu":
        rows, skips = _pack_tables(**arrays, layout=traverse_pallas.TREE_LAYOUT)
    return BVH(**arrays, prim_ids=put(a["prim_ids"]), rows=rows, skips=skips, leaf_size=leaf_size)


_pack_tables = jax.jit(traverse_pallas.pack_tables, static_argnames="layout")


def shapes(num_faces: int, *, leaf_size: int = 1) -> BVH | None:
    """The `BVH` that `build` returns for `num_faces` triangles, as `jax.ShapeDtypeStruct`s (shapes and
    dtypes only), or None where they cannot be known before the build.

    With leaf_size 1 every builder makes a full binary tree with one triangle per leaf (a node is
    split while it holds more than `leaf_size`; each split has two non-empty children), so it has
    num_faces leaves and 2·num_faces − 1 nodes whatever the split positions. That is enough to
    compile the programs that take the tree while it is being built (`jaxrt.scene.build`'s
    `on_shapes`). Larger leaves give a node count that depends on the splits: None.
    """
    if leaf_size != 1 or num_faces < 1:
        return None
    nn = 2 * int(num_faces) - 1
    s = jax.ShapeDtypeStruct
    arrays = dict(node_box=s((nn, 6), jnp.float32), node_leaf=s((nn, 2), jnp.int32),
                  links=s((NUM_RAY_CLASSES * nn, 2), jnp.int32), triangles=s((num_faces, 9), jnp.float32))
    rows = skips = None
    if jax.default_backend() == "gpu":  # as `build`
        rows, skips = jax.eval_shape(functools.partial(_pack_tables, layout=traverse_pallas.TREE_LAYOUT), **arrays)
    return BVH(**arrays, prim_ids=s((num_faces,), jnp.int32), rows=rows, skips=skips, leaf_size=leaf_size)


def stats(tree: BVH) -> BVHStats:
    """Node count, depth, SAH cost and leaf sizes of a built tree (host-side)."""
    box = np.asarray(tree.node_box, np.float64)
    leaf = np.asarray(tree.node_leaf)
    links = np.asarray(tree.links)
    nn = box.shape[0]
    is_leaf = leaf[:, 1] > 0
    first = links[:nn, 0]  # class 0: first child (interior)
    second = links[np.where(is_leaf, 0, first), 1]  # the first child's miss link is its sibling
    depth = np.zeros(nn, np.int64)
    frontier = np.array([0])
    d = 0
    while len(frontier):
        depth[frontier] = d
        inner = frontier[~is_leaf[frontier]]
        frontier = np.concatenate([first[inner], second[inner]])
        d += 1
    ext = box[:, 3:] - box[:, :3]
    area = ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0]
    rel = area / max(area[0], 1e-300)
    counts = leaf[is_leaf, 1]
    sah = float(np.sum(rel[~is_leaf]) + np.sum(rel[is_leaf] * leaf[is_leaf, 1]))
    return BVHStats(nodes=nn, leaves=int(is_leaf.sum()), depth=int(depth.max()), sah_cost=sah,
                    leaf_size_min=int(counts.min()), leaf_size_max=int(counts.max()),
                    leaf_size_mean=float(counts.mean()), triangles=int(tree.prim_ids.shape[0]))


def default_lanes() -> int:
    # CPU: a lane pool whose state stays in cache; GPU: enough lanes to fill the device.
    return 1024 if jax.default_backend() == "cpu" else 1 << 17


def default_steps() -> int:
    return 2 if jax.default_backend() == "cpu" else 16


IMPLS = _config.TRAVERSALS


def _impl(impl: str | None) -> str:
    impl = impl or _config.config().traversal
    if impl not in IMPLS:
        raise InputError(f"bvh: traversal impl (argument or JAXRT_TRAVERSAL) must be one of {IMPLS}; got {impl!r}")
    return impl


def _points(tree, found, best, u, v):
    """Hit points and unit geometric normals of the hits (found, best, u, v), from the leaf-order
    triangle table in float32: `jaxrt.shading.surface.make_surface`'s arithmetic (the point from the
    barycentrics, the normalised cross product of the edges), so a surface built from them is the
    one built from the gathered corners; zeros on a miss."""
    tri = tree.triangles[jnp.maximum(best, 0)]
    v0, v1, v2 = tri[:, 0:3], tri[:, 3:6], tri[:, 6:9]
    p = (1.0 - u - v)[:, None] * v0 + u[:, None] * v1 + v[:, None] * v2
    n = jnp.cross(v1 - v0, v2 - v0)
    n2 = n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2]
    ok = n2 > 1e-30
    ng = jnp.where(ok[:, None], n * lax.rsqrt(jnp.where(ok, n2, 1.0))[:, None], 0.0)
    return jnp.where(found[:, None], p, 0.0), jnp.where(found[:, None], ng, 0.0)


def _run(tree, origins, directions, tmin, tmax, *, any_hit, lanes, steps_per_iter, count_steps=False, impl=None,
         refine=False, points=False, order=None):
    origins = lax.stop_gradient(jnp.asarray(origins, jnp.float32))
    directions = lax.stop_gradient(jnp.asarray(directions, jnp.float32))
    if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
        raise InputError(f"bvh: origins and directions must both be (N,3); got {origins.shape} and {directions.shape}")
    n = origins.shape[0]
    tmin = jnp.broadcast_to(lax.stop_gradient(jnp.asarray(tmin, jnp.float32)), (n,))
    tmax = jnp.broadcast_to(lax.stop_gradient(jnp.asarray(tmax, jnp.float32)), (n,))
    if n == 0:
        z = jnp.zeros(0, jnp.float32)
        z3 = ((jnp.zeros((0, 3), jnp.float32),) * 2) if points else ()
        return jnp.zeros(0, bool), z, jnp.zeros(0, jnp.int32), z, z, jnp.zeros(0, jnp.int32), *z3
    arrays = dict(node_box=tree.node_box, node_leaf=tree.node_leaf, links=tree.links, triangles=tree.triangles)
    if tree.rows is not None:
        arrays["rows"], arrays["skips"] = tree.rows, tree.skips

    def with_points(out):
        # the hit points and normals of the kernels that do not return them, from the table
        if not points:
            return out
        found, t, best, u, v, steps = out
        u, v = jnp.where(found, u, 0.0), jnp.where(found, v, 0.0)
        return (found, t, best, u, v, steps, *_points(tree, found, best, u, v))

    def refined(out, o, d):
        # Once per ray: t of the chosen triangle in double-float, so grazing hits keep ~1e-7
        # relative accuracy (the float32 test's t degrades as eps / cos(angle)).
        found, t, best, u, v, steps = out
        if refine:
            t = traverse_xla.refine_t(tree.triangles[jnp.maximum(best, 0)], o, d, t)
        return with_points((found, t, best, u, v, steps))

    def xla(o, d, lo, hi):
        return refined(traverse_xla.traverse(arrays, o, d, lo, hi, any_hit=any_hit, leaf_size=tree.leaf_size,
                                             steps_per_iter=steps_per_iter or default_steps(),
                                             lanes=lanes or default_lanes(), count_steps=count_steps), o, d)

    def pallas(o, d, lo, hi, interpret=False):
        # The interpreter runs program instances one after another: few, wide blocks are fastest.
        kw = dict(block=1024) if interpret else {}
        out = traverse_pallas.traverse(arrays, o, d, lo, hi, any_hit=any_hit, leaf_size=tree.leaf_size,
                                  interpret=interpret, order=order, **kw)
        return refined((*out, jnp.zeros(n, jnp.int32)), o, d)

    def native(o, d, lo, hi):
        # the kernel refines t itself, in double, for hits only
        out = traverse_cpu.traverse(arrays, o, d, lo, hi, any_hit=any_hit, refine=refine)
        return with_points((*out, jnp.zeros(n, jnp.int32)))

    def embree(o, d, lo, hi):
        # Embree's scene is built from the leaf-order triangle table: its primID is `best`; the
        # kernel has each hit's triangle at hand and returns its point and normal itself
        out = traverse_embree.traverse(tree.triangles, o, d, lo, hi, any_hit=any_hit, refine=refine, points=points,
                                       key=tree.table_key)
        found, t, best, u, v, *pn = out
        return (found, t, best, u, v, jnp.zeros(n, jnp.int32), *pn)

    impl = _impl(impl)
    args = (origins, directions, tmin, tmax)
    if impl == "xla" or count_steps:
        return xla(*args)
    if impl == "pallas":
        return pallas(*args)
    if impl == "pallas-interpret":
        return pallas(*args, interpret=True)
    # available() compiles the C++ kernels on first use; where Embree is not installed "embree" and
    # "auto" use the native kernel, and where that cannot be compiled it warns once and they use the
    # XLA loop. A GPU process does not build them for "auto" (its functions are lowered for the GPU).
    on_cpu = impl in ("cpu", "embree") or (impl == "auto" and jax.default_backend() == "cpu")
    has_embree = on_cpu and impl != "cpu" and traverse_embree.available()
    if impl == "embree" and not has_embree:
        traverse_embree.note_missing()  # asked for by name: say once that it is not there
    has_native = on_cpu and not has_embree and traverse_cpu.available()
    cpu = embree if has_embree else native if has_native else xla
    if impl in ("cpu", "embree"):
        return cpu(*args)
    backend = jax.default_backend()
    if backend == "cpu":
        # a process without an accelerator lowers everything for the CPU: trace only that branch
        # (tracing the Pallas kernel and the XLA loop too took 1-2.5 s of every first frame)
        return cpu(*args)
    if backend == "gpu" and jax.export.default_export_platform() == "cuda":
        # likewise a process whose default device is an NVIDIA GPU traces only the Pallas kernel;
        # a computation such a process places on its CPU device needs JAXRT_TRAVERSAL=cpu or xla
        return pallas(*args)
    # auto: the Pallas (Triton) kernel where the computation is lowered for an NVIDIA GPU, the
    # native kernel for the CPU, the portable XLA loop elsewhere (decided at lowering, so one
    # jitted function serves all).
    return lax.platform_dependent(*args, cuda=pallas, cpu=cpu, default=xla)


def uses_embree(impl: str | None = None) -> bool:
    """Whether `intersect` and `occluded` with this impl (None: JAXRT_TRAVERSAL) trace through Embree
    in a function lowered for the default backend."""
    impl = _impl(impl)
    on_cpu = impl == "embree" or (impl == "auto" and jax.default_backend() == "cpu")
    return on_cpu and traverse_embree.available()


def with_table_key(tree: BVH, impl: str | None = None) -> BVH:
    """The tree with Embree's key of its triangle table (`traverse_embree.table_key`) where its ray
    queries go through Embree (`uses_embree`), else the tree unchanged.

    Embree's kernel finds its scene by a hash of the table; without a key every call computes it
    (one pass over the table: ~2-4 ms for the 871k-triangle dragon), with one the calls skip it. Call
    this inside the traced function that traces the tree, on the tree it traces: the key is computed
    there from the same triangles, so it follows any edit of them made before (`eqx.tree_at` on the
    scene). A tree whose triangles are replaced after this call carries a stale key: don't keep
    keyed trees (the kernel's spot check of 64 rows catches most such tables, not all)."""
    if not uses_embree(impl):
        return tree
    return eqx.tree_at(lambda t: t.table_key, tree, traverse_embree.table_key(tree.triangles),
                       is_leaf=lambda x: x is None)


def intersect(
    tree: BVH,
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmin: Float[Array, " N"] | float = 0.0,
    tmax: Float[Array, " N"] | float = jnp.inf,
    *,
    lanes: int | None = None,
    steps_per_iter: int | None = None,
    impl: str | None = None,
    order: Int[Array, " N"] | None = None,
) -> Hit:
    """Closest hit of each ray with t in [tmin, tmax] (see the module docstring).

    lanes: rays in flight at once (default 1024 on CPU, 2**17 on GPU; finished lanes refill from
    the queue); steps_per_iter: traversal steps per loop iteration (default 2 on CPU, 16 on GPU).
    Both only affect speed, never results, and apply to the XLA loop only. impl: "auto" (default;
    the default device's kernel: the Pallas kernel of `jaxrt.accel.traverse_pallas` where it is an
    NVIDIA GPU, Embree (`jaxrt.accel.traverse_embree`) where it is the CPU and Embree is installed, else
    the C++ kernel of `jaxrt.accel.traverse_cpu` there, else the XLA loop; a process that places work
    on a device other than its default one chooses with impl), "xla" (the pure-JAX loop of
    `jaxrt.accel.traverse_xla`), "cpu" (the C++ kernel; CPU only), "embree" (Embree, else the C++
    kernel; CPU only), "pallas" (GPU only) or
    "pallas-interpret" (the kernel in the Pallas interpreter, any backend, slow: for tests); the
    env var JAXRT_TRAVERSAL sets it when the argument is None. Where the C++ kernel cannot be
    compiled, "auto", "embree" and "cpu" warn once and use the XLA loop.
    All give the same hits up to ties between triangles at the same distance to within an ulp.
    order: a hint, a permutation of the rays in which the GPU kernel takes them (the live rays of a
    batch first, say: `traverse_pallas.traverse`); the other back ends ignore it.
    """
    # t comes refined (each traversal's t of the chosen triangle in double(-float) precision) and is
    # clamped to the valid interval.
    found, t, best, u, v, _ = _run(tree, origins, directions, tmin, tmax, any_hit=False, lanes=lanes,
                                   steps_per_iter=steps_per_iter, impl=impl, refine=True, order=order)
    prim = jnp.where(found, tree.prim_ids[jnp.maximum(best, 0)], -1)
    t = jnp.clip(t, jnp.asarray(tmin, jnp.float32), jnp.asarray(tmax, jnp.float32))
    return Hit(t=jnp.where(found, t, jnp.inf), prim=prim, u=jnp.where(found, u, 0.0), v=jnp.where(found, v, 0.0))


def intersect_few(
    triangles: Float[Array, "L 9"],
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmin: Float[Array, " N"] | float = 0.0,
    tmax: Float[Array, " N"] | float = jnp.inf,
    *,
    exact: bool = True,
) -> Hit:
    """Closest hit of each ray with t in [tmin, tmax] among a few triangles (rows [v0, v1, v2]),
    every ray against every triangle: the trees' watertight test (Woop, Benthin & Wald 2013, with
    exact edge signs; `traverse_xla.intersect_triangles`), no tree, loop or conditional, so it fuses
    into the computation around it. prim indexes the rows of `triangles` (-1 on a miss). The work is
    N·L tests: for a handful of triangles (a scene's emitters, say), not for a mesh.

    exact=False: edge signs from the rounded products alone, where a tie (a ray within rounding of an
    edge or vertex) counts as inside, so shared edges still lose no ray but such a ray may also hit a
    triangle it passes by an ulp; and t as float32 computes it (not refined). About a third of the
    arithmetic, for callers to whom an ulp at an edge and t's last digits do not matter."""
    o = jnp.asarray(origins, jnp.float32)
    d = jnp.asarray(directions, jnp.float32)
    n = o.shape[0]
    lo = jnp.broadcast_to(jnp.asarray(tmin, jnp.float32), (n,))
    hi = jnp.broadcast_to(jnp.asarray(tmax, jnp.float32), (n,))
    tri = jnp.asarray(triangles, jnp.float32)[None]
    ray = traverse_xla.precompute(o, d)
    hit, t, u, v = traverse_xla.intersect_triangles(ray, tri, lo, hi, jnp.ones((n, tri.shape[1]), bool), exact=exact)
    # the nearest by a running selection, triangle after triangle (elementwise: on a GPU a reduction
    # over a short row axis is a kernel of its own)
    best_t, best, best_u, best_v = jnp.full((n,), jnp.inf), jnp.full((n,), -1, jnp.int32), jnp.zeros(n), jnp.zeros(n)
    for j in range(tri.shape[1]):
        closer = hit[:, j] & (t[:, j] < best_t)
        best_t = jnp.where(closer, t[:, j], best_t)
        best = jnp.where(closer, j, best)
        best_u, best_v = jnp.where(closer, u[:, j], best_u), jnp.where(closer, v[:, j], best_v)
    if exact:
        # t of the chosen triangle in double-float, as the trees' hits (grazing rays lose float32's t)
        rows = tri[0][jnp.maximum(best, 0)]
        best_t = jnp.where(best >= 0, jnp.clip(traverse_xla.refine_t(rows, o, d, best_t), lo, hi), jnp.inf)
    return Hit(t=best_t, prim=best, u=best_u, v=best_v)


def intersect_points(
    tree: BVH,
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmin: Float[Array, " N"] | float = 0.0,
    tmax: Float[Array, " N"] | float = jnp.inf,
    *,
    lanes: int | None = None,
    steps_per_iter: int | None = None,
    impl: str | None = None,
) -> tuple[Hit, Float[Array, "N 3"], Float[Array, "N 3"]]:
    """`intersect`, and the hit point p and unit geometric normal ng of each hit (zeros on a miss).

    p is the barycentric point (1-u-v)·v0 + u·v1 + v·v2 and ng = (v1-v0) × (v2-v0) normalised (the
    winding's normal), as `jaxrt.shading.surface.make_surface` computes them from the corners:
    Embree's kernel returns them with the hit, computed in double from the triangle it has at hand
    and rounded once (within a few float32 ulps of the corners' float32 arithmetic), so a caller
    needs no gathers of the corners; the other traversals compute them from the triangle table with
    `make_surface`'s float32 arithmetic (the same values). Not differentiable (the traversal's
    inputs are under stop_gradient): a differentiable surface comes from `prim`, u, v.
    """
    found, t, best, u, v, _, p, ng = _run(tree, origins, directions, tmin, tmax, any_hit=False, lanes=lanes,
                                          steps_per_iter=steps_per_iter, impl=impl, refine=True, points=True)
    prim = jnp.where(found, tree.prim_ids[jnp.maximum(best, 0)], -1)
    t = jnp.clip(t, jnp.asarray(tmin, jnp.float32), jnp.asarray(tmax, jnp.float32))
    hit = Hit(t=jnp.where(found, t, jnp.inf), prim=prim, u=jnp.where(found, u, 0.0), v=jnp.where(found, v, 0.0))
    return hit, p, ng


def intersect_points_shadowed(
    tree: BVH,
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmin: Float[Array, " N"] | float,
    tmax: Float[Array, " N"] | float,
    lights: Float[Array, "L 3"],
) -> tuple[Hit, Float[Array, "N 3"], Float[Array, "N 3"], Bool[Array, "N L"]]:
    """`intersect_points`, and whether each hit's shadow segment to each of L point lights is
    blocked, in one Embree call (`traverse_embree.direct`; only where `uses_embree()`: the caller
    checks). The segments are those of the Whitted trace loop (`jaxrt.integrators.whitted.
    shadow_segments`: from the hit offset along its geometric normal, turned towards the ray, to
    the light), made in the kernel with the same float32 operations and traced from the light's end
    as `occluded(from_end=True)`; False on misses and for lights behind the oriented normal. Not
    differentiable."""
    if not uses_embree():
        raise InputError("bvh.intersect_points_shadowed: Embree's CPU traversal only (see `uses_embree`)")
    o = lax.stop_gradient(jnp.asarray(origins, jnp.float32))
    d = lax.stop_gradient(jnp.asarray(directions, jnp.float32))
    n = o.shape[0]
    lo = jnp.broadcast_to(lax.stop_gradient(jnp.asarray(tmin, jnp.float32)), (n,))
    hi = jnp.broadcast_to(lax.stop_gradient(jnp.asarray(tmax, jnp.float32)), (n,))
    found, t, best, u, v, p, ng, occ = traverse_embree.direct(tree.triangles, o, d, lo, hi,
                                                              lax.stop_gradient(lights))
    prim = jnp.where(found, tree.prim_ids[jnp.maximum(best, 0)], -1)
    t = jnp.clip(t, lo, hi)
    hit = Hit(t=jnp.where(found, t, jnp.inf), prim=prim, u=jnp.where(found, u, 0.0), v=jnp.where(found, v, 0.0))
    return hit, p, ng, occ


def occluded(
    tree: BVH,
    origins: Float[Array, "N 3"],
    directions: Float[Array, "N 3"],
    tmax: Float[Array, " N"] | float = jnp.inf,
    tmin: Float[Array, " N"] | float = 0.0,
    *,
    lanes: int | None = None,
    steps_per_iter: int | None = None,
    impl: str | None = None,
    from_end: bool = False,
    order: Int[Array, " N"] | None = None,
) -> Bool[Array, " N"]:
    """True where any triangle is hit with t in [tmin, tmax] (any-hit, stops at the first hit).

    For a shadow ray from p towards a light at distance L along unit d, pass tmax = L*(1-eps)
    and tmin (or an offset origin) to skip the surface the ray starts on. lanes, steps_per_iter,
    impl: as for `intersect`. from_end: trace each ray with finite tmax backwards, from
    o + tmax*d along -d over [0, tmax - tmin] (the same segment; its far end rounded to float32):
    shadow rays towards one light then share their origin, which a GPU warp traverses more
    coherently, and find occluders nearer the light first. Rays with infinite tmax go forwards.
    order: as for `intersect`.
    """
    if from_end:
        o = jnp.asarray(origins, jnp.float32)
        d = jnp.asarray(directions, jnp.float32)
        lo = jnp.broadcast_to(jnp.asarray(tmin, jnp.float32), o.shape[:1])
        hi = jnp.broadcast_to(jnp.asarray(tmax, jnp.float32), o.shape[:1])
        fin = jnp.isfinite(hi)
        origins = jnp.where(fin[:, None], o + jnp.where(fin, hi, 0.0)[:, None] * d, o)
        directions = jnp.where(fin[:, None], -d, d)
        tmin, tmax = jnp.where(fin, 0.0, lo), jnp.where(fin, hi - lo, hi)
    found, *_ = _run(tree, origins, directions, tmin, tmax, any_hit=True, lanes=lanes,
                     steps_per_iter=steps_per_iter, impl=impl, order=order)
    return found


def node_visits(tree: BVH, origins, directions, tmin=0.0, tmax=jnp.inf, *, any_hit: bool = False,
                lanes: int | None = None, steps_per_iter: int | None = None) -> Int[Array, " N"]:
    """Traversal steps (nodes visited) per ray; for benchmarks and diagnostics."""
    *_, steps = _run(tree, origins, directions, tmin, tmax, any_hit=any_hit, lanes=lanes,
                     steps_per_iter=steps_per_iter, count_steps=True)
    return steps
