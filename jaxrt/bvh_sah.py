"""Binned-SAH BVH topology in vectorised numpy (host side); `bvh.build(..., builder="sah")`.

Top-down, one level at a time like the LBVH of `jaxrt.bvh_build`, but a node with more than
`SAH_MIN` triangles is split by the surface area heuristic over `BINS` centroid bins along the
axis of its widest centroid extent (Wald 2007). Nodes with at most `SAH_MIN` triangles (and nodes
whose centroids all coincide) take the LBVH split: the highest differing Morton bit, or the middle.

The build runs in two phases so that no level moves triangle data:
1. SAH levels. The triangles stay in Morton order; each carries the (temporary) id of the node it
   is in. Per level, every binned node's centroid bounds, bin counts and bin boxes are scatter
   reductions keyed by node (and bin): `np.minimum.at` / `np.maximum.at` on 1-D float32 rows,
   numpy's fast path (a 2-D `.at` or a `reduceat` along the triangle axis is ~10x slower), and
   `np.bincount`. The sweep over the bins' prefix / suffix boxes is a cumulative min/max along
   the bin axis; a split only relabels triangles (left or right child), so nothing is partitioned
   per level. Triangles of nodes that stop being binned are dropped from the working arrays.
2. One stable counting sort (two 16-bit radix passes) by the start of each triangle's final SAH
   node puts every node's triangles in one contiguous range, still in Morton order inside; then
   the Morton splits of the small nodes run on those ranges (a vectorised binary search per level,
   O(nodes)), and the nodes are renumbered breadth-first.
The result is the same tree, node numbering and leaf order as splitting level by level with a
stable partition of each node (the first version of this module; checked in tests/test_bvh_sah.py
against a plain recursive build). The output goes through the same `bvh_build.finish` as the
LBVH, so the layout, the six threaded link orders and both traversals are unchanged.

Measured (BENCHMARKS.md, "Tree quality"): SAH splits pay at every level, not only the top ones
(full dragon SAH cost: LBVH 60.9, threshold 1024 → 60.0, 16 → 53.8, 0 → 52.3).
"""

from __future__ import annotations

import numpy as np

from jaxrt.bvh_build import _highest_bit

BINS = 16  # 32 measured no better
SAH_MIN = 16  # nodes with more triangles are binned; a module setting so benchmarks can vary it
ALL_AXES = False  # bin all three axes: lower SAH cost, but no fewer node visits (measured)
_COMPACT = 0.2  # drop finished triangles from the working arrays once they are this fraction


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half surface area of boxes (..., 3); 0 for empty boxes (lo = +inf)."""
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _segment_reduce(ufunc, rows: np.ndarray, key: np.ndarray, size: int) -> np.ndarray:
    """Per-key np.minimum or np.maximum of each row of rows (r, n) float32 (keys (n,) in
    [0, size)): (r, size), +inf / -inf where a key has no element."""
    out = np.full((len(rows), size), np.inf if ufunc is np.minimum else -np.inf, np.float32)
    for r in range(len(rows)):
        ufunc.at(out[r], key, rows[r])
    return out


def _sweep(nb: np.ndarray, blo: np.ndarray, bhi: np.ndarray, cnt: np.ndarray):
    """Best binned split per node: (cost (k,) float64, inf where no split separates the
    triangles; bin j (k,): left = bins 0..j; left count (k,)). nb (k, bins) counts, blo/bhi
    (k, bins, 3) float32 bin boxes, cnt (k,) triangles per node."""
    k = len(cnt)
    llo = np.minimum.accumulate(blo, axis=1)[:, :-1]
    lhi = np.maximum.accumulate(bhi, axis=1)[:, :-1]
    rlo = np.minimum.accumulate(blo[:, ::-1], axis=1)[:, ::-1][:, 1:]
    rhi = np.maximum.accumulate(bhi[:, ::-1], axis=1)[:, ::-1][:, 1:]
    nl = np.cumsum(nb, axis=1)[:, :-1]
    nr = cnt[:, None] - nl
    cost = _area(llo.astype(np.float64), lhi) * nl + _area(rlo.astype(np.float64), rhi) * nr
    cost = np.where((nl > 0) & (nr > 0), cost, np.inf)
    j = np.argmin(cost, axis=1)
    return cost[np.arange(k), j], j, nl[np.arange(k), j]


def _stable_order(key: np.ndarray) -> np.ndarray:
    """Stable argsort of non-negative integer keys below 2**32 by two 16-bit radix passes (numpy's
    stable sort is a radix sort for 16-bit types; for wider ones it is a much slower timsort)."""
    p1 = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    if int(key.max(initial=0)) < 1 << 16:
        return p1
    p2 = np.argsort((key[p1] >> 16).astype(np.uint16), kind="stable")
    return p1[p2]


def topology(tmin, tmax, cent, codes, order, leaf_size, bins: int | None = None, sah_min: int | None = None):
    """Node topology by binned SAH (nodes above sah_min triangles) and Morton splits (below).

    tmin/tmax (F,3) float32 triangle boxes, cent (F,3) float32 their centres (any fixed scale),
    codes (F,) uint64 Morton codes, order (F,) the Morton sort. Returns (order, left, start,
    count, levels) in `bvh_build.finish`'s form; `order` is a new array (leaf order -> face index).
    """
    bins = BINS if bins is None else bins
    sah_min = SAH_MIN if sah_min is None else sah_min
    nf = len(order)
    big_min = max(sah_min, leaf_size)  # nodes with more triangles are binned
    cap = 2 * nf
    # Nodes in creation order ("temporary" ids); renumbered breadth-first at the end.
    tleft = np.full(cap, -1, np.int64)
    tstart = np.zeros(cap, np.int64)
    tcount = np.zeros(cap, np.int64)
    tcount[0] = nf
    ntemp = 1
    split_levels = []  # (parents, their left children) per SAH level, for the starts

    # --- phase 1: SAH levels on triangles in Morton order, labelled with their node -------------
    label = np.zeros(nf, np.int64)  # final phase-1 node of each triangle (Morton position)
    pos = np.arange(nf)  # Morton positions of the working triangles
    # rows: lo xyz, hi xyz, centre xyz of the working triangles, in Morton order
    x = np.take(np.concatenate([tmin.T, tmax.T, cent.T]).astype(np.float32), order, axis=1)
    lab = np.zeros(nf, np.int64)
    big = np.array([0]) if nf > big_min else np.zeros(0, np.int64)
    while len(big):
        k = len(big)
        loc_of = np.full(ntemp, k, np.int64)  # node id -> row of this level's tables (k: not binned)
        loc_of[big] = np.arange(k)
        loc = loc_of[lab]
        n_big = int(tcount[big].sum())
        if len(lab) - n_big > _COMPACT * len(lab):  # drop triangles whose nodes are finished
            keep = loc < k
            gone = ~keep
            label[pos[gone]] = lab[gone]
            idx = np.flatnonzero(keep)
            x, pos, lab, loc = np.take(x, idx, axis=1), pos[idx], lab[idx], loc[idx]
        n = len(lab)
        cnt = tcount[big]
        clo = _segment_reduce(np.minimum, x[6:], loc, k + 1)
        chi = _segment_reduce(np.maximum, x[6:], loc, k + 1)
        ext = chi[:, :k] - clo[:, :k]  # (3, k) centroid extents
        cands = range(3) if ALL_AXES else [None]
        best_cost = np.full(k, np.inf)
        best_j = np.zeros(k, np.int64)
        best_nl = np.zeros(k, np.int64)
        b_best = None
        rows = np.arange(n)
        for cand in cands:
            axis = np.argmax(ext, axis=0) if cand is None else np.full(k, cand)
            ea = ext[axis, np.arange(k)]
            scale = np.where(ea > 0, bins * (1 - 1e-6) / np.where(ea > 0, ea, 1), 0.0).astype(np.float32)
            # per-row tables with a last row for the triangles of nodes not binned at this level
            axis_t = np.append(axis, 0)
            clo_t = np.append(clo[axis, np.arange(k)], np.float32(0))
            scale_t = np.append(scale, np.float32(0))
            ca = np.take(x[6:].reshape(-1), axis_t[loc] * n + rows)
            b = ((ca - clo_t[loc]) * scale_t[loc]).astype(np.int64)
            np.clip(b, 0, bins - 1, out=b)
            key = loc * bins + b
            nb = np.bincount(key, minlength=(k + 1) * bins).reshape(k + 1, bins)[:k]
            blo = _segment_reduce(np.minimum, x[:3], key, (k + 1) * bins)
            bhi = _segment_reduce(np.maximum, x[3:6], key, (k + 1) * bins)
            blo = blo.reshape(3, k + 1, bins)[:, :k].transpose(1, 2, 0)  # (k, bins, 3)
            bhi = bhi.reshape(3, k + 1, bins)[:, :k].transpose(1, 2, 0)
            cj, j, nl = _sweep(nb, blo, bhi, cnt)
            better = cj < best_cost
            best_cost = np.where(better, cj, best_cost)
            best_j = np.where(better, j, best_j)
            best_nl = np.where(better, nl, best_nl)
            if b_best is None:
                b_best = b
            elif better.any():
                b_best = np.where(np.append(better, False)[loc], b, b_best)
        ok = np.isfinite(best_cost)
        # Nodes whose centroids all coincide (no bin split) take the LBVH's split for equal codes:
        # the middle of their Morton range.
        nl = np.where(ok, best_nl, cnt // 2)
        lid = ntemp + 2 * np.arange(k)
        tleft[big] = lid
        tcount[lid], tcount[lid + 1] = nl, cnt - nl
        split_levels.append((big, lid))
        ntemp += 2 * k
        right = b_best > np.append(np.where(ok, best_j, bins), bins)[loc]
        if not ok.all():
            sel = np.flatnonzero(~np.append(ok, True)[loc])  # in Morton order
            g = loc[sel]
            o = np.argsort(g, kind="stable")
            g = g[o]
            first = np.searchsorted(g, g)  # index of each group's first element
            right[sel[o]] = (np.arange(len(sel)) - first) >= nl[g]
        lab = np.where(loc < k, np.append(lid, 0)[loc] + right, lab)
        nxt = np.concatenate([lid, lid + 1])
        big = nxt[tcount[nxt] > big_min]
    label[pos] = lab

    # starts: a left child starts where its parent does, the right child after the left
    for par, lid in split_levels:
        tstart[lid] = tstart[par]
        tstart[lid + 1] = tstart[par] + tcount[lid]

    # --- phase 2: contiguous ranges (Morton order inside), Morton splits of the small nodes ------
    perm = _stable_order(tstart[label])
    order = order[perm]
    ids = np.flatnonzero((tleft[:ntemp] < 0) & (tcount[:ntemp] > leaf_size))
    while len(ids):
        s, e = tstart[ids], tstart[ids] + tcount[ids]
        # the first position whose code has the highest differing bit set, by a binary search
        cs_s, cs_e = codes[order[s]], codes[order[e - 1]]
        xb = cs_s ^ cs_e
        same = xb == 0
        bit = _highest_bit(np.where(same, np.uint64(1), xb))
        target = (cs_e >> bit) << bit
        lo, hi = s.copy(), e - 1
        for _ in range(int(np.max(e - s)).bit_length() + 1):
            mid = (lo + hi) // 2
            below = codes[order[mid]] < target
            lo, hi = np.where(below, mid + 1, lo), np.where(below, hi, mid)
        split = np.where(same, (s + e) // 2, lo)
        k = len(ids)
        lid = ntemp + 2 * np.arange(k)
        tleft[ids] = lid
        tstart[lid], tstart[lid + 1] = s, split
        tcount[lid], tcount[lid + 1] = split - s, e - split
        ntemp += 2 * k
        nxt = np.concatenate([lid, lid + 1])
        ids = nxt[tcount[nxt] > leaf_size]

    # --- breadth-first numbering: level by level, children of a level's nodes in its order ----
    left = np.full(ntemp, -1, np.int64)
    start = np.zeros(ntemp, np.int64)
    count = np.zeros(ntemp, np.int64)
    levels = []
    cur = np.array([0])  # temporary ids of this level, in breadth-first order
    nn = 0
    while len(cur):
        new = nn + np.arange(len(cur))
        nn += len(cur)
        levels.append(new)
        start[new], count[new] = tstart[cur], tcount[cur]
        inner = tleft[cur] >= 0
        left[new[inner]] = nn + 2 * np.arange(int(inner.sum()))
        tl = tleft[cur[inner]]
        cur = np.empty(2 * len(tl), np.int64)
        cur[0::2], cur[1::2] = tl, tl + 1
    return order, left, start, count, levels
