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
_COMPACT = 0.2  # drop finished units from the working arrays once they are this fraction
FAN = 8  # triangles per unit grow by this factor per unit level
UNIT_LEVELS = 3  # unit sizes 1, FAN, FAN**2
_DEBUG = False


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


def _reduce_runs(rows: np.ndarray, fan: int, ufunc) -> np.ndarray:
    """ufunc.reduce of rows (r, n) over runs of `fan` consecutive columns (the last run may be
    shorter): (r, ceil(n / fan))."""
    q = rows.shape[1] // fan
    out = ufunc.reduce(rows[:, :q * fan].reshape(len(rows), q, fan), axis=2)
    if rows.shape[1] > q * fan:
        out = np.concatenate([out, ufunc.reduce(rows[:, q * fan:], axis=1, keepdims=True)], axis=1)
    return out


def _unit_levels(x: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """Rows and triangle counts of the units of each level (see `topology`). x (9, F): lo, hi
    and centroid rows of the triangles in Morton order (level 0); higher levels have 12 rows: lo,
    hi, lowest and highest centroid of their FAN**l triangles."""
    rows, cnt = [x], [None]
    lo, hi, cmin, cmax, c = x[:3], x[3:6], x[6:9], x[6:9], np.ones(x.shape[1], np.int64)
    for _ in range(1, UNIT_LEVELS):
        if lo.shape[1] <= 1:
            break
        lo, hi = _reduce_runs(lo, FAN, np.minimum), _reduce_runs(hi, FAN, np.maximum)
        cmin, cmax = _reduce_runs(cmin, FAN, np.minimum), _reduce_runs(cmax, FAN, np.maximum)
        c = _reduce_runs(c[None], FAN, np.add)[0]
        rows.append(np.concatenate([lo, hi, cmin, cmax]))
        cnt.append(c)
    return rows, cnt


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

    # --- phase 1: SAH levels on units of triangles, each labelled with its node ---------------
    # A unit is a run of FAN**l consecutive triangles of the Morton order (level l; level 0: one
    # triangle) with its box and centroid bounds. While a unit's centroids fall in one bin of its
    # node (the bin of its lowest and of its highest centroid agree: binning is monotone) it is
    # binned as a whole, which gives the same counts and bin boxes as its triangles; otherwise it
    # is replaced by its FAN sub-units. Near the root most of the work is on units of FAN**2.
    x = np.take(np.concatenate([tmin.T, tmax.T, cent.T]).astype(np.float32), order, axis=1)
    lev_rows, lev_cnt = _unit_levels(x)
    nlev = len(lev_rows)
    top = nlev - 1
    m_top = lev_rows[top].shape[1]
    g_rows = [np.zeros((len(r), 0), np.float32) for r in lev_rows]
    g_idx = [np.zeros(0, np.int64) for _ in range(nlev)]
    g_lab = [np.zeros(0, np.int64) for _ in range(nlev)]
    g_rows[top], g_idx[top], g_lab[top] = lev_rows[top], np.arange(m_top), np.zeros(m_top, np.int64)
    done = [[] for _ in range(nlev)]  # (unit index, final phase-1 node) of finished units

    def cnt_of(lv):
        return None if lv == 0 else lev_cnt[lv][g_idx[lv]]

    def cmin(lv):  # rows of the lowest centroids (level 0: the centroids themselves)
        return g_rows[lv][6:9]

    def cmax(lv):
        return g_rows[lv][9:12] if lv else g_rows[lv][6:9]

    big = np.array([0]) if nf > big_min else np.zeros(0, np.int64)
    while len(big):
        k = len(big)
        loc_of = np.full(ntemp + 1, k, np.int64)  # node id -> row of this level's tables; k: none
        loc_of[big] = np.arange(k)
        g_loc = []
        for lv in range(nlev):
            loc = loc_of[g_lab[lv]]
            gone = loc == k  # units of finished nodes (or replaced: label -1)
            if gone.sum() > _COMPACT * len(loc):
                fin = gone & (g_lab[lv] >= 0)
                done[lv].append((g_idx[lv][fin], g_lab[lv][fin]))
                keep = np.flatnonzero(~gone)
                g_rows[lv], g_idx[lv], g_lab[lv] = np.take(g_rows[lv], keep, axis=1), g_idx[lv][keep], g_lab[lv][keep]
                loc = loc[keep]
            g_loc.append(loc)
        if _DEBUG:
            print("level", len(split_levels), "k", k, "units", [len(q) for q in g_loc])
        cnt = tcount[big]
        clo = np.full((3, k + 1), np.inf, np.float32)
        chi = np.full((3, k + 1), -np.inf, np.float32)
        for lv in range(nlev):
            for r in range(3):
                np.minimum.at(clo[r], g_loc[lv], cmin(lv)[r])
                np.maximum.at(chi[r], g_loc[lv], cmax(lv)[r])
        ext = chi[:, :k] - clo[:, :k]  # (3, k) centroid extents
        # per candidate axis: per-row tables, with a last row for units not binned at this level
        tabs = []
        for cand in (range(3) if ALL_AXES else [None]):
            axis = np.argmax(ext, axis=0) if cand is None else np.full(k, cand)
            ea = ext[axis, np.arange(k)]
            scale = np.where(ea > 0, bins * (1 - 1e-6) / np.where(ea > 0, ea, 1), 0.0).astype(np.float32)
            tabs.append((np.append(axis, 0), np.append(clo[axis, np.arange(k)], np.float32(0)),
                         np.append(scale, np.float32(0))))

        def bin_of(rows, loc, tab, bins=bins):
            axis_t, clo_t, scale_t = tab
            n = len(loc)
            ca = np.take(rows.reshape(-1), axis_t[loc] * n + np.arange(n))
            b = ((ca - clo_t[loc]) * scale_t[loc]).astype(np.int64)
            return np.clip(b, 0, bins - 1, out=b)

        def push(lv, parents, lab, loc):
            """Append the sub-units of units `parents` of level lv + 1 to level lv's working set."""
            child = (parents[:, None] * FAN + np.arange(FAN)).ravel()
            ok_c = child < lev_rows[lv].shape[1]
            child = child[ok_c]
            g_rows[lv] = np.concatenate([g_rows[lv], np.take(lev_rows[lv], child, axis=1)], axis=1)
            g_idx[lv] = np.concatenate([g_idx[lv], child])
            g_lab[lv] = np.concatenate([g_lab[lv], np.repeat(lab, FAN)[ok_c]])
            g_loc[lv] = np.concatenate([g_loc[lv], np.repeat(loc, FAN)[ok_c]])

        # bins of every unit for every candidate axis, top level first: a unit whose centroids
        # span more than one bin is replaced by its sub-units (binned when their level comes)
        g_b = [None] * nlev
        for lv in reversed(range(nlev)):
            bs = [bin_of(cmin(lv), g_loc[lv], tab) for tab in tabs]
            if lv:
                split = np.zeros(len(g_loc[lv]), bool)
                for tab, b in zip(tabs, bs):
                    split |= b != bin_of(cmax(lv), g_loc[lv], tab)
                if split.any():
                    sel = np.flatnonzero(split)
                    push(lv - 1, g_idx[lv][sel], g_lab[lv][sel], g_loc[lv][sel])
                    g_lab[lv][sel] = -1
                    g_loc[lv][sel] = k
                    for b in bs:
                        b[sel] = 0
            g_b[lv] = bs
        best_cost = np.full(k, np.inf)
        best_j = np.zeros(k, np.int64)
        best_nl = np.zeros(k, np.int64)
        b_best = [b[0] for b in g_b]
        for ci in range(len(tabs)):
            nb = np.zeros((k + 1) * bins, np.int64)
            blo = np.full((3, (k + 1) * bins), np.inf, np.float32)
            bhi = np.full((3, (k + 1) * bins), -np.inf, np.float32)
            for lv in range(nlev):
                key = g_loc[lv] * bins + g_b[lv][ci]
                w = cnt_of(lv)
                nb += np.bincount(key, w, minlength=(k + 1) * bins).astype(np.int64)
                for r in range(3):
                    np.minimum.at(blo[r], key, g_rows[lv][r])
                    np.maximum.at(bhi[r], key, g_rows[lv][3 + r])
            nb = nb.reshape(k + 1, bins)[:k]
            blo = blo.reshape(3, k + 1, bins)[:, :k].transpose(1, 2, 0)  # (k, bins, 3)
            bhi = bhi.reshape(3, k + 1, bins)[:, :k].transpose(1, 2, 0)
            cj, j, nl = _sweep(nb, blo, bhi, cnt)
            better = cj < best_cost
            best_cost = np.where(better, cj, best_cost)
            best_j = np.where(better, j, best_j)
            best_nl = np.where(better, nl, best_nl)
            if ci and better.any():
                for lv in range(nlev):
                    b_best[lv] = np.where(np.append(better, False)[g_loc[lv]], g_b[lv][ci], b_best[lv])
        ok = np.isfinite(best_cost)
        # Nodes whose centroids all coincide (no bin split) take the LBVH's split for equal codes:
        # the middle of their Morton range, so their units are taken down to single triangles.
        nl = np.where(ok, best_nl, cnt // 2)
        lid = ntemp + 2 * np.arange(k)
        tleft[big] = lid
        tcount[lid], tcount[lid + 1] = nl, cnt - nl
        split_levels.append((big, lid))
        ntemp += 2 * k
        ok_t = np.append(ok, True)
        if not ok.all():
            for lv in reversed(range(1, nlev)):
                sel = np.flatnonzero(~ok_t[g_loc[lv]])
                if len(sel):
                    n0 = len(g_loc[lv - 1])
                    push(lv - 1, g_idx[lv][sel], g_lab[lv][sel], g_loc[lv][sel])
                    b_best[lv - 1] = np.concatenate([b_best[lv - 1], np.zeros(len(g_loc[lv - 1]) - n0, np.int64)])
                    g_lab[lv][sel] = -1
                    g_loc[lv][sel] = k
        j_t = np.append(np.where(ok, best_j, bins), bins)
        child_t = np.append(lid, 0)
        for lv in range(nlev):
            loc = g_loc[lv]
            right = b_best[lv] > j_t[loc]
            if lv == 0 and not ok.all():
                sel = np.flatnonzero(~ok_t[loc])
                o = np.lexsort((g_idx[0][sel], loc[sel]))  # by node, then Morton position
                sel = sel[o]
                g = loc[sel]
                first = np.searchsorted(g, g)  # index of each node's first triangle
                right[sel] = (np.arange(len(sel)) - first) >= nl[g]
            g_lab[lv] = np.where(loc < k, child_t[loc] + right, g_lab[lv])
        nxt = np.concatenate([lid, lid + 1])
        big = nxt[tcount[nxt] > big_min]
    label = np.empty(nf, np.int64)  # final phase-1 node of each triangle (Morton position)
    for lv in range(nlev):
        live = g_lab[lv] >= 0
        idx = np.concatenate([g_idx[lv][live]] + [d[0] for d in done[lv]])
        lab = np.concatenate([g_lab[lv][live]] + [d[1] for d in done[lv]])
        run = FAN ** lv
        p = (idx[:, None] * run + np.arange(run)).ravel()
        inside = p < nf
        label[p[inside]] = np.repeat(lab, run)[inside]

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
