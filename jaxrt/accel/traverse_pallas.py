"""BVH traversal as one Pallas kernel (Triton backend on GPU; interpret mode anywhere, for tests).

The pure-XLA traversal (`jaxrt.accel.traverse_xla.traverse`) keeps every lane's state in HBM arrays and
pays a device->host round trip for the while-loop predicate every `steps_per_iter` steps. Here each
program instance takes a block of `block` consecutive rays (image tiles: coherent), keeps their
state in registers and loops on the GPU until all of the block's rays end; the GPU's block
scheduler starts the next block on a free multiprocessor, which is the lane refill of the XLA path
done by hardware.

Results are the XLA path's: the same stackless links and node order, box test (same slab formula
and far-distance widening) and watertight triangle test with exact edge signs (as there, the exact
path runs only where some tested pair's rounded products tie: here a branch per program of 32
rays). The default node table (`pack_rows`, stored once per tree as `BVH.rows`) puts each interior
node's two children's boxes in its row and each leaf's triangle in the leaf's row: a step loads one
row, tests both children and moves straight to the nearer child that is hit, so children whose
boxes miss are never loaded (27 % fewer steps than one box per row, measured with the dragon's camera
and shadow rays); the miss links of the threaded tree still order the traversal. A miss link always
leads to a node's farther child, whose box the ray tested when it visited the parent: a per-ray bit
trail (one bit per depth, set when both children were hit) says whether it was hit, and where not the
ray takes that node's miss link at once instead of stepping into it (`pack_skips`: a quarter of the
dragon's steps, simulated). The kernel is bound by instruction issue more than by memory
(BENCHMARKS.md): the triangle test runs only in warps where some ray is at a leaf, and u, v are
divided once per ray at the end. The per-ray constants are `predicates.ray_constants`, computed
in the kernel. The hit distance is float32 and may differ from the XLA path's in the last ulp where
the compiler contracts a multiply-add differently, so two triangles at the same distance to within
an ulp may be chosen differently (ties); `bvh.intersect` then refines t of the chosen triangle in
double-float in XLA for both paths.

Tables are read with gathers (`ref[index_vector]`); the child-box and four-wide node rows by default
as 4-word vector loads from the 2-D table (`VECTOR_LOADS`): with incoherent rays every lane of a
warp reads a different row, the L1 cache serves a gather as one request per row, and Nsight Compute
showed the kernel bound by that (L1 throughput 91 % of peak on the dragon's bounce rays, one NVIDIA
H200); a 16-byte load asks once for four words (the same rays 45-60 % faster; BENCHMARKS.md).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float, Int

from jaxrt.accel.predicates import FAR_SCALE, edge_products, edge_sign, opaque, opaque_zero, pick3, ray_constants
from jaxrt.accel.builder import NUM_RAY_CLASSES as NUM_CLASSES

_ROW = 12  # words per node row with inline leaves: 9 (box or triangle), first, count, pad
_CB_ROW = 16  # words per node row with child boxes (see pack_rows)
_SKIP_SHIFT = 5  # skip-table entries (`pack_skips`): miss link << 5 | depth of its node (31: deeper)
_SKIP_DEPTH = 31
_WIDE_ROW = 32  # words per node row of the four-wide tree (see pack_wide)
_WIDE_SHIFT = 7  # its skip entries: miss link << 7 | depth << 2 | position among its siblings
_WIDE_TRAIL = 20  # depths of the four-wide tree with trail fields (3 bits each, in two int32 words)
# The layouts whose node table holds one row per node (packed once per tree by `pack_tables`): words a row.
_ROW_TABLES = {"childbox": _CB_ROW, "wide": _WIDE_ROW}


def _kernel(*refs, any_hit: bool, leaf_size: int, steps_per_iter: int, nf: int, nn: int, layout: str,
            gate_exact: bool, skip_tri: bool, trail: int, block: int, scalar_loads: bool, unroll: int,
            vector_loads: bool = False, postpone: bool = False, ordered: bool = False):
    # (with `ordered`, the first input is the order in which the rays are traced: see `traverse`)
    order_r, refs = (refs[0], refs[1:]) if ordered else (None, refs)
    o_r, d_r, tmin_r, tmax_r, box_r, leaf_r, links_r, tri_r, t_o, best_o, u_o, v_o, *count_o = refs

    def row(n, words):
        # The first `words` words of row n of the layout's node table, one (block,) array each. As
        # 4-word vector loads (vector_loads: the table is 2-D, each lane reads 16 aligned bytes at once)
        # or one gather per word (flat table). Incoherent rays read a different row in every lane, so
        # the L1 cache serves each gather instruction as up to 32 separate requests: the kernel is
        # bound by that throughput, and a 16-byte load asks it once for four words.
        if not vector_loads:
            r = n * _ROW_TABLES[layout]
            return [box_r[r + k] for k in range(words)]
        from jax.experimental import pallas as pl

        out = []
        for k in range(-(-words // 4)):
            x = box_r[n, pl.ds(4 * k, 4)]  # (block, 4)
            out += [c.reshape(c.shape[0]) for c in jnp.split(x, 4, axis=1)]
        return out[:words]

    def tri_test(ray, vs, valid, t_best, signs=None):
        # signs: None = exact where a tie of rounded products occurs in the warp (gate_exact) or
        # always; "rounded" = from the rounded products only, the pair's tie flag returned last;
        # "exact" = always exact.
        ox, oy, oz, _, _, _, sx, sy, sz, kx, ky, kz, _, t_lo = ray
        zero = opaque_zero(kz)
        px, py, pz = [], [], []
        for j in range(3):
            qx, qy, qz = vs[3 * j] - ox, vs[3 * j + 1] - oy, vs[3 * j + 2] - oz
            px.append(pick3(kx, qx, qy, qz))
            py.append(pick3(ky, qx, qy, qz))
            pz.append(pick3(kz, qx, qy, qz))
        x = [px[j] - opaque(sx * pz[j], zero) for j in range(3)]
        y = [py[j] - opaque(sy * pz[j], zero) for j in range(3)]
        z = [sz * pz[j] for j in range(3)]
        (ax, bx, cx), (ay, by, cy), (az, bz, cz) = x, y, z
        edges = ((cx, cy, bx, by), (ax, ay, cx, cy), (bx, by, ax, ay))
        prods = [edge_products(*e, zero) for e in edges]
        # a tested pair whose rounded products tie somewhere (unused, and so not computed, with "exact")
        tie = valid & ((prods[0][0] == prods[0][1]) | (prods[1][0] == prods[1][1]) | (prods[2][0] == prods[2][1]))
        if signs == "rounded":
            su, sv, sw = (edge_sign(*e, *p, exact=False) for e, p in zip(edges, prods))
        elif gate_exact and signs is None:
            # Tied rounded products are rare: the exact-sign arithmetic runs only for programs where
            # some tested ray/triangle pair needs it (a warp-uniform branch), as the XLA path's cond.
            su, sv, sw = lax.cond(jnp.max(tie.astype(jnp.int32)) > 0,
                                  lambda: tuple(edge_sign(*e, *p, exact=True) for e, p in zip(edges, prods)),
                                  lambda: tuple(edge_sign(*e, *p, exact=False) for e, p in zip(edges, prods)))
        else:
            su, sv, sw = (edge_sign(*e, *p, exact=True) for e, p in zip(edges, prods))
        U, V, W = (jnp.abs(p1 - p2) * sg for (p1, p2), sg in zip(prods, (su, sv, sw)))
        inside = ((su >= 0) & (sv >= 0) & (sw >= 0)) | ((su <= 0) & (sv <= 0) & (sw <= 0))
        det = U + V + W
        ok = inside & (det != 0)
        det_safe = jnp.where(ok, det, 1.0)
        t = (U * az + V * bz + W * cz) / det_safe
        hit = valid & ok & (t >= t_lo) & (t <= t_best)
        # u = V/det and v = W/det are divided once per ray at the end (same values), not per test.
        return (hit, t, V, W, det_safe) + ((tie,) if signs == "rounded" else ())

    def slab(ray, bb, t_best):
        ox, oy, oz, ix, iy, iz = ray[:6]
        t_lo = ray[13]
        t0x = (bb[0] - ox) * ix
        t0y = (bb[1] - oy) * iy
        t0z = (bb[2] - oz) * iz
        t1x = (bb[3] - ox) * ix
        t1y = (bb[4] - oy) * iy
        t1z = (bb[5] - oz) * iz
        t_near = jnp.maximum(jnp.maximum(jnp.maximum(jnp.minimum(t0x, t1x), jnp.minimum(t0y, t1y)),
                                         jnp.minimum(t0z, t1z)), t_lo)
        t_far = jnp.minimum(jnp.minimum(jnp.maximum(t0x, t1x), jnp.maximum(t0y, t1y)), jnp.maximum(t0z, t1z))
        return t_near <= jnp.minimum(t_far * FAR_SCALE, t_best)

    def keep(h, t, bary, idx, hit):
        # hit: (t, triangle, V, W, det) of the best so far; strict < keeps the earlier triangle on
        # exact ties (the XLA path's argmin).
        better = h & ((t < hit[0]) | (hit[1] < 0))
        return tuple(jnp.where(better, x, y) for x, y in zip((t, idx) + bary, hit))

    def test_leaf(ray, vs, valid, hit):
        def test():
            h, t, *bary = tri_test(ray, vs, valid, hit[0])
            return h, t, tuple(bary)

        if not skip_tri:
            return test()
        # The kernel is bound by instruction issue, and the triangle test is half a step's work:
        # a warp none of whose rays is at a leaf skips it.
        z = jnp.zeros_like(hit[0])
        return lax.cond(jnp.max(valid.astype(jnp.int32)) > 0, test,
                        lambda: (jnp.zeros_like(valid), z, (z, z, z + 1.0)))

    def postponed(ray, n, at_leaf, nxt, hit, pend):
        # Postponed leaves (Aila and Laine 2009, "Understanding the efficiency of ray traversal on
        # GPUs"): a ray that reaches a leaf notes it and goes on along the tree instead of testing its
        # triangle at once. The warp runs the triangle test only where some ray must (it holds a noted
        # leaf and reaches another, or its walk ends), and then every ray with a noted leaf or at a
        # leaf now tests one. On incoherent rays a warp otherwise runs the test whenever any one of
        # its 32 rays is at a leaf: in over half its loop iterations on the dragon's bounce rays
        # (`count_steps`). A noted leaf's triangle is loaded again for its test. Returns (next node,
        # hit, noted leaf or -1, whether the warp ran the test).
        waiting = pend >= 0
        forced = waiting & (at_leaf | (nxt < 0))
        tests = waiting | at_leaf
        yes, no = jnp.ones_like(waiting), jnp.zeros_like(waiting)

        def test():
            v = row(jnp.where(waiting, pend, n), 10)
            h, t, *bary = tri_test(ray, v[:9], tests, hit[0])
            return keep(h, t, tuple(bary), lax.bitcast_convert_type(v[9], jnp.int32), hit), h, yes

        hit, h, ran = lax.cond(jnp.max(forced.astype(jnp.int32)) > 0, test, lambda: (hit, no, no))
        # tested: a ray that had a noted leaf notes the one it is at now (if any); untested: a ray at a
        # leaf notes it (it had none, or the test would have run)
        pend = jnp.where(ran, jnp.where(waiting & at_leaf, n, -1), jnp.where(at_leaf, n, pend))
        if any_hit:
            nxt, pend = jnp.where(h, -1, nxt), jnp.where(h, -1, pend)
        return nxt, hit, pend, ran

    def step_childbox(ray, node, hit, bits):
        # A node's row holds its children's boxes: one load tests both, and the ray moves straight to
        # the nearer child that is hit (or the farther, or the miss link), so children whose boxes
        # miss are never loaded. The farther child, when the nearer was hit, is reached later by the
        # nearer's miss link without its own box test: its row then tests its children instead.
        # links_r here is the skip table (`pack_skips`): per class and node, the miss link and the
        # depth of the node it leads to. With `postpone` bits is (trail, noted leaf or -1).
        if postpone:
            bits, pend = bits
        cls = ray[12]
        active = node >= 0
        n = jnp.maximum(node, 0)
        w = row(n, _CB_ROW)
        code = lax.bitcast_convert_type(w[15], jnp.int32)  # 1: leaf; -(depth + 1): interior
        is_leaf = code > 0
        h_a = slab(ray, w[0:6], hit[0])
        h_b = slab(ray, w[6:12], hit[0])
        child_a = lax.bitcast_convert_type(w[12], jnp.int32)
        child_b = lax.bitcast_convert_type(w[13], jnp.int32)
        swap = (lax.shift_right_logical(lax.bitcast_convert_type(w[14], jnp.int32), cls) & 1) > 0
        near, far = jnp.where(swap, child_b, child_a), jnp.where(swap, child_a, child_b)
        h_near, h_far = jnp.where(swap, h_b, h_a), jnp.where(swap, h_a, h_b)
        if not postpone:
            h, t, bary = test_leaf(ray, w[:9], active & is_leaf, hit)
            hit = keep(h, t, bary, lax.bitcast_convert_type(w[9], jnp.int32), hit)
        sk = links_r[cls * nn + n]
        miss = lax.shift_right_arithmetic(sk, jnp.int32(_SKIP_SHIFT))
        nxt_leaf = jnp.where(h, -1, miss) if any_hit and not postpone else miss
        nxt = jnp.where(is_leaf, nxt_leaf, jnp.where(h_near, near, jnp.where(h_far, far, miss)))
        nxt = jnp.where(active, nxt, -1)
        if trail:
            # Bit trail: bit k set = the ray hit the box of the farther child at depth k that it has
            # not entered yet. The miss link always leads to such a farther (second-visited) child; if
            # its bit is clear its box was tested and missed, so the ray takes that node's miss link in
            # turn (one 4-byte load) instead of a step that would load its row and test its children's
            # boxes for nothing (a quarter of all steps on the dragon, simulated). Deeper subtrees than
            # `trail` levels keep no bits and are always entered (correct, as without the trail).
            child_depth = -code  # depth of an interior node's children
            both = active & ~is_leaf & h_near & h_far & (child_depth < trail)
            bits = bits | jnp.where(both, lax.shift_left(jnp.int32(1), jnp.clip(child_depth, 0, 31)), 0)
            via = (nxt >= 0) & (nxt == miss)

            def hop(s):
                m, md, via, bits = s
                tracked = md < trail
                bit = lax.shift_left(jnp.int32(1), md)
                enter = ~tracked | ((bits & bit) != 0)
                bits = jnp.where(via & tracked, bits & ~bit, bits)
                skip = via & ~enter
                sk = links_r[cls * nn + jnp.maximum(m, 0)]
                m = jnp.where(skip, lax.shift_right_arithmetic(sk, jnp.int32(_SKIP_SHIFT)), m)
                md = jnp.where(skip, sk & _SKIP_DEPTH, md)
                return m, md, skip & (m >= 0), bits

            # As many hops as the warp needs (one or two fixed hops without the vote measured no faster).
            nxt, _, _, bits = lax.while_loop(lambda s: jnp.max(s[2].astype(jnp.int32)) > 0, hop,
                                             (nxt, sk & _SKIP_DEPTH, via, bits))
        if postpone:
            nxt, hit, pend, tested = postponed(ray, n, active & is_leaf, nxt, hit, pend)
            return nxt, hit, (bits, pend), tested
        return nxt, hit, bits, active & is_leaf

    def field(d):
        # the four-wide trail: 3 bits for each depth 1-20, depths 1-10 in the first word, 11-20 in the second
        d = jnp.clip(d, 1, _WIDE_TRAIL)
        low = d <= 10
        return low, 3 * (jnp.where(low, d, d - 10) - 1)

    def step_wide(ray, node, hit, bits):
        # A four-wide node's row holds its (up to) four children's boxes: one load tests them all and
        # the ray moves straight to the first child that is hit, in its class's order (a fixed order
        # per ray class, as the binary tree's links: Ylitie et al. 2017 order a wide node's children by
        # the ray's octant the same way). The children after it that were hit are noted in the trail
        # (3 bits for the node's children's depth); the miss links lead from one child to the next in
        # that order, and a child arrived at by a miss link whose bit is clear is skipped at once (its
        # box was tested and missed). Half the binary tree's levels: fewer, wider steps for the warp.
        cls = ray[12]
        active = node >= 0
        n = jnp.maximum(node, 0)
        w = row(n, 30)
        code = lax.bitcast_convert_type(w[29], jnp.int32)  # 1: leaf; -(depth + 1): interior
        is_leaf = code > 0
        kid = [lax.bitcast_convert_type(w[24 + s], jnp.int32) for s in range(4)]
        hs = [slab(ray, w[6 * s:6 * s + 6], hit[0]) & (kid[s] >= 0) for s in range(4)]
        order = lax.shift_right_logical(lax.bitcast_convert_type(w[28], jnp.int32), 3 * cls)
        s0, s1, s2 = ((order & m) > 0 for m in (1, 2, 4))

        def ordered(x):
            # class order: pair (slots 0, 1) swapped where s1, pair (2, 3) where s2, the pairs where s0
            a0, a1 = jnp.where(s1, x[1], x[0]), jnp.where(s1, x[0], x[1])
            b0, b1 = jnp.where(s2, x[3], x[2]), jnp.where(s2, x[2], x[3])
            return (jnp.where(s0, b0, a0), jnp.where(s0, b1, a1), jnp.where(s0, a0, b0), jnp.where(s0, a1, b1))

        hp, kp = ordered(hs), ordered(kid)
        mask = (hp[0].astype(jnp.int32) | (hp[1].astype(jnp.int32) << 1) | (hp[2].astype(jnp.int32) << 2)
                | (hp[3].astype(jnp.int32) << 3))
        first = jnp.where(hp[0], kp[0], jnp.where(hp[1], kp[1], jnp.where(hp[2], kp[2], kp[3])))
        h, t, bary = test_leaf(ray, w[:9], active & is_leaf, hit)
        hit = keep(h, t, bary, lax.bitcast_convert_type(w[9], jnp.int32), hit)
        sk = links_r[cls * nn + n]
        miss = lax.shift_right_arithmetic(sk, jnp.int32(_WIDE_SHIFT))
        nxt_leaf = jnp.where(h, -1, miss) if any_hit else miss
        nxt = jnp.where(is_leaf, nxt_leaf, jnp.where(mask != 0, first, miss))
        nxt = jnp.where(active, nxt, -1)
        if trail:
            t0, t1 = bits
            kd = -code  # the children's depth
            low, sh = field(kd)
            rest = lax.shift_left(lax.shift_right_logical(mask & (mask - 1), 1), sh)  # hit after the first
            clear = ~lax.shift_left(jnp.int32(7), sh)
            put = active & ~is_leaf & (kd <= min(trail, _WIDE_TRAIL))
            t0 = jnp.where(put & low, (t0 & clear) | rest, t0)
            t1 = jnp.where(put & ~low, (t1 & clear) | rest, t1)
            via = (nxt >= 0) & (nxt == miss)

            def hop(s):
                m, md, pos, via, t0, t1 = s
                low, sh = field(md)
                f = lax.shift_right_logical(jnp.where(low, t0, t1), sh)
                tracked = (md >= 1) & (md <= min(trail, _WIDE_TRAIL))
                enter = ~tracked | ((lax.shift_right_logical(f, jnp.maximum(pos - 1, 0)) & 1) != 0)
                skip = via & ~enter
                sk = links_r[cls * nn + jnp.maximum(m, 0)]
                m = jnp.where(skip, lax.shift_right_arithmetic(sk, jnp.int32(_WIDE_SHIFT)), m)
                md = jnp.where(skip, lax.shift_right_logical(sk, 2) & _SKIP_DEPTH, md)
                pos = jnp.where(skip, sk & 3, pos)
                return m, md, pos, skip & (m >= 0), t0, t1

            nxt, _, _, _, t0, t1 = lax.while_loop(
                lambda s: jnp.max(s[3].astype(jnp.int32)) > 0, hop,
                (nxt, lax.shift_right_logical(sk, 2) & _SKIP_DEPTH, sk & 3, via, t0, t1))
            bits = (t0, t1)
        return nxt, hit, bits, active & is_leaf

    def step_nodes(ray, node, hit, bits):
        # layout "inline": one 12-word row per node, an interior node's box or a leaf's triangle;
        # "tables": separate box, leaf-range and triangle tables (any leaf size).
        cls = ray[12]
        active = node >= 0
        n = jnp.maximum(node, 0)
        if layout == "inline":
            r12 = n * _ROW
            w = [box_r[r12 + k] for k in range(9)]
            bb = w[:6]
            first = lax.bitcast_convert_type(box_r[r12 + 9], jnp.int32)
            count = lax.bitcast_convert_type(box_r[r12 + 10], jnp.int32)
        else:
            b6 = n * 6
            bb = [box_r[b6 + k] for k in range(6)]
            first = leaf_r[n * 2]
            count = leaf_r[n * 2 + 1]
        box_in = slab(ray, bb, hit[0])
        if layout == "inline":
            # A leaf's row holds its triangle, not its box: the triangle test alone decides (the
            # padded box test is implied by a hit in [tmin, t_best]) and a leaf's hit and miss links
            # are the same node, so box_hit only matters for interior nodes.
            box_hit = active & ((count > 0) | box_in)
        else:
            box_hit = active & box_in
        leaf_hit = box_hit & (count > 0)
        first = jnp.where(leaf_hit, first, 0)  # lanes not testing a leaf read triangle 0 (cached)
        any_h = jnp.zeros_like(active)
        for j in range(leaf_size):
            idx = jnp.minimum(first + j, nf - 1)
            if layout == "inline":
                vs = w
            else:
                i9 = idx * 9
                vs = [tri_r[i9 + k] for k in range(9)]
            h, t, bary = test_leaf(ray, vs, leaf_hit & (count > j), hit)
            hit = keep(h, t, bary, idx, hit)
            any_h = any_h | h
        row = (cls * nn + n) * 2
        nxt = jnp.where(box_hit, links_r[row], links_r[row + 1])
        if any_hit:
            nxt = jnp.where(any_h, -1, nxt)
        return jnp.where(active, nxt, -1), hit, bits, leaf_hit

    def brute(ray, hit):
        # Every ray against every triangle of the (leaf-order) table, in index order: no tree, no
        # divergence, and the warp's rays all read the same triangle at once (a broadcast load).
        # For a few dozen triangles this is less work than walking a tree whose boxes overlap every
        # ray: a step's two slab tests, dependent row loads and the warp's wait for its slowest ray.
        # Exact edge signs: a first sweep uses the rounded products only and notes whether any
        # tested pair tied; only a block where one did sweeps again with exact signs (a warp vote per
        # block, not per triangle; the same hits, since the two signs differ only at ties).
        valid = jnp.ones(shape, jnp.bool_)

        def test(i, hit, tied, signs):
            if scalar_loads:
                vs = [jnp.full(shape, tri_r[i * 9 + k]) for k in range(9)]
            else:
                i9 = jnp.full(shape, i * 9, jnp.int32)
                vs = [tri_r[i9 + k] for k in range(9)]
            h, t, *rest = tri_test(ray, vs, valid, hit[0], signs=signs)
            if signs == "rounded":
                tied = tied | rest.pop()
            return keep(h, t, tuple(rest), jnp.full(shape, i, jnp.int32), hit), tied

        def tests(first, count, hit, tied, signs):
            for j in range(count):  # unrolled: the loads of the next triangles issue early
                hit, tied = test(first + j, hit, tied, signs)
            return hit, tied

        def sweep(hit, signs):
            tied = jnp.zeros(shape, jnp.bool_)
            step = max(1, min(unroll, nf))
            full = nf // step
            if any_hit:
                # stop once every ray of the block has a hit (the padding rays of the last block never
                # do; that block tests every triangle)
                k, hit, tied = lax.while_loop(
                    lambda s: (s[0] < full) & (jnp.min(s[1][1]) < 0),
                    lambda s: (s[0] + 1, *tests(s[0] * step, step, s[1], s[2], signs)), (jnp.int32(0), hit, tied))
            else:
                hit, tied = lax.fori_loop(0, full, lambda k, s: tests(k * step, step, *s, signs), (hit, tied))
            return tests(full * step, nf - full * step, hit, tied, signs)

        if not gate_exact:
            return sweep(hit, "exact")[0]
        first, tied = sweep(hit, "rounded")
        return lax.cond(jnp.max(tied.astype(jnp.int32)) > 0, lambda: sweep(hit, "exact")[0], lambda: first)

    step = {"childbox": step_childbox, "wide": step_wide}.get(layout, step_nodes)

    def finish(hit):
        t, best, bv, bw, det = hit
        return t, best, bv / det, bw / det

    def steps(ray, node, hit, bits):
        # returns the state and, of the last step, where the warp ran the triangle test (`count_steps`)
        for _ in range(steps_per_iter):
            node, hit, bits, tested = step(ray, node, hit, bits)
        return node, hit, bits, tested

    def live(s):
        # the loop runs while some ray of the program walks the tree or holds a noted leaf (`postpone`)
        node = jnp.maximum(s[0], s[2][1]) if postpone else s[0]
        return jnp.max(node) >= 0

    # One block of consecutive rays per program, traced until the slowest of them ends. The per-ray
    # constants are computed here (the XLA path's own function, bit for bit) rather than read: an XLA
    # pass writing 14 columns cost as much as a fifth of a shadow launch.
    from jax.experimental import pallas as pl  # see `traverse`: imported where a kernel is built

    if ordered:
        # this program's rays are order[its block]: read where they are, written back there
        r = order_r[...]
        lo, hi = tmin_r[r], tmax_r[r]
    else:
        r = pl.program_id(0) * block + jnp.arange(block, dtype=jnp.int32)
        lo, hi = tmin_r[...], tmax_r[...]
    i3 = r * 3
    inv, shear, kx, ky, kz, cls = ray_constants(*(d_r[i3 + k] for k in range(3)))
    ray = (*(o_r[i3 + k] for k in range(3)), *inv, *shear, kx, ky, kz, cls, lo)
    shape = ray[0].shape
    z = jnp.zeros(shape, jnp.float32)
    hit = (hi, jnp.full(shape, -1, jnp.int32), z, z, z + 1.0)

    def put(out):
        for ref, x in zip((t_o, best_o, u_o, v_o), out):
            if ordered:
                ref[r] = x
            else:
                ref[...] = x

    if layout == "brute":
        put(finish(brute(ray, hit)))
        return
    zi = jnp.zeros(shape, jnp.int32)
    bits0 = (zi, zi - 1 if postpone else zi) if layout == "wide" or postpone else zi
    if not count_o:
        _, hit, _ = lax.while_loop(live, lambda s: steps(ray, *s)[:3], (zi, hit, bits0))
        put(finish(hit))
        return

    # Counting (`traverse(..., count_steps=True)`, for measurements): the steps each ray takes, the
    # loop iterations of its program and those in which the warp runs the triangle test.
    def counted(s):
        node, hit, bits, n_steps, n_iter, n_leaf = s
        nxt, hit, bits, tested = steps(ray, node, hit, bits)
        return nxt, hit, bits, n_steps + (node >= 0), n_iter + 1, n_leaf + jnp.max(tested.astype(jnp.int32))

    _, hit, _, n_steps, n_iter, n_leaf = lax.while_loop(live, counted, (zi, hit, bits0, zi, zi, zi))
    t_o[...], best_o[...], u_o[...], v_o[...] = finish(hit)
    count_o[0][...], count_o[1][...], count_o[2][...] = n_steps, n_iter, n_leaf


def _children(node_leaf, links):
    """(is_leaf, a, b, links (classes, nn, 2)): a is class 0's first child of an interior node, b its sibling."""
    nn = node_leaf.shape[0]
    lk = links.reshape(NUM_CLASSES, nn, 2)
    is_leaf = node_leaf[:, 1] > 0
    a = jnp.where(is_leaf, 0, lk[0, :, 0])  # class 0's hit link of an interior node: its first child
    b = jnp.where(is_leaf, 0, lk[0, a, 1])  # whose miss link is the sibling
    return is_leaf, a, b, lk


def _parents(node_leaf, links) -> Array:
    """(nn,) int32 parent of every node (the root's is 0)."""
    nn = node_leaf.shape[0]
    is_leaf, a, b, _ = _children(node_leaf, links)
    inner = jnp.where(is_leaf, nn, jnp.arange(nn, dtype=jnp.int32))  # leaves' (meaningless) children: dropped
    parent = jnp.zeros(nn, jnp.int32).at[jnp.where(is_leaf, nn, a)].set(inner, mode="drop")
    return parent.at[jnp.where(is_leaf, nn, b)].set(inner, mode="drop")


def node_depth(node_leaf, links) -> Array:
    """(nn,) int32 depth of every node (root 0), by pointer jumping over parent links (log2(nn) rounds)."""
    nn = node_leaf.shape[0]
    parent = _parents(node_leaf, links)
    depth = (jnp.arange(nn) != 0).astype(jnp.int32)
    for _ in range(max(1, (nn - 1).bit_length())):
        depth, parent = depth + depth[parent], parent[parent]
    return depth


def pack_rows(node_box: Float[Array, "nn 6"], node_leaf, links, triangles: Float[Array, "F 9"],
              depth=None) -> Float[Array, "nn 16"]:
    """The kernel's node table (nn, 16) float32 (int fields stored bit-cast), one row per node:

    interior: box of child a (6), box of child b (6), a, b, order bits, -(depth + 1) — child a is the
              first child of ray class 0; bit c of `order` set where class c visits b first
    leaf:     its triangle v0 v1 v2 (9), its leaf-order triangle index, 0 ... 0, 1

    From a BVH's arrays (see bvh.BVH; leaf_size 1) and optionally `node_depth`'s result. Built once
    per tree (`bvh.build` stores it as `BVH.rows`), not per traversal call: for the full dragon it is
    111 MB.
    """
    nn = node_box.shape[0]
    is_leaf, a, b, lk = _children(node_leaf, links)
    order = jnp.zeros(nn, jnp.int32)
    for c in range(NUM_CLASSES):
        order = order | ((lk[c, :, 0] != a) & ~is_leaf).astype(jnp.int32) << c
    f32 = lambda x: lax.bitcast_convert_type(x.astype(jnp.int32), jnp.float32)  # noqa: E731
    inner = jnp.concatenate([node_box[a], node_box[b], f32(a)[:, None], f32(b)[:, None], f32(order)[:, None],
                             f32(-1 - (node_depth(node_leaf, links) if depth is None else depth))[:, None]],
                            axis=1)
    first = jnp.where(is_leaf, node_leaf[:, 0], 0)
    leaf = jnp.concatenate([triangles[first], f32(first)[:, None], jnp.zeros((nn, 5), jnp.float32),
                            f32(jnp.ones(nn))[:, None]], axis=1)
    return jnp.where(is_leaf[:, None], leaf, inner)


def pack_skips(node_leaf, links, depth=None) -> Array:
    """The child-box kernel's link table (classes * nn,) int32: per ray class c and node n (entry c*nn + n),
    miss link << 5 | depth of the node it leads to (31 for depth 31 and deeper; -1 << 5 | 0 where it
    ends). Built once per tree with `pack_rows` (`BVH.skips`); `depth`: `node_depth`'s result, if at hand."""
    nn = node_leaf.shape[0]
    if nn >= 1 << (31 - _SKIP_SHIFT):
        raise ValueError(f"traverse_pallas: {nn} nodes do not fit the skip table's {31 - _SKIP_SHIFT}-bit links")
    miss = links.reshape(-1, 2)[:, 1]
    depth = node_depth(node_leaf, links) if depth is None else depth
    depth = jnp.minimum(depth, _SKIP_DEPTH)[jnp.maximum(miss, 0)]
    return lax.shift_left(miss, jnp.int32(_SKIP_SHIFT)) | jnp.where(miss >= 0, depth, 0)


def pack_wide(node_box: Float[Array, "nn 6"], node_leaf, links, triangles: Float[Array, "F 9"],
              depth=None) -> tuple[Float[Array, "nn 32"], Int[Array, " nn6"]]:
    """The four-wide kernel's tables (layout "wide"): node rows (nn, 32) float32 and links (classes * nn,)
    int32, from a binary BVH's arrays (leaf_size 1) and optionally `node_depth`'s result.

    The four-wide tree is the binary tree with every other level collapsed: its nodes are the binary
    tree's leaves and its interior nodes at even depths, numbered in the binary tree's order (rows past
    their count are zero: the table keeps the binary tree's nn rows, so its shape is known before the
    build). An interior node's children are its binary grandchildren, in slots (a's first, a's
    second, b's first, b's second), where a, b are its binary children (a: ray class 0's first); a
    leaf child fills the first slot of its pair and leaves the second empty. Rows:

    interior: 4 boxes (24), 4 children (-1: empty), order bits, -(depth + 1), 0, 0 — per ray class c
              three bits at 3c: swap the pairs, swap within a's pair, swap within b's pair, so that
              the slots in the class's order are the binary tree's depth-first order for that class
    leaf:     its triangle v0 v1 v2 (9), its leaf-order triangle index, 0 ... 0, 1 (word 29), 0, 0

    Links: per class c and node m (entry c * nn + m), the node that follows m's subtree in class c's
    order (the next child of m's parent, or an ancestor's next child; -1 at the end) << 7 | that
    node's depth (31 for 31 and deeper) << 2 | its position (0-3) among its parent's children in that
    order. The position of a leaf in an empty slot's pair counts the empty slot.
    """
    nn = node_box.shape[0]
    if nn >= 1 << (31 - _WIDE_SHIFT):
        raise ValueError(f"traverse_pallas: {nn} nodes do not fit the wide skip table's {31 - _WIDE_SHIFT}-bit links")
    is_leaf, a, b, lk = _children(node_leaf, links)
    depth = node_depth(node_leaf, links) if depth is None else depth
    parent = _parents(node_leaf, links)
    kept = is_leaf | (depth % 2 == 0)
    new = jnp.cumsum(kept.astype(jnp.int32)) - 1
    f32 = lambda x: lax.bitcast_convert_type(x.astype(jnp.int32), jnp.float32)  # noqa: E731

    def pair(x):
        return jnp.where(is_leaf[x], x, a[x]), jnp.where(is_leaf[x], -1, b[x])

    slots = (*pair(a), *pair(b))
    boxes = [jnp.where((s >= 0)[:, None], node_box[jnp.maximum(s, 0)], 0.0) for s in slots]
    kids = [f32(jnp.where(s >= 0, new[jnp.maximum(s, 0)], -1))[:, None] for s in slots]
    order = jnp.zeros(nn, jnp.int32)
    for c in range(NUM_CLASSES):
        swap = [lk[c, :, 0] != a, ~is_leaf[a] & (lk[c, a, 0] != a[a]), ~is_leaf[b] & (lk[c, b, 0] != a[b])]
        bits = sum(x.astype(jnp.int32) << k for k, x in enumerate(swap))
        order = order | jnp.where(is_leaf, 0, bits) << (3 * c)
    z2 = jnp.zeros((nn, 2), jnp.float32)
    inner = jnp.concatenate([*boxes, *kids, f32(order)[:, None], f32(-1 - depth // 2)[:, None], z2], axis=1)
    first = jnp.where(is_leaf, node_leaf[:, 0], 0)
    leaf = jnp.concatenate([triangles[first], f32(first)[:, None], jnp.zeros((nn, 19), jnp.float32),
                            f32(jnp.ones(nn))[:, None], z2], axis=1)
    at = jnp.where(kept, new, nn)
    rows = jnp.zeros((nn, _WIDE_ROW), jnp.float32).at[at].set(jnp.where(is_leaf[:, None], leaf, inner), mode="drop")

    # every kept node's position among its four-wide parent's children, per class: a leaf whose
    # binary parent q is kept fills a pair (0 or 2); else q's own place among the pairs, then its order in q
    q = parent
    idx = jnp.arange(nn, dtype=jnp.int32)
    pos, skips = [], []
    for c in range(NUM_CLASSES):
        second = (idx != lk[c, q, 0]).astype(jnp.int32)
        q_second = (q != lk[c, parent[q], 0]).astype(jnp.int32)
        pos.append(jnp.where(kept[q], 2 * second, 2 * q_second + second))
    wide_depth = jnp.minimum((depth + 1) // 2, _SKIP_DEPTH)
    for c in range(NUM_CLASSES):
        y = lk[c, :, 1]  # the binary miss link; where it is a collapsed node, its first child in class c
        y0 = jnp.maximum(y, 0)
        tgt = jnp.where(kept[y0], y0, lk[c, y0, 0])
        entry = (lax.shift_left(new[tgt], jnp.int32(_WIDE_SHIFT)) | lax.shift_left(wide_depth[tgt], jnp.int32(2))
                 | pos[c][tgt])
        entry = jnp.where(y >= 0, entry, lax.shift_left(jnp.int32(-1), jnp.int32(_WIDE_SHIFT)))
        skips.append(jnp.full(nn, -1 << _WIDE_SHIFT, jnp.int32).at[at].set(entry, mode="drop"))
    return rows, jnp.concatenate(skips)


#: The node table that the GPU kernel reads for trees of one triangle per leaf, packed once per tree
#: by `bvh.build` (`pack_tables`): "childbox" (binary, `pack_rows`) or "wide" (four-wide, `pack_wide`).
#: The four-wide tree takes 39-45 % fewer steps, but its steps cost more than that on an H200: every
#: kind of ray was slower with it, on the dragon and on the Cornell box (BENCHMARKS.md, "Path tracing:
#: vector loads in the traversal, and skipped chunks").
TREE_LAYOUT = "childbox"


def pack_tables(node_box: Float[Array, "nn 6"], node_leaf, links, triangles: Float[Array, "F 9"],
                layout: str | None = None):
    """The node rows and links of one tree for `layout` (default `TREE_LAYOUT`): (`pack_rows`,
    `pack_skips`) for "childbox", `pack_wide` for "wide"; node depths computed once for both."""
    layout = layout or TREE_LAYOUT
    depth = node_depth(node_leaf, links)
    if layout == "wide":
        return pack_wide(node_box, node_leaf, links, triangles, depth)
    return pack_rows(node_box, node_leaf, links, triangles, depth), pack_skips(node_leaf, links, depth)


LAYOUTS = ("childbox", "wide", "inline", "tables", "brute")
TRAIL_DEPTH = 31  # the bit trail covers depths 0-30 (one int32 per ray)

#: Tables of at most this many triangles are traced by brute force (layout "brute": every ray
#: against every triangle) when a call names no layout. 0, so never: on an H200 brute force beat the
#: tree on incoherent rays in the 32-triangle Cornell box (3.6-4.4 against 2.1-2.8 Grays/s) but lost
#: on camera rays and on occlusion queries, and the Cornell box's path-tracing pass was slower with it
#: (12.5 against 12.1 ms; its kernel also compiles 4-5 s longer). BENCHMARKS.md, "Path tracing:
#: brute force for small scenes"; `benchmarks/brute_force.py` measures it again.
BRUTE_FORCE_MAX_TRIANGLES = 0
#: Node rows read as 4-word vector loads (`traverse`'s vector_loads) unless a call says otherwise
#: (one NVIDIA H200, the dragon's incoherent rays: 400-600 against 260-365 Mrays/s with a gather a word).
VECTOR_LOADS = True
#: Triangles a brute-force loop iteration tests (written out in the kernel).
BRUTE_FORCE_UNROLL = 4
#: Child-box rows: leaves postponed (`traverse`'s postpone) unless a call says otherwise. Off: it halves
#: the share of loop iterations that run the triangle test (the dragon's bounce rays: 54 -> 31 %,
#: `benchmarks/brute_force.py --count`) but every kind of ray ran slower on an H200 (dragon bounce 399
#: against 414 Mrays/s, camera 3624 against 3938; the environment-lit dragon's path-tracing pass 19.87
#: against 19.59 ms): the kernel waits on its dependent node loads, not on the test's arithmetic, and a
#: noted leaf's triangle is loaded a second time (BENCHMARKS.md, "Path tracing: postponed leaves").
POSTPONE_LEAVES = False


def default_layout(num_triangles: int, leaf_size: int) -> str:
    """The node table `traverse` reads when a call names none: brute force for tables of at most
    `BRUTE_FORCE_MAX_TRIANGLES` triangles, else `TREE_LAYOUT` (leaf size 1) or "tables"."""
    if num_triangles <= BRUTE_FORCE_MAX_TRIANGLES:
        return "brute"
    return TREE_LAYOUT if leaf_size == 1 else "tables"


def traverse(arrays: dict, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"], tmin: Float[Array, " N"],
             tmax: Float[Array, " N"], *, any_hit: bool, leaf_size: int, block: int = 32,
             steps_per_iter: int = 1, num_warps: int = 1, interpret: bool = False, layout: str | None = None,
             gate_exact: bool = True, skip_tri: bool = True, trail: int = TRAIL_DEPTH, scalar_loads: bool = False,
             unroll: int | None = None, vector_loads: bool | None = None, postpone: bool | None = None,
             count_steps: bool = False, order: Int[Array, " N"] | None = None):
    """Trace N rays; returns (found, t, tri_index_in_leaf_order, u, v), each (N,), as
    `traverse_xla.traverse` (without the step counts).

    order: None, or a permutation of the N rays in which the kernel takes them (a program's block of
    rays is order[block]; each reads its ray and writes its results where the ray is): the results
    are the same. For a batch whose live rays are scattered among rays with an empty interval, the
    live ones first keeps them together in full warps (a warp costs as long as its slowest lane), with
    no copy of the rays or their results.

    arrays: node_box (nn,6), node_leaf (nn,2), links (6nn,2), triangles (F,9), optionally rows
    (nn,16) and skips (6nn,) (see bvh.BVH); origins, directions (N,3) float32; tmin, tmax (N,) float32.
    block: rays per program instance (a power of 2); steps_per_iter: traversal steps between two
    checks of the loop predicate; num_warps: Triton warps per program; interpret: run the kernel
    with the Pallas interpreter (any backend; slow, for tests). gate_exact: evaluate the exact
    edge signs only in programs where a rounded-product tie occurs (else always).
    layout (default `default_layout`): the table a step reads —
      "childbox": each node's row holds its children's boxes (`pack_tables`: arrays["rows"] and
                  arrays["skips"] when present, else packed per call): a step tests both children and moves straight
                  to the nearer one that is hit, so missed children are never loaded;
      "wide":     the same with four children a row (`pack_wide`; the tree's own tables where it was
                  packed with this layout, else packed per call);
      "inline":   one 12-word row per node, an interior node's box or a leaf's triangle (packed
                  per call);
      "tables":   separate box / leaf-range / triangle tables, any leaf size;
      "brute":    no tree: every ray tests every triangle of the table, in index order (an exact tie
                  in t keeps the lower index; the tree layouts keep the first one visited).
    skip_tri: a warp none of whose rays is at a leaf skips the triangle test's arithmetic (a
    warp-uniform branch). trail (child-box layout): levels of the tree covered by the bit trail that
    skips farther children known to be missed (0 to 31; 0 = no trail). scalar_loads (brute force):
    read each triangle as scalars rather than as a gather whose lanes share one address; unroll
    (brute force): triangles tested per loop iteration (default `BRUTE_FORCE_UNROLL`). vector_loads
    (child-box and wide rows; default `VECTOR_LOADS`): read a row as 4-word vector loads instead of a
    gather a word. postpone (child-box rows; default `POSTPONE_LEAVES`): a ray at a leaf notes it and
    walks on, and a warp tests its rays' noted leaves together, where one of them must (Aila and Laine
    2009). All options give the same results; BENCHMARKS.md has their speeds.
    count_steps (child-box and wide layouts; with steps_per_iter 1): also return, per ray, the steps it
    took, its program's loop iterations, and those iterations in which some ray of the program was at a
    leaf (three (N,) int32 arrays after v) — a measurement, slower than the plain kernel.
    """
    # The default is resolved here, outside the jitted function, so that it is part of its static
    # arguments (a module constant read while tracing would not be part of the jit cache's key).
    layout = layout or default_layout(arrays["triangles"].shape[0], leaf_size)
    if layout not in LAYOUTS:
        raise ValueError(f"traverse_pallas: layout must be one of {LAYOUTS}, got {layout!r}")
    if not 0 <= trail <= TRAIL_DEPTH:
        raise ValueError(f"traverse_pallas: trail must be in [0, {TRAIL_DEPTH}], got {trail}")
    if layout in ("childbox", "wide", "inline") and leaf_size != 1:
        raise ValueError(f"traverse_pallas: layout {layout!r} needs leaf_size 1")
    if count_steps and order is not None:
        raise ValueError("traverse_pallas: count_steps takes no order")
    if count_steps and (layout not in _ROW_TABLES or steps_per_iter != 1):
        raise ValueError(f"traverse_pallas: count_steps needs layout 'childbox' or 'wide' and steps_per_iter 1, "
                         f"got {layout!r} and {steps_per_iter}")
    return _traverse(arrays, origins, directions, tmin, tmax, any_hit=any_hit, leaf_size=leaf_size, block=block,
                     steps_per_iter=steps_per_iter, num_warps=num_warps, interpret=interpret, layout=layout,
                     gate_exact=gate_exact, skip_tri=skip_tri, trail=trail, scalar_loads=scalar_loads,
                     unroll=BRUTE_FORCE_UNROLL if unroll is None else unroll,
                     vector_loads=(VECTOR_LOADS if vector_loads is None else vector_loads)
                     and layout in _ROW_TABLES,
                     postpone=(POSTPONE_LEAVES if postpone is None else postpone) and layout == "childbox",
                     count_steps=count_steps, order=order)


@functools.partial(jax.jit, static_argnames=("any_hit", "leaf_size", "block", "steps_per_iter", "num_warps",
                                             "interpret", "layout", "gate_exact", "skip_tri", "trail",
                                             "scalar_loads", "unroll", "vector_loads", "postpone",
                                             "count_steps"))
def _traverse(arrays, origins, directions, tmin, tmax, *, any_hit, leaf_size, block, steps_per_iter, num_warps,
              interpret, layout, gate_exact, skip_tri, trail, scalar_loads, unroll, vector_loads, postpone,
              count_steps, order=None):
    nn = arrays["node_box"].shape[0]
    nf = arrays["triangles"].shape[0]
    n = origins.shape[0]
    n_pad = -(-n // block) * block
    pad = n_pad - n
    # Padding rays have an empty interval (tmin 1 > tmax 0): they miss the root's children and end.
    per_ray = [jnp.pad(origins.astype(jnp.float32), ((0, pad), (0, 0))).reshape(-1),
               jnp.pad(directions.astype(jnp.float32), ((0, pad), (0, 0)), constant_values=1.0).reshape(-1),
               jnp.pad(tmin.astype(jnp.float32), (0, pad), constant_values=1.0),
               jnp.pad(tmax.astype(jnp.float32), (0, pad), constant_values=0.0)]
    box, leaf, tri = arrays["node_box"], arrays["node_leaf"], arrays["triangles"]
    links = arrays["links"]
    if layout in _ROW_TABLES:
        if arrays.get("rows") is not None and arrays["rows"].shape[1] == _ROW_TABLES[layout]:  # the tree's own
            box, links = arrays["rows"], arrays["skips"]
        else:
            box, links = pack_tables(box, leaf, links, tri, layout)
        leaf, tri = leaf[:1], tri[:1]  # unused by these layouts
    elif layout == "brute":
        box, leaf, links = box[:1], leaf[:1], links[:1]  # unused: the kernel reads only the triangles
    elif layout == "inline":
        is_leaf = (leaf[:, 1] > 0)[:, None]
        body = jnp.where(is_leaf, tri[jnp.where(is_leaf[:, 0], leaf[:, 0], 0)],
                         jnp.pad(box, ((0, 0), (0, 3))))
        box = jnp.concatenate([body, lax.bitcast_convert_type(leaf, jnp.float32), jnp.zeros((nn, 1), jnp.float32)],
                              axis=1)
        leaf, tri = leaf[:1], tri[:1]
    # Pallas (and its Triton back end) is imported where a kernel is built, not with the module: the
    # import costs 0.2-0.3 s and a CPU process never builds one (it only packs node tables here).
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    tables = [box if vector_loads else box.reshape(-1), leaf.reshape(-1), links.reshape(-1), tri.reshape(-1)]
    whole = lambda x: pl.BlockSpec(x.shape, lambda i: (0,) * x.ndim)  # noqa: E731
    f32 = jax.ShapeDtypeStruct((n_pad,), jnp.float32)
    i32 = jax.ShapeDtypeStruct((n_pad,), jnp.int32)
    kw = {}
    if not interpret:
        kw["compiler_params"] = plgpu.CompilerParams(num_warps=num_warps, num_stages=1)
    static = dict(any_hit=any_hit, leaf_size=leaf_size, steps_per_iter=steps_per_iter, nf=nf, nn=nn, layout=layout,
                  gate_exact=gate_exact, skip_tri=skip_tri, trail=trail if layout in _ROW_TABLES else 0, block=block,
                  scalar_loads=scalar_loads, unroll=unroll if layout == "brute" else 1, vector_loads=vector_loads,
                  postpone=postpone, ordered=order is not None)
    name = "bvh_any_hit" if any_hit else "bvh_closest_hit"
    ray_spec = pl.BlockSpec((block,), lambda i: (i,))
    outs = (f32, i32, f32, f32) + ((i32,) * 3 if count_steps else ())
    if order is None:
        lead, in_specs, out_spec = [], [whole(per_ray[0]), whole(per_ray[1]), ray_spec, ray_spec], ray_spec
    else:
        # a program reads its block of the order and then any ray's data (the padding rays keep
        # their places at the end)
        lead = [jnp.concatenate([order.astype(jnp.int32), jnp.arange(n, n_pad, dtype=jnp.int32)])]
        in_specs = [ray_spec] + [whole(x) for x in per_ray]
        out_spec = pl.BlockSpec((n_pad,), lambda i: (0,))
        name += "_ordered"
    t, best, u, v, *counts = pl.pallas_call(
        functools.partial(_kernel, **static),
        out_shape=outs,
        grid=(n_pad // block,),
        in_specs=in_specs + [whole(tb) for tb in tables],
        out_specs=(out_spec,) * len(outs),
        interpret=interpret, name=name, **kw,
    )(*lead, *per_ray, *tables)
    t, best, u, v = t[:n], best[:n], u[:n], v[:n]
    return (best >= 0, t, best, u, v, *(c[:n] for c in counts))
