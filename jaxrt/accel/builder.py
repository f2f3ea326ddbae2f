"""BVH construction in vectorised numpy (host side). Public entry point: `jaxrt.accel.bvh.build`.

The builder is a top-down LBVH (Lauterbach et al. 2009; Karras 2012's split rule): triangle
centroids are quantised to 17 bits per axis and sorted by 51-bit Morton code; a node covering the
sorted range [s, e) splits where the highest Morton bit that differs between its first and last
code flips (a binary search), or at the middle where all codes are equal. Every node of a level is
split at once, so a level costs a handful of numpy calls and the whole build is dominated by the
sort. Leaves hold at most `leaf_size` triangles, which are contiguous in the sorted order, so the
triangles are stored in leaf order with `prim_ids` mapping back to the original face index.

For stackless traversal the tree is threaded six times, once per ray class (dominant direction
axis x/y/z and its sign): in class c, an interior node's children are ordered near-to-far along
that axis, and each node stores `links[c, node] = (hit, miss)`: where to go after its box is hit
(the first child; for a leaf, the same as miss) and where to go after its box is missed or its
leaf is done (the next node in that class's pre-order after the subtree, -1 at the end). This is
the multiple-threaded BVH of Hachisuka (2015) in flat-array form.

`finish` (bounds, threading, output) is shared with the binned-SAH topology of `jaxrt.accel.sah`;
nodes are numbered breadth-first, or depth-first with layout="dfs" (subtrees contiguous in memory).
"""

from __future__ import annotations

import numpy as np

from jaxrt.accel import sah
from jaxrt.accel.morton import highest_bit, morton_codes
from jaxrt.errors import InputError

NUM_RAY_CLASSES = 6  # (dominant axis, sign)


BUILDERS = ("lbvh", "sah")
LAYOUTS = ("bfs", "dfs")


def build_arrays(vertices, faces, leaf_size: int = 4, builder: str = "lbvh",
                 layout: str = "bfs", sah_settings: sah.SahSettings = sah.DEFAULT) -> dict[str, np.ndarray]:
    """Build the flat BVH arrays (see `jaxrt.accel.bvh.BVH` for their layout). Host-side numpy.

    builder: "lbvh" (Morton-code splits, this module) or "sah" (binned SAH splits for large nodes,
    Morton splits below; `jaxrt.accel.sah`). Both give the same output layout. layout: node
    numbering, "bfs" (breadth-first) or "dfs" (depth-first; see `finish`).
    """
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"bvh.build: vertices must be (V,3) and faces (F,3); got {v.shape} and {f.shape}")
    if len(f) == 0:
        raise InputError("bvh.build: no triangles")
    if not np.all(np.isfinite(v)):
        raise InputError("bvh.build: vertices contain NaN or Inf")
    if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
        raise InputError(f"bvh.build: face indices must be integers in [0, {len(v) - 1}]")
    if not 1 <= leaf_size <= 16:
        raise InputError(f"bvh.build: leaf_size must be in 1..16, got {leaf_size}")
    if builder not in BUILDERS:
        raise InputError(f"bvh.build: builder must be one of {BUILDERS}, got {builder!r}")
    if layout not in LAYOUTS:
        raise InputError(f"bvh.build: layout must be one of {LAYOUTS}, got {layout!r}")
    v = v.astype(np.float32)
    tri = v[f]  # (F, 3, 3)
    nf = len(f)
    tmin = np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])
    tmax = np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
    cent = tmin + tmax  # twice the box centre; Morton quantisation is scale-free
    codes = morton_codes(cent)
    order = np.argsort(codes, kind="stable")
    if builder == "sah":
        order, left, start, count, levels = sah.topology(tmin, tmax, cent, codes, order, leaf_size, sah_settings)
        return finish(tri, tmin, tmax, order, left, start, count, levels, layout)
    cs = codes[order]

    # --- topology, one level at a time (breadth-first numbering: children > parent) ---------------
    cap = 2 * nf
    left = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    parent = np.full(cap, -1, np.int64)
    levels = []
    ids, s, e = np.array([0]), np.array([0]), np.array([nf])
    nn = 1
    while len(ids):
        levels.append(ids)
        start[ids], count[ids] = s, e - s
        inner = (e - s) > leaf_size
        ids, s, e = ids[inner], s[inner], e[inner]
        if not len(ids):
            break
        x = cs[s] ^ cs[e - 1]
        same = x == 0
        b = highest_bit(np.where(same, np.uint64(1), x))
        target = (cs[e - 1] >> b) << b
        split = np.where(same, (s + e) // 2, np.searchsorted(cs, target, side="left"))
        k = len(ids)
        lid = nn + 2 * np.arange(k)
        left[ids] = lid
        parent[lid], parent[lid + 1] = ids, ids
        nn += 2 * k
        ids = np.stack([lid, lid + 1], axis=1).ravel()
        s, e = np.stack([s, split], axis=1).ravel(), np.stack([split, e], axis=1).ravel()
    return finish(tri, tmin, tmax, order, left[:nn], start[:nn], count[:nn], levels, layout)


def finish(tri, tmin, tmax, order, left, start, count, levels, layout: str = "bfs") -> dict[str, np.ndarray]:
    """Bounds, threading and leaf-order triangles of a topology (shared by the builders).

    tri (F,3,3) float32 and tmin/tmax (F,3) their boxes, order (F,) leaf order -> face index;
    left/start/count (nn,) int64 per node: first child (children are left, left + 1; -1 for a
    leaf), first position in `order` and triangle count; levels: node ids per depth, breadth-first
    numbering (every child id > its parent's). layout: "bfs" keeps that numbering in the output,
    "dfs" renumbers the nodes in depth-first (class 0 pre-) order.
    """
    nn = len(left)
    nf = len(order)
    is_leaf = left < 0
    count = np.where(is_leaf, count, 0)

    # --- bounds, bottom-up -------------------------------------------------------------------------
    lo = np.empty((nn, 3), np.float32)
    hi = np.empty((nn, 3), np.float32)
    leaves = np.flatnonzero(is_leaf)
    leaves = leaves[np.argsort(start[leaves])]
    lo[leaves] = np.minimum.reduceat(np.take(tmin, order, axis=0), start[leaves], axis=0)
    hi[leaves] = np.maximum.reduceat(np.take(tmax, order, axis=0), start[leaves], axis=0)
    depth = np.empty(nn, np.int64)
    for k, ids in enumerate(levels):
        depth[ids] = k
    levels = [ids[~is_leaf[ids]] for ids in levels]  # interior nodes per level
    for ids in reversed(levels):
        if len(ids):
            lo[ids] = np.minimum(lo[left[ids]], lo[left[ids] + 1])
            hi[ids] = np.maximum(hi[left[ids]], hi[left[ids] + 1])
    # Pad outward by a few ulps so that a triangle lying in a box face is never culled by the
    # float32 slab test (the traversal also widens the far distance; see traverse_xla).
    lo_pad = lo - np.abs(lo) * np.float32(2.0**-20) - np.float32(1e-30)
    hi_pad = hi + np.abs(hi) * np.float32(2.0**-20) + np.float32(1e-30)

    # --- threading: one pre-order per ray class -----------------------------------------------------
    size = np.ones(nn, np.int64)  # nodes in subtree
    for ids in reversed(levels):
        size[ids] = 1 + size[left[ids]] + size[left[ids] + 1]
    ctr = (lo.astype(np.float64) + hi).T.copy()  # (3, nn) twice the box centre
    ar = np.arange(nn)
    at = np.empty(nn + 1, np.int64)  # node at each pre-order index (nn: -1, the end)
    at[nn] = -1
    links = np.empty((NUM_RAY_CLASSES, nn, 2), np.int32)
    sibling_sum = np.where(is_leaf, 0, 2 * left + 1)  # first + second child of an interior node

    def thread(c, pre, first):
        at[pre] = ar
        miss = at[pre + size]
        links[c, :, 1] = miss
        links[c, :, 0] = np.where(is_leaf, miss, first)

    # Class 2*axis orders each node's children by their centres along the axis, level by level;
    # class 2*axis + 1 (negative direction) visits every node's children the other way round, i.e.
    # the mirrored pre-order, in which the nodes before X are X's ancestors and the nodes that the
    # positive order visits after X's subtree: pre' = depth + nn - pre - size.
    for axis in range(3):
        pre = np.zeros(nn, np.int64)  # pre-order index
        first = np.full(nn, -1, np.int64)
        for ids in levels:
            if not len(ids):
                continue
            a = left[ids]
            n1 = np.where(ctr[axis][a] <= ctr[axis][a + 1], a, a + 1)
            first[ids] = n1
            p_par = pre[ids] + 1
            pre[n1] = p_par
            pre[(2 * a + 1) - n1] = p_par + size[n1]
        thread(2 * axis, pre, first)
        if axis == 0:
            pre0, order0 = pre, at[:nn].copy()
        thread(2 * axis + 1, depth + nn - pre - size, np.where(is_leaf, -1, sibling_sum - first))
    box = np.concatenate([lo_pad, hi_pad], axis=1).astype(np.float32)
    unpadded = np.concatenate([lo, hi], axis=1)
    node_leaf = np.stack([start, count], axis=1)
    if layout == "dfs":
        # Renumber nodes in class 0's pre-order: every subtree is one contiguous run of rows, so
        # a ray's nodes share cache lines (the breadth-first numbering spreads a subtree over
        # every level). The root stays 0; links are node ids, so they are mapped too.
        new = np.append(pre0, -1).astype(np.int32)  # new id of each old id; -1 stays -1
        old = order0  # old id of each new id
        for c in range(NUM_RAY_CLASSES):
            links[c] = np.take(new, np.take(links[c], old, axis=0))
        box, unpadded, node_leaf = box[old], unpadded[old], node_leaf[old]

    tri_sorted = np.take(tri, order, axis=0)
    return dict(
        node_box=box,  # (nn, 6)
        node_leaf=node_leaf.astype(np.int32),  # (nn, 2)
        links=links.reshape(NUM_RAY_CLASSES * nn, 2),
        triangles=tri_sorted.reshape(nf, 9).astype(np.float32, copy=False),
        prim_ids=order.astype(np.int32),
        unpadded_box=unpadded,
    )
