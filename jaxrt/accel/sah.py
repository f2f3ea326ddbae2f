"""Binned-SAH BVH topology in vectorised numpy (host side); `bvh.build(..., builder="sah")`.

Top-down, one level at a time like the LBVH of `jaxrt.accel.builder`, but a node with more than
`sah_min` triangles is split by the surface area heuristic over `bins` centroid bins along the
axis of its widest centroid extent (Wald 2007). Nodes with at most `sah_min` triangles (and nodes
where no bin boundary separates the centroids) take the LBVH split: the highest differing Morton
bit of their range, or its middle where all codes are equal.

The build runs in phases so that no level moves triangle data (`_sah_levels`):
1. SAH levels. The triangles stay in Morton order; each carries the (temporary) id of its node.
   Per level, every binned node's bin counts and bin boxes are scatter reductions keyed by
   (bin, node): `np.bincount` and `np.minimum.at` / `np.maximum.at` on 1-D float32 rows (numpy's
   fast path; a 2-D `.at` or a `reduceat` is several times slower). A split only relabels
   triangles (left or right child). Triangles of finished nodes are dropped from the working set.
   Centroid bounds, which place the bins, are not recomputed per node: a child's are its
   parent's cut at the split plane and clipped to twice the child's box (exact from the bins),
   so they are conservative; `exact_bounds` recomputes them (6 more scatter passes per level)
   and then gives the tree of a textbook top-down binned-SAH build, node for node.
   Near the root (nodes above `run_nodes` triangles) the elements are clusters: the triangles of
   one cell of a Morton grid coarse enough for ~`run` triangles per cell, binned at their mean
   centroid with their box and count. A cluster whose centroids straddle its node's chosen split
   plane is replaced by its triangles, so every split is the plane's exact partition; only the
   choice of the plane sees clusters.
2. One stable counting sort (two 16-bit radix passes) by the start of each triangle's last SAH
   node puts every node's triangles in one contiguous range, in Morton order inside; then the
   Morton splits of the small nodes run on those ranges (a vectorised binary search per level,
   O(nodes)), and the nodes are renumbered breadth-first.
The output goes through the same `builder.finish` as the LBVH, so the layout, the six threaded
link orders and both traversals are unchanged. Deterministic: no randomness, no threads.

Measured (BENCHMARKS.md, "Tree quality"): SAH splits pay at every level, not only the top ones
(full dragon SAH cost: LBVH 60.9, threshold 1024 → 60.0, 16 → 53.8, 0 → 52.3). The conservative
bounds and the clusters cost +0.06 % (53.79 → 53.82, node visits unchanged); the topology takes
~0.8–1 s for the full dragon (with exact bounds: ~4–5 s).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxrt.accel.morton import highest_bit
from jaxrt.errors import InputError



@dataclasses.dataclass(frozen=True)
class SahSettings:
    """The binned-SAH builder's settings (an argument of `topology`, so a build never depends on
    module state); the defaults are the measured best (BENCHMARKS.md, "Tree quality").

    bins: centroid bins per split (32 measured no better); sah_min: nodes with more triangles
    are binned, the rest split by Morton code; all_axes: bin all three axes (lower SAH cost, but
    no fewer node visits, measured); exact_bounds: exact centroid bounds per node (slower, no
    clusters); run: near the root, clusters of ~run triangles (one Morton grid cell) are binned as
    one element ... run_nodes: ... in nodes with more triangles than this (1024: SAH cost +0.1 %,
    no faster); compact: drop finished elements from the working arrays once they are this
    fraction.
    """

    bins: int = 16
    sah_min: int = 16
    all_axes: bool = False
    exact_bounds: bool = False
    run: int = 8
    run_nodes: int = 4096
    compact: float = 0.2

    def __post_init__(self):
        if not (2 <= self.bins <= 256 and self.sah_min >= 1 and self.run >= 1 and self.run_nodes >= 1
                and 0.0 < self.compact <= 1.0):
            raise InputError(f"SahSettings: out of range: {self}")


DEFAULT = SahSettings()


def _segment_reduce(ufunc, rows: np.ndarray, key: np.ndarray, size: int) -> np.ndarray:
    """Per-key np.minimum or np.maximum of each row of rows (r, n) float32 (keys (n,) in
    [0, size)): (r, size), +inf / -inf where a key has no element."""
    out = np.full((len(rows), size), np.inf if ufunc is np.minimum else -np.inf, np.float32)
    for r in range(len(rows)):
        ufunc.at(out[r], key, rows[r])
    return out


def _sweep(nb: np.ndarray, blo: np.ndarray, bhi: np.ndarray, cnt: np.ndarray, exact: bool):
    """Best binned split per node: cost (k,) (inf where no split separates the
    triangles), bin j (k,) (left = bins 0..j), left count (k,) and the children's boxes (k, 2, 6)
    [lo xyz, hi xyz] float32. nb (bins, k) counts, blo/bhi (3, bins, k) float32 bin boxes (+inf /
    -inf where empty), cnt (k,) triangles per node."""
    bins, k = nb.shape
    box = np.empty((bins, 6, k), np.float32)  # (lo, -hi): one min-sweep grows both
    box[:, :3] = blo.transpose(1, 0, 2)
    np.negative(bhi.transpose(1, 0, 2), out=box[:, 3:])
    # left[i]: bins 0..i, right[i]: bins i+1..; one bin at a time over rows of k nodes (numpy's
    # accumulate along the short bin axis is ~10x slower)
    left = np.empty((bins - 1, 6, k), np.float32)
    right = np.empty((bins - 1, 6, k), np.float32)
    left[0], right[-1] = box[0], box[-1]
    for i in range(1, bins - 1):
        np.minimum(left[i - 1], box[i], out=left[i])
        np.minimum(right[bins - 1 - i], box[bins - 1 - i], out=right[bins - 2 - i])

    # float32 is plenty to rank the splits; exact bounds rank them in float64
    dtype = np.float64 if exact else np.float32

    def area(b):  # half surface area; 0 for an empty side
        e = b[:, 3:].astype(dtype)
        e += b[:, :3]
        np.negative(e, out=e)  # hi - lo
        np.maximum(e, 0, out=e)
        return e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]

    nl = np.cumsum(nb, axis=0)[:-1]
    nr = cnt[None] - nl
    cost = area(left) * nl.astype(dtype) + area(right) * nr.astype(dtype)
    cost = np.where((nl > 0) & (nr > 0), cost, np.inf)
    j = np.argmin(cost, axis=0)
    r = np.arange(k)
    boxes = np.stack([left[j, :, r], right[j, :, r]], 1)  # (k, 2, 6)
    np.negative(boxes[..., 3:], out=boxes[..., 3:])
    return cost[j, r], j, nl[j, r], boxes


def _stable_order(key: np.ndarray) -> np.ndarray:
    """Stable argsort of non-negative integer keys below 2**32 by two 16-bit radix passes (numpy's
    stable sort is a radix sort for 16-bit types; for wider ones it is a much slower timsort)."""
    p1 = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    if int(key.max(initial=0)) < 1 << 16:
        return p1
    p2 = np.argsort((key[p1] >> 16).astype(np.uint16), kind="stable")
    return p1[p2]


def _child_bounds(clo, chi, axis, scale, j, boxes):
    """Centroid bounds (k, 2, 6) of both children of a binned split, without a pass over the
    triangles: the parent's (clo, chi (3, k)), cut at the split plane (the edge of bin j + 1 on
    `axis`) and inside twice the child's box (a centroid here is lo + hi)."""
    k = len(j)
    r = np.arange(k)
    cut = (clo[axis, r] + (j + 1) / np.where(scale > 0, scale, 1)).astype(np.float32)
    cb = np.empty((k, 2, 6), np.float32)
    cb[:, :, :3] = clo.T[:, None]
    cb[:, :, 3:] = chi.T[:, None]
    cb[r, 0, 3 + axis] = np.minimum(cb[r, 0, 3 + axis], cut)
    cb[r, 1, axis] = np.maximum(cb[r, 1, axis], cut)
    cb[..., :3] = np.maximum(cb[..., :3], 2 * boxes[..., :3])
    cb[..., 3:] = np.minimum(cb[..., 3:], 2 * boxes[..., 3:])
    return cb


class _Nodes:
    """Nodes in creation order ("temporary" ids; renumbered breadth-first at the end): first
    child (children are left, left + 1; -1 for none), first leaf-order position, triangles."""

    def __init__(self, nf: int):
        cap = 2 * nf + 1
        self.left = np.full(cap, -1, np.int64)
        self.start = np.zeros(cap, np.int64)
        self.count = np.zeros(cap, np.int64)
        self.count[0] = nf
        self.n = 1
        self.splits = []  # (parents, their left children) of every binned level

    def split(self, ids: np.ndarray, nl: np.ndarray) -> np.ndarray:
        """Give nodes `ids` two children with nl and count - nl triangles; returns the left ids."""
        lid = self.n + 2 * np.arange(len(ids))
        self.left[ids] = lid
        self.count[lid], self.count[lid + 1] = nl, self.count[ids] - nl
        self.n += 2 * len(ids)
        return lid


def _sah_levels(nodes, x, w, codes, lab, big, cb, stop, settings: SahSettings, label, pos, expand=None):
    """Binned-SAH splits, level by level, of the nodes `big` and their descendants with more
    than `stop` triangles. Elements are triangles (or clusters of them, see `expand`): x (9, n)
    float32 rows lo xyz, hi xyz, centroid xyz (as lo + hi); w (n,) triangles per element (None:
    1); codes (n,) uint64 Morton codes (a cluster's: its first triangle's); lab (n,) int64 node
    of each element; cb (k, 6) centroid bounds (lo xyz, hi xyz) of the nodes `big`. Writes the
    last node of every element into label[pos] (pos (n,): the elements' indices there).

    expand: for clusters of triangles as elements (then x has 6 more rows: the lowest and highest
    centroid of the cluster's triangles); a function from cluster positions (pos) to the
    triangles' (x, codes, pos). A cluster whose centroids straddle its node's split plane is
    replaced by its triangles, so that every split is the plane's exact partition; the bin
    counts and boxes that chose the plane count each cluster at its mean centroid."""
    bins = settings.bins
    ar = np.arange(len(lab))
    while len(big):
        k = len(big)
        cnt = nodes.count[big]
        n = len(lab)
        # node id -> row of this level's tables; k: not binned now (also for id -1, the last entry)
        loc_of = np.full(nodes.n + 1, k, np.int64)
        loc_of[big] = np.arange(k)
        loc = loc_of[lab]
        gone = loc == k
        n_gone = int(gone.sum())
        if n_gone > settings.compact * n:  # drop the elements of finished nodes
            label[pos[gone]] = lab[gone]
            keep = np.flatnonzero(~gone)
            x, pos, lab, loc, codes = np.take(x, keep, axis=1), pos[keep], lab[keep], loc[keep], codes[keep]
            w = None if w is None else w[keep]
            n, n_gone = len(lab), 0
        if settings.exact_bounds:
            clo = _segment_reduce(np.minimum, x[6:], loc, k + 1)[:, :k]
            chi = _segment_reduce(np.maximum, x[6:], loc, k + 1)[:, :k]
        else:
            clo, chi = np.ascontiguousarray(cb[:, :3].T), np.ascontiguousarray(cb[:, 3:].T)
        ext = chi - clo  # (3, k)
        xc = x[6:].reshape(-1)
        rows = ar[:n]
        for ci, cand in enumerate(range(3) if settings.all_axes else [None]):
            axis = np.argmax(ext, axis=0) if cand is None else np.full(k, cand)
            ea = ext[axis, np.arange(k)]
            scale = np.where(ea > 0, bins * (1 - 1e-6) / np.where(ea > 0, ea, 1), 0.0).astype(np.float32)
            # per-node tables with a last row for the elements of nodes not binned at this level
            ca = np.take(xc, np.append(axis * n, 0)[loc] + rows)
            ca -= np.append(clo[axis, np.arange(k)], np.float32(0))[loc]
            ca *= np.append(scale, np.float32(0))[loc]
            b = ca.astype(np.int64)
            np.clip(b, 0, bins - 1, out=b)
            key = b * (k + 1)  # bin-major: (bin, node)
            key += loc
            nb = np.bincount(key, w, minlength=bins * (k + 1)).reshape(bins, k + 1)[:, :k].astype(np.int64)
            blo = _segment_reduce(np.minimum, x[:3], key, bins * (k + 1)).reshape(3, bins, k + 1)[:, :, :k]
            bhi = _segment_reduce(np.maximum, x[3:6], key, bins * (k + 1)).reshape(3, bins, k + 1)[:, :, :k]
            cost, j, nl, boxes = _sweep(nb, blo, bhi, cnt, settings.exact_bounds)
            ccb = _child_bounds(clo, chi, axis, scale, j, boxes)
            if ci == 0:
                best = [cost, j, nl, boxes, ccb, key]
                split_axis, split_scale = axis, scale
            else:
                better = cost < best[0]
                key = np.where(np.append(better, False)[loc], key, best[5])
                best = [np.where(better.reshape((-1,) + (1,) * (np.ndim(a) - 1)), a, o)
                        for a, o in zip([cost, j, nl, boxes, ccb], best[:5])] + [key]
        cost, j, nl, boxes, ccb, key = best
        ok = np.isfinite(cost)
        lid = nodes.n + 2 * np.arange(k)
        # child of each (bin, node): left for bins 0..j; a last column for unbinned elements
        child = np.zeros((bins, k + 1), np.int64)
        child[:, :k] = lid + ((np.arange(bins)[:, None] > j) & ok)
        new = child.reshape(-1)[key]
        if expand is not None:
            # clusters on both sides of the plane: replaced by their triangles (at the end)
            ta = np.append(split_axis, 0)[loc]
            c0 = np.append(clo[split_axis, np.arange(k)], np.float32(0))[loc]
            sc = np.append(split_scale, np.float32(0))[loc]
            xa = x[9:].reshape(-1)
            bmin = ((np.take(xa, ta * n + rows) - c0) * sc).astype(np.int64)
            bmax = ((np.take(xa, (ta + 3) * n + rows) - c0) * sc).astype(np.int64)
            jj = np.append(np.where(ok, j, bins), bins)[loc]
            # (and every cluster of a node without a bin split: it takes a Morton split below)
            cut = np.flatnonzero(((bmin <= jj) & (bmax > jj)) | (~np.append(ok, True)[loc] & (w > 1)))
            if len(cut):
                tx, tcodes, tpos = expand(pos[cut])
                tn = np.repeat(np.arange(len(cut)), w[cut])  # cluster of each triangle
                tloc = loc[cut][tn]
                tb = ((np.take(tx[6:9].reshape(-1), split_axis[tloc] * tx.shape[1] + np.arange(tx.shape[1]))
                       - clo[split_axis[tloc], tloc]) * split_scale[tloc]).astype(np.int64)
                tnew = lid[tloc] + ((tb > j[tloc]) & ok[tloc])
                loc[cut], lab[cut] = k, -1  # the clusters themselves leave the working set
                x = np.concatenate([x, tx], axis=1)
                w = np.concatenate([w, np.ones(len(tn), w.dtype)])
                codes, pos = np.concatenate([codes, tcodes]), np.concatenate([pos, tpos])
                loc, new = np.concatenate([loc, tloc]), np.concatenate([new, tnew])
                lab = np.concatenate([lab, np.full(len(tn), -1, np.int64)])
                n = len(lab)
                rows = ar[:n] if n <= len(ar) else np.arange(n)
                ar = rows
        if not ok.all():
            # No bin split separates the centroids: the LBVH's split of the node's Morton range
            # (the first code with the highest differing bit set; the middle where all are equal).
            sel = np.flatnonzero(~np.append(ok, True)[loc])
            o = np.lexsort((codes[sel], loc[sel]))  # by node, then Morton code (stable)
            sel = sel[o]
            g = loc[sel]
            first = np.searchsorted(g, g)  # index of each node's first element
            last = np.searchsorted(g, g, side="right") - 1
            cs = codes[sel]
            xb = cs[first] ^ cs[last]
            same = xb == 0
            bit = highest_bit(np.where(same, np.uint64(1), xb))
            target = (cs[last] >> bit) << bit
            ws = np.ones(len(sel), np.int64) if w is None else w[sel]
            before = np.cumsum(ws) - ws  # triangles before each element ...
            before -= before[first]  # ... in its node
            r = np.where(same, before >= cnt[g] // 2, cs >= target)
            new[sel] += r
            nl = np.where(ok, nl, np.bincount(g, ws * ~r, minlength=k).astype(np.int64))
            # exact boxes and centroid bounds of their children
            side = 2 * g + r
            bad = np.flatnonzero(~ok)
            lo6 = _segment_reduce(np.minimum, np.concatenate([x[:3][:, sel], x[6:9][:, sel]]), side, 2 * k)
            hi6 = _segment_reduce(np.maximum, np.concatenate([x[3:6][:, sel], x[6:9][:, sel]]), side, 2 * k)
            boxes[bad] = np.concatenate([lo6[:3], hi6[:3]]).T.reshape(k, 2, 6)[bad]
            ccb[bad] = np.concatenate([lo6[3:], hi6[3:]]).T.reshape(k, 2, 6)[bad]
        if expand is not None:
            # exact counts and boxes of the children (a cluster counts in the bin of its mean)
            side = np.where((loc < k) & (new >= 0), new - nodes.n, 2 * k)
            nl2 = np.bincount(side, w, minlength=2 * k + 1)[:2 * k].astype(np.int64).reshape(k, 2)
            bl = _segment_reduce(np.minimum, x[:3], side, 2 * k + 1)[:, :2 * k]
            bh = _segment_reduce(np.maximum, x[3:6], side, 2 * k + 1)[:, :2 * k]
            bx = np.concatenate([bl, bh]).T.reshape(k, 2, 6)
            boxes = np.where(ok[:, None, None], bx, boxes)
            nl = np.where(ok, nl2[:, 0], nl)
            ccb[..., :3] = np.maximum(ccb[..., :3], 2 * boxes[..., :3])
            ccb[..., 3:] = np.minimum(ccb[..., 3:], 2 * boxes[..., 3:])
        lab = np.where(loc < k, new, lab) if n_gone or expand is not None else new
        nodes.splits.append((big, nodes.split(big, nl)))
        nxt = np.concatenate([lid, lid + 1])
        keep_n = nodes.count[nxt] > stop
        big = nxt[keep_n]
        cb = np.concatenate([ccb[:, 0], ccb[:, 1]])[keep_n]
    label[pos] = lab


def topology(tmin, tmax, cent, codes, order, leaf_size, settings: SahSettings = DEFAULT):
    """Node topology by binned SAH (nodes above sah_min triangles) and Morton splits (below).

    tmin/tmax (F,3) float32 triangle boxes, cent (F,3) float32 their centres as tmin + tmax,
    codes (F,) uint64 Morton codes, order (F,) the Morton sort. Returns (order, left, start,
    count, levels) in `builder.finish`'s form; `order` is a new array (leaf order -> face index).
    """
    sah_min = settings.sah_min
    nf = len(order)
    big_min = max(sah_min, leaf_size)  # nodes with more triangles are binned
    nodes = _Nodes(nf)
    # --- phase 1: SAH levels on triangles in Morton order, labelled with their node -------------
    # rows: lo xyz, hi xyz, centroid xyz of the triangles in Morton order
    x = np.empty((9, nf), np.float32)
    for r, a in enumerate((tmin, tmax, cent)):
        x[3 * r:3 * r + 3] = np.take(a, order, axis=0).T
    codes_m = codes[order]
    label = np.zeros(nf, np.int64)  # final phase-1 node of each triangle (Morton position)
    if nf > big_min:
        if nf > settings.run_nodes and not (settings.all_axes or settings.exact_bounds):
            # Near the root, bin clusters instead of triangles: the triangles of one cell of a
            # coarser Morton grid (consecutive in Morton order; ~run per cluster) as one element
            # with their box, mean centroid, centroid bounds and count.
            grid = codes_m.copy()
            for _ in range(17):
                if np.count_nonzero(grid[1:] != grid[:-1]) < nf / settings.run:
                    break
                grid >>= np.uint64(3)
            first = np.flatnonzero(np.concatenate([[True], grid[1:] != grid[:-1]]))
            nc = len(first)
            cl = np.repeat(np.arange(nc), np.diff(np.append(first, nf)))
            wr = np.bincount(cl, minlength=nc)
            mean = np.stack([np.bincount(cl, x[6 + a], minlength=nc) for a in range(3)]) / wr
            xr = np.concatenate([_segment_reduce(np.minimum, x[:3], cl, nc),
                                 _segment_reduce(np.maximum, x[3:6], cl, nc), mean.astype(np.float32),
                                 _segment_reduce(np.minimum, x[6:], cl, nc),
                                 _segment_reduce(np.maximum, x[6:], cl, nc)])

            def expand(p):
                """x rows (with centroid bounds), codes and positions (nc + Morton position) of
                the triangles of clusters p."""
                m = wr[p]
                t = np.repeat(first[p] - (np.cumsum(m) - m), m) + np.arange(int(m.sum()))
                tx = np.take(x, t, axis=1)
                return np.concatenate([tx, tx[6:], tx[6:]]), codes_m[t], nc + t

            lab_r = np.full(nc + nf, -1, np.int64)
            cb = np.concatenate([xr[6:9].min(1), xr[6:9].max(1)])[None]
            _sah_levels(nodes, xr, wr, codes_m[first], np.zeros(nc, np.int64), np.array([0]), cb,
                        settings.run_nodes, settings, lab_r, np.arange(nc), expand)
            label = np.where(lab_r[nc:] >= 0, lab_r[nc:], lab_r[cl])
        big = np.flatnonzero((nodes.left[:nodes.n] < 0) & (nodes.count[:nodes.n] > big_min))
        if len(big):
            # the centroid bounds of the nodes to bin, exact
            loc_of = np.full(nodes.n, len(big), np.int64)
            loc_of[big] = np.arange(len(big))
            loc = loc_of[label]
            cb = np.concatenate([_segment_reduce(np.minimum, x[6:], loc, len(big) + 1),
                                 _segment_reduce(np.maximum, x[6:], loc, len(big) + 1)])[:, :-1].T
            _sah_levels(nodes, x, None, codes_m, label.copy(), big, cb, big_min, settings, label, np.arange(nf))
    tleft, tstart, tcount, ntemp = nodes.left, nodes.start, nodes.count, nodes.n
    split_levels = nodes.splits

    # starts: a left child starts where its parent does, the right child after the left
    for par, lid in split_levels:
        tstart[lid] = tstart[par]
        tstart[lid + 1] = tstart[par] + tcount[lid]

    # --- phase 2: contiguous ranges (Morton order inside), Morton splits of the small nodes ------
    perm = _stable_order(tstart[label])
    order = order[perm]
    cs = codes_m[perm]  # codes in the new order
    ids = np.flatnonzero((tleft[:ntemp] < 0) & (tcount[:ntemp] > leaf_size))
    while len(ids):
        s, e = tstart[ids], tstart[ids] + tcount[ids]
        # the first position whose code has the highest differing bit set, by a binary search
        cs_s, cs_e = cs[s], cs[e - 1]
        xb = cs_s ^ cs_e
        same = xb == 0
        bit = highest_bit(np.where(same, np.uint64(1), xb))
        target = (cs_e >> bit) << bit
        lo, hi = s.copy(), e - 1
        for _ in range(int(np.max(e - s)).bit_length() + 1):
            mid = (lo + hi) // 2
            below = cs[mid] < target
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
    start = np.empty(ntemp, np.int64)
    count = np.empty(ntemp, np.int64)
    levels = []
    cur = np.array([0])  # temporary ids of this level, in breadth-first order
    nn = 0
    while len(cur):
        m = len(cur)
        levels.append(np.arange(nn, nn + m))
        start[nn:nn + m], count[nn:nn + m] = tstart[cur], tcount[cur]
        tl = tleft[cur]
        inner = tl >= 0
        tl = tl[inner]
        left[nn:nn + m][inner] = nn + m + 2 * np.arange(len(tl))
        nn += m
        cur = np.empty(2 * len(tl), np.int64)
        cur[0::2], cur[1::2] = tl, tl + 1
    return order, left, start, count, levels
