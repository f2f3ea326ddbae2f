"""Binned-SAH BVH topology in vectorised numpy (host side); `bvh.build(..., builder="sah")`.

Top-down, one level at a time like the LBVH of `jaxrt.bvh_build`, but a node with more than
`SAH_MIN` triangles is split by the surface area heuristic over `BINS` centroid bins along the
axis of its widest centroid extent (Wald 2007): all nodes of a level are binned at once (bin
counts by `np.bincount`, bin boxes by one `np.minimum.at` of (lo, -hi) on (node, bin) keys), the
sweep over the bins' prefix / suffix boxes is a cumulative min/max along the bin axis, and each
node's triangles are partitioned stably in place (segmented prefix sums), so they stay contiguous
and in Morton order. Nodes with at most `SAH_MIN` triangles (and nodes whose centroids all fall
in one bin) take the LBVH split: the highest differing Morton bit, found by a vectorised binary
search inside the node's range (O(nodes) per level, where binning is O(triangles)).

Measured (BENCHMARKS.md, "Tree quality"): SAH splits pay at every level, not only the top ones
(full dragon SAH cost: LBVH 60.9, threshold 1024 → 60.0, 16 → 53.8, 0 → 52.3), and the build costs
about twice the LBVH's. The output topology (breadth-first numbering, children `left` and
`left + 1`) goes through the same `bvh_build.finish` as the LBVH, so the layout, the six threaded
link orders and both traversals are unchanged.
"""

from __future__ import annotations

import numpy as np

from jaxrt.bvh_build import _highest_bit

BINS = 16  # 32 measured no better
SAH_MIN = 16  # nodes with more triangles are binned; a module setting so benchmarks can vary it
ALL_AXES = False  # bin all three axes: lower SAH cost, but no fewer node visits (measured)


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half surface area of boxes (..., 3); 0 for empty boxes (lo = +inf)."""
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _sah_split(tmin, tmax, cent, order, s, e, bins):
    """Left-child size per node by binned SAH (0 where no bin split separates the centroids).

    Nodes are the ranges [s, e) of `order`. Returns nl (k,) int64; for the n elements of the
    concatenated ranges: left flag (n,) bool, position in `order` (n,) and node (n,); and the
    offset of each node's first element in that concatenation (k,).
    """
    k = len(s)
    cnt = e - s
    g = np.repeat(np.arange(k), cnt)  # node of each element
    offs = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    pos = np.arange(len(g)) - offs[g] + s[g]
    tri = order[pos]
    c = cent[tri]
    clo = np.minimum.reduceat(c, offs, axis=0)
    chi = np.maximum.reduceat(c, offs, axis=0)
    ext = chi - clo
    lohi = np.concatenate([tmin[tri], -tmax[tri]], axis=1)
    cands = range(3) if ALL_AXES else [None]
    best_cost = np.full(k, np.inf)
    best_j = np.zeros(k, np.int64)
    best_nl = np.zeros(k, np.int64)
    b_best = np.zeros(len(g), np.int64)
    for cand in cands:
        axis = np.argmax(ext, axis=1) if cand is None else np.full(k, cand)
        ea = ext[np.arange(k), axis]
        ca = c[np.arange(len(g)), axis[g]]
        scale = np.where(ea > 0, bins * (1 - 1e-6) / np.where(ea > 0, ea, 1), 0.0)
        b = ((ca - clo[g, axis[g]]) * scale[g]).astype(np.int64)
        np.clip(b, 0, bins - 1, out=b)
        key = g * bins + b
        nb = np.bincount(key, minlength=k * bins).reshape(k, bins)
        # bin boxes as one min-reduction of (lo, -hi): one scatter pass instead of two
        box = np.full((k * bins, 6), np.inf, np.float32)
        np.minimum.at(box, key, lohi)
        box = box.reshape(k, bins, 6)
        blo, bhi = box[..., :3], -box[..., 3:]
        # split after bin j: left = bins 0..j, right = bins j+1..
        llo = np.minimum.accumulate(blo, axis=1)[:, :-1]
        lhi = np.maximum.accumulate(bhi, axis=1)[:, :-1]
        rlo = np.minimum.accumulate(blo[:, ::-1], axis=1)[:, ::-1][:, 1:]
        rhi = np.maximum.accumulate(bhi[:, ::-1], axis=1)[:, ::-1][:, 1:]
        nl = np.cumsum(nb, axis=1)[:, :-1]
        nr = cnt[:, None] - nl
        cost = _area(llo.astype(np.float64), lhi) * nl + _area(rlo.astype(np.float64), rhi) * nr
        cost = np.where((nl > 0) & (nr > 0), cost, np.inf)
        j = np.argmin(cost, axis=1)
        cj = cost[np.arange(k), j]
        better = cj < best_cost
        best_cost = np.where(better, cj, best_cost)
        best_j = np.where(better, j, best_j)
        best_nl = np.where(better, nl[np.arange(k), j], best_nl)
        b_best = np.where(better[g], b, b_best)
    ok = np.isfinite(best_cost)
    j, b = best_j, b_best
    is_left = b <= j[g]
    return np.where(ok, best_nl, 0), is_left & ok[g], pos, g, offs


def topology(tmin, tmax, cent, codes, order, leaf_size, bins: int | None = None, sah_min: int | None = None):
    """Node topology by binned SAH (nodes above sah_min triangles) and Morton splits (below).

    tmin/tmax (F,3) float32 triangle boxes, cent (F,3) their centres (any fixed scale), codes (F,)
    uint64 Morton codes, order (F,) the Morton sort. Returns (order, left, start, count, levels)
    in `bvh_build.finish`'s form; `order` is a new array (leaf order -> face index).
    """
    bins = BINS if bins is None else bins
    sah_min = SAH_MIN if sah_min is None else sah_min
    order = order.copy()
    nf = len(order)
    cap = 2 * nf
    left = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
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
        split = np.zeros(len(ids), np.int64)
        big = (e - s) > sah_min
        if big.any():
            sb, eb = s[big], e[big]
            nl, is_left, pos, g, offs = _sah_split(tmin, tmax, cent, order, sb, eb, bins)
            # stable partition of each range: lefts first, in their (Morton) order, then rights
            cl = np.cumsum(is_left) - is_left  # lefts before each element, globally
            rank_l = cl - cl[offs][g]
            rank_r = (pos - sb[g]) - rank_l
            nl_g = nl[g]
            moved = nl > 0
            newpos = np.where(is_left, sb[g] + rank_l, sb[g] + nl_g + rank_r)
            keep = moved[g]
            order[newpos[keep]] = order[pos[keep]].copy()
            split[big] = np.where(moved, sb + nl, -1)
        small = split <= 0
        if small.any():
            # Morton split of [s, e) (codes are sorted inside every range): the first position
            # whose code has the highest differing bit set, by a vectorised binary search.
            ss, es = s[small], e[small]
            cs_s, cs_e = codes[order[ss]], codes[order[es - 1]]
            x = cs_s ^ cs_e
            same = x == 0
            bit = _highest_bit(np.where(same, np.uint64(1), x))
            target = (cs_e >> bit) << bit
            lo, hi = ss.copy(), es - 1
            for _ in range(int(np.max(es - ss)).bit_length() + 1):
                mid = (lo + hi) // 2
                below = codes[order[mid]] < target
                lo, hi = np.where(below, mid + 1, lo), np.where(below, hi, mid)
            split[small] = np.where(same, (ss + es) // 2, lo)
        k = len(ids)
        lid = nn + 2 * np.arange(k)
        left[ids] = lid
        nn += 2 * k
        ids = np.stack([lid, lid + 1], axis=1).ravel()
        s, e = np.stack([s, split], axis=1).ravel(), np.stack([split, e], axis=1).ravel()
    return order, left[:nn], start[:nn], count[:nn], levels
