"""The binned-SAH builder (`bvh.build(..., builder="sah")`) and depth-first numbering (`layout="dfs"`):
layout invariants, the SAH cost and the root split checked by independent numpy / brute force,
traversal against float64 brute force; and `bvh.occluded(from_end=True)` against brute-force segments."""

import dataclasses

import jax
import numpy as np
import pytest
import trimesh
from test_bvh import check_against_reference, ray_mix

from jaxrt.accel import bvh
from jaxrt.accel import builder as bvh_build
from jaxrt.accel import sah as bvh_sah
from jaxrt.geometry import data
from jaxrt.geometry import mesh


def soup(n=600, seed=3):
    """Random triangles of mixed sizes (some long and thin), plus duplicates: a hard case for splits."""
    rng = np.random.default_rng(seed)
    c = rng.random((n, 1, 3)) * [4.0, 1.0, 2.0]
    size = np.where(rng.random((n, 1, 1)) < 0.1, 1.0, 0.05)
    v = (c + rng.normal(size=(n, 3, 3)) * size).reshape(-1, 3)
    f = np.arange(3 * n).reshape(n, 3)
    return v.astype(np.float32), np.concatenate([f, f[:20]])


def children(tree):
    """(first, second) child of every node from class 0's links (-1, -1 for leaves)."""
    leaf = np.asarray(tree.node_leaf)
    links = np.asarray(tree.links)
    nn = len(leaf)
    is_leaf = leaf[:, 1] > 0
    first = np.where(is_leaf, -1, links[:nn, 0])
    second = np.where(is_leaf, -1, links[np.maximum(first, 0), 1])
    return first, second, is_leaf


def subtree_tris(tree, first, second, is_leaf, node):
    stack, out = [node], []
    leaf = np.asarray(tree.node_leaf)
    while stack:
        n = stack.pop()
        if is_leaf[n]:
            out.extend(range(leaf[n, 0], leaf[n, 0] + leaf[n, 1]))
        else:
            stack += [first[n], second[n]]
    return np.array(out)


@pytest.mark.parametrize("leaf_size,builder,layout", [(1, "sah", "bfs"), (3, "sah", "bfs"), (1, "sah", "dfs"),
                                                       (3, "lbvh", "dfs")])
def test_sah_build_invariants(leaf_size, builder, layout):
    v, f = soup()
    check_invariants(v, f, leaf_size, builder, layout)


def check_invariants(v, f, leaf_size, builder, layout, sah_settings=bvh_sah.DEFAULT):
    tree = bvh.build(v, f, leaf_size=leaf_size, builder=builder, layout=layout, sah_settings=sah_settings)
    box = np.asarray(tree.node_box)
    leaf = np.asarray(tree.node_leaf)
    links = np.asarray(tree.links)
    nn = len(box)
    first, second, is_leaf = children(tree)
    cover = np.zeros(len(f), int)
    for s, c in leaf[is_leaf]:
        assert 1 <= c <= leaf_size
        cover[s:s + c] += 1
    assert np.all(cover == 1)  # every triangle in exactly one leaf
    np.testing.assert_array_equal(np.asarray(tree.triangles).reshape(-1, 3, 3),
                                  v[f][np.asarray(tree.prim_ids)])
    tris = np.asarray(tree.triangles).reshape(-1, 3, 3)
    for n in range(nn):  # every node's box holds its subtree's triangles and its children's boxes
        t = tris[subtree_tris(tree, first, second, is_leaf, n)].reshape(-1, 3)
        assert np.all(t >= box[n, :3]) and np.all(t <= box[n, 3:])
        if not is_leaf[n]:
            for ch in (first[n], second[n]):
                assert np.all(box[ch, :3] >= box[n, :3]) and np.all(box[ch, 3:] <= box[n, 3:])
    for c in range(6):  # each class's threading visits every node once
        lk = links[c * nn:(c + 1) * nn]
        seen, n = [], 0
        while n >= 0 and len(seen) <= nn:
            seen.append(n)
            n = lk[n, 0]
        assert sorted(seen) == list(range(nn))
        if layout == "dfs" and c == 0:
            assert seen == list(range(nn))  # depth-first numbering is class 0's visiting order
    # the same tree whatever the numbering: equal stats and leaf order
    other = bvh.build(v, f, leaf_size=leaf_size, builder=builder, layout="bfs" if layout == "dfs" else "dfs",
                      sah_settings=sah_settings)
    a, b = dataclasses.asdict(other.stats), dataclasses.asdict(tree.stats)
    assert a.pop("sah_cost") == pytest.approx(b.pop("sah_cost"), rel=1e-12) and a == b
    np.testing.assert_array_equal(np.asarray(other.prim_ids), np.asarray(tree.prim_ids))


def test_sah_cost_independent_and_better_than_lbvh():
    """SAH cost recomputed from the triangles alone (not node_box), and lower than the LBVH's."""
    v, f = soup()
    costs = {}
    for builder in ("lbvh", "sah"):
        tree = bvh.build(v, f, builder=builder)
        first, second, is_leaf = children(tree)
        tris = v.astype(np.float64)[f][np.asarray(tree.prim_ids)]

        def area(idx, tris=tris):
            p = tris[idx].reshape(-1, 3)
            e = p.max(0) - p.min(0)
            return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]

        root = area(np.arange(len(f)))
        cost = 0.0
        for n in range(len(is_leaf)):
            idx = subtree_tris(tree, first, second, is_leaf, n)
            cost += area(idx) / root * (len(idx) if is_leaf[n] else 1)
        assert tree.stats.sah_cost == pytest.approx(cost, rel=1e-4)  # stats uses the padded boxes
        costs[builder] = cost
    assert costs["sah"] < costs["lbvh"]


def test_sah_root_split_is_the_best_binned_split():
    """The root's two subtrees are the cheapest split over the bins, found by a plain loop."""
    v, f = soup()
    tree = bvh.build(v, f, builder="sah")
    first, second, is_leaf = children(tree)
    prim = np.asarray(tree.prim_ids)
    tri = v.astype(np.float64)[f]
    lo, hi = tri.min(1), tri.max(1)
    c = (lo + hi) / 2
    axis = int(np.argmax(c.max(0) - c.min(0)))
    x = (c[:, axis] - c[:, axis].min()) / np.ptp(c[:, axis])
    b = np.minimum((x * bvh_sah.DEFAULT.bins).astype(int), bvh_sah.DEFAULT.bins - 1)

    def half_area(mask):
        e = hi[mask].max(0) - lo[mask].min(0)
        return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]

    best = min((half_area(b <= j) * np.sum(b <= j) + half_area(b > j) * np.sum(b > j), j)
               for j in range(bvh_sah.DEFAULT.bins - 1) if 0 < np.sum(b <= j) < len(f))
    left = np.zeros(len(f), bool)
    left[prim[subtree_tris(tree, first, second, is_leaf, first[0])]] = True
    got = half_area(left) * left.sum() + half_area(~left) * (~left).sum()
    assert got == pytest.approx(best[0], rel=1e-6)
    assert np.array_equal(left, b <= best[1]) or np.array_equal(~left, b <= best[1])


def reference_topology(v, f, leaf_size, exact):
    """The SAH tree by plain recursion over Morton-ordered triangle lists, written from the rules
    in bvh_sah's docstring (same float32 binning arithmetic, so the trees must be equal): a node
    above SAH_MIN triangles takes the cheapest of the BINS - 1 bin splits along its widest
    centroid extent; smaller nodes, and nodes with no bin split, take the Morton split. exact:
    centroid bounds recomputed per node; else the parent's cut at the split plane and clipped to
    twice the child's box. Returns nested (left, right) tuples with leaves as tuples of face ids."""
    bins, big_min = bvh_sah.DEFAULT.bins, max(bvh_sah.DEFAULT.sah_min, leaf_size)
    tri = v.astype(np.float32)[f]
    tmin, tmax = tri.min(1), tri.max(1)
    cent = tmin + tmax
    codes = bvh_build.morton_codes(cent)
    morder = np.argsort(codes, kind="stable")
    lo, hi, c, cs = tmin[morder], tmax[morder], cent[morder], codes[morder]
    dt = np.float64 if exact else np.float32

    def area(p):
        e = np.maximum(hi[p].max(0).astype(dt) - lo[p].min(0).astype(dt), 0)
        return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]

    def bounds(p):
        return np.concatenate([c[p].min(0), c[p].max(0)])

    def node(p, cb):
        n = len(p)
        if n <= leaf_size:
            return tuple(morder[p])
        if n > big_min:
            cb = bounds(p) if exact else cb
            ext = cb[3:] - cb[:3]
            a = int(np.argmax(ext))
            scale = np.float32(np.float32(bins * (1 - 1e-6)) / ext[a]) if ext[a] > 0 else np.float32(0)
            b = np.clip(((c[p, a] - cb[a]) * scale).astype(np.int64), 0, bins - 1)
            best = None
            for j in range(bins - 1):
                left = b <= j
                nl = int(left.sum())
                if 0 < nl < n:
                    cost = area(p[left]) * dt(nl) + area(p[~left]) * dt(n - nl)
                    if best is None or cost < best[0]:
                        best = (cost, j)
            if best is not None:
                left = b <= best[1]
                kids = p[left], p[~left]
                cut = np.float32(np.float64(cb[a]) + (best[1] + 1) / np.float64(scale))
                cbs = [cb.copy(), cb.copy()]
                cbs[0][3 + a] = min(cbs[0][3 + a], cut)
                cbs[1][a] = max(cbs[1][a], cut)
                for q, k in zip(cbs, kids):
                    q[:3] = np.maximum(q[:3], 2 * lo[k].min(0))
                    q[3:] = np.minimum(q[3:], 2 * hi[k].max(0))
                return node(kids[0], cbs[0]), node(kids[1], cbs[1])
        x = int(cs[p[0]] ^ cs[p[-1]])
        if x == 0:
            m = n // 2
        else:
            bit = np.uint64(x.bit_length() - 1)
            m = int(np.searchsorted(cs[p], (cs[p[-1]] >> bit) << bit))
        return node(p[:m], bounds(p[:m])), node(p[m:], bounds(p[m:]))

    p = np.arange(len(f))
    return node(p, bounds(p))


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("leaf_size", [1, 3])
def test_sah_topology_matches_recursive_reference(exact, leaf_size):
    v, f = soup()
    f = np.concatenate([f, np.repeat(f[:1], 40, axis=0)])  # 41 equal centroids: no bin split
    tri = v.astype(np.float32)[f]
    tmin, tmax = tri.min(1), tri.max(1)
    codes = bvh_build.morton_codes(tmin + tmax)
    order, left, start, count, _ = bvh_sah.topology(tmin, tmax, tmin + tmax, codes, np.argsort(codes, kind="stable"),
                                                    leaf_size, bvh_sah.SahSettings(exact_bounds=exact))

    def nest(i):
        return tuple(order[start[i]:start[i] + count[i]]) if left[i] < 0 else (nest(left[i]), nest(left[i] + 1))

    assert nest(0) == reference_topology(v, f, leaf_size, exact)


def test_sah_clusters():
    """Clusters near the root (forced on small meshes): a valid tree, as good as without them."""
    v, f = soup()
    f = np.concatenate([f, np.repeat(f[:1], 40, axis=0)])
    for leaf_size in (1, 3):
        check_invariants(v, f, leaf_size, "sah", "bfs", bvh_sah.SahSettings(run_nodes=48))
    s = trimesh.creation.icosphere(subdivisions=4)  # 5120 triangles, a surface like the models
    # clusters binned in nodes of >= 64 of them
    with_clusters = bvh.build(s.vertices, s.faces, builder="sah",
                              sah_settings=bvh_sah.SahSettings(run_nodes=512)).stats.sah_cost
    without = bvh.build(s.vertices, s.faces, builder="sah",
                        sah_settings=bvh_sah.SahSettings(run_nodes=10**9)).stats.sah_cost
    assert with_clusters == pytest.approx(without, rel=0.01)


@pytest.mark.data
def test_sah_traversal_matches_brute_force(data_dir, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    m = mesh.load(data.find("dragon_res4"))
    tree = bvh.build(m.vertices, m.faces, builder="sah", layout="dfs")
    o, d, tmin, tmax = ray_mix(m, 1500, seed=2)
    hit = jax.jit(bvh.intersect)(tree, o, d, tmin, tmax)
    tri = m.vertices.astype(np.float64)[m.faces]
    _, ref_p = check_against_reference(tri, o.astype(np.float64), d.astype(np.float64),
                                       tmin.astype(np.float64), tmax.astype(np.float64), hit)
    assert 0.3 < np.mean(ref_p >= 0) < 0.95
    blocked = np.asarray(jax.jit(bvh.occluded)(tree, o, d, tmax, tmin))
    assert np.array_equal(blocked, np.asarray(hit.prim) >= 0)


def test_builder_rejects_unknown_name():
    s = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(bvh.InputError, match="builder"):
        bvh.build(s.vertices, s.faces, builder="median")


def segment_blocked_f64(tri, p0, p1, margin):
    """Brute-force float64: does segment p0->p1 cross a triangle at s in [0, 1]? Also flags rays
    whose crossings lie within `margin` of either end or of a triangle edge (ties under float32)."""
    d = p1 - p0
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pv = np.cross(d[:, None], e2[None])
    det = np.einsum("rfc,fc->rf", pv, e1)
    inv = 1.0 / np.where(det == 0, np.inf, det)
    tv = p0[:, None] - v0[None]
    u = np.einsum("rfc,rfc->rf", tv, pv) * inv
    qv = np.cross(tv, e1[None])
    v = np.einsum("rc,rfc->rf", d, qv) * inv
    s = np.einsum("fc,rfc->rf", e2, qv) * inv
    inside = (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= 1)
    near = ((np.abs(s) < margin) | (np.abs(s - 1) < margin)) & (u > -margin) & (v > -margin) & (u + v < 1 + margin)
    edge = (np.minimum(np.minimum(np.abs(u), np.abs(v)), np.abs(1 - u - v)) < margin) & (s > -margin) & (s < 1 + margin)
    return inside.any(1), (near | edge).any(1)


@pytest.mark.data
def test_occluded_from_end_matches_brute_force(data_dir, monkeypatch):
    """Shadow segments (surface point -> light) traced from the light end, against float64 brute force."""
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    m = mesh.load(data.find("dragon_res4"))
    tree = bvh.build(m.vertices, m.faces)
    tri = m.vertices.astype(np.float64)[m.faces]
    rng = np.random.default_rng(5)
    n = 600
    f = rng.integers(0, len(tri), n)
    p = np.einsum("kj,kjc->kc", rng.dirichlet([1, 1, 1], n), tri[f])
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    r = np.linalg.norm(hi - lo) / 2
    light = (lo + hi) / 2 + np.array([-1.0, 2.0, 1.5]) * r
    o = p.astype(np.float32)
    d = (light - o).astype(np.float32)
    tmin = np.float32(1e-3)
    tmax = np.where(np.arange(n) % 7 == 0, np.inf, 1 - 1e-3).astype(np.float32)  # some infinite: forwards
    fn = jax.jit(lambda o, d, hi: bvh.occluded(tree, o, d, hi, tmin, from_end=True))
    got = np.asarray(fn(o, d, tmax))
    fwd = np.asarray(jax.jit(lambda o, d, hi: bvh.occluded(tree, o, d, hi, tmin))(o, d, tmax))
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    far = np.where(np.isfinite(tmax), tmax, 1e3).astype(np.float64)
    ref, tie = segment_blocked_f64(tri, o64 + tmin * d64, o64 + far[:, None] * d64, 1e-6)
    assert 0.2 < ref.mean() < 0.8  # both outcomes occur
    assert np.array_equal(got[~tie], ref[~tie]) and tie.mean() < 0.1
    assert np.array_equal(got[~tie], fwd[~tie])


def _same_triangle(n):
    """n copies of one triangle: every centroid and Morton code equal, nothing to split on."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    return v, np.zeros((n, 3), np.int64) + np.arange(3)


@pytest.mark.parametrize("builder,layout", [("lbvh", "bfs"), ("sah", "bfs"), ("sah", "dfs"), ("lbvh", "dfs")])
@pytest.mark.parametrize("case", ["soup", "one", "two", "same", "sphere"])
def test_shapes_before_the_build_are_the_built_trees(builder, layout, case):
    """`bvh.shapes(F)` (what `jaxrt.scene.build` compiles against while the tree is built) has every
    array's shape and dtype of the tree `bvh.build` then makes, whatever the splits: random soup with
    duplicates, one and two triangles, many copies of one triangle (no split position separates
    them), a subdivided sphere."""
    if case == "soup":
        v, f = soup(300)
    elif case == "sphere":
        m = trimesh.creation.icosphere(3)
        v, f = np.asarray(m.vertices, np.float32), np.asarray(m.faces)
    elif case == "same":
        v, f = _same_triangle(37)
    else:
        v, f = soup(1 if case == "one" else 2)
    tree = bvh.build(v, f, leaf_size=1, builder=builder, layout=layout)
    want = jax.tree.structure(tree), [(x.shape, x.dtype) for x in jax.tree.leaves(tree)]
    shaped = bvh.shapes(len(f))
    assert all(isinstance(x, jax.ShapeDtypeStruct) for x in jax.tree.leaves(shaped))
    assert (jax.tree.structure(shaped), [(x.shape, x.dtype) for x in jax.tree.leaves(shaped)]) == want
    assert np.asarray(tree.node_leaf)[:, 1].max() == 1  # one triangle per leaf: the premise of shapes()


def test_shapes_are_unknown_for_larger_leaves():
    assert bvh.shapes(100, leaf_size=4) is None and bvh.shapes(0) is None
