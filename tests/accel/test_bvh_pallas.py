"""The Pallas traversal kernel (jaxrt.accel.traverse_pallas), run in the Pallas interpreter on this CPU, gives the
XLA loop's hits and agrees with float64 brute force; the traversal switch (impl / JAXRT_TRAVERSAL).

On a GPU the same kernel is compiled by Triton; benchmarks/gpu.py checks there that both traversals
agree on every ray of full-resolution frames.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_bvh import check_against_reference, icosphere_mesh, ray_mix

from jaxrt.accel import bvh
from jaxrt.geometry import data
from jaxrt.geometry import mesh
from jaxrt.errors import InputError


@pytest.fixture(scope="module")
def fns():
    """Jitted closest-hit and any-hit for both traversals (compiled once per tree shape)."""

    def make(impl):
        return (jax.jit(lambda tr, o, d, lo, hi: bvh.intersect(tr, o, d, lo, hi, impl=impl)),
                jax.jit(lambda tr, o, d, lo, hi: bvh.occluded(tr, o, d, hi, lo, impl=impl)))

    return {"xla": make("xla"), "pallas": make("pallas-interpret")}


def assert_same_hits(a, b):
    """Same triangle for every ray and the same t, u, v (the kernel runs the XLA loop's arithmetic)."""
    pa, pb = np.asarray(a.prim), np.asarray(b.prim)
    assert np.array_equal(pa, pb), f"{int(np.sum(pa != pb))} rays hit different triangles"
    # atol: where t comes out of cancellation (a ray leaving a surface at a grazing angle: t ~ 1e-3 for
    # terms ~ 1 in these unit-size meshes), a multiply-add contracted by one compiler and not by
    # another moves it by an ulp of the terms, ~1e-8 absolute
    np.testing.assert_allclose(np.asarray(a.t), np.asarray(b.t), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(a.u), np.asarray(b.u), atol=1e-6)
    np.testing.assert_allclose(np.asarray(a.v), np.asarray(b.v), atol=1e-6)


@pytest.mark.data
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_pallas_matches_xla_and_brute_force(data_dir, fns, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    m = mesh.load(data.find("bunny"))
    tree = bvh.build(m.vertices, m.faces)
    # 700 rays: not a multiple of the kernel's block (1024 in the interpreter): padding rays are exercised.
    o, d, tmin, tmax = ray_mix(m, 700, seed=3)
    hit_p = fns["pallas"][0](tree, o, d, tmin, tmax)
    hit_x = fns["xla"][0](tree, o, d, tmin, tmax)
    assert_same_hits(hit_p, hit_x)
    tri = m.vertices.astype(np.float64)[m.faces]
    _, ref_p = check_against_reference(tri, o.astype(np.float64), d.astype(np.float64), tmin.astype(np.float64),
                                       tmax.astype(np.float64), hit_p)
    assert 0.3 < np.mean(ref_p >= 0) < 0.95
    occ_p = np.asarray(fns["pallas"][1](tree, o, d, tmin, tmax))
    occ_x = np.asarray(fns["xla"][1](tree, o, d, tmin, tmax))
    assert np.array_equal(occ_p, occ_x)
    assert np.array_equal(occ_p, np.asarray(hit_p.prim) >= 0)


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_pallas_watertight_edges_and_vertices(fns, leaf_size):
    """Rays aimed exactly at edges and vertices of a closed mesh all hit (exact edge signs), also with
    several triangles per leaf (the kernel's per-leaf loop)."""
    m = icosphere_mesh(2)
    tree = bvh.build(m.vertices, m.faces, leaf_size=leaf_size)
    v = m.vertices.astype(np.float64)
    rng = np.random.default_rng(11)
    n = 1200
    e = m.faces[rng.integers(0, len(m.faces), n)][:, :2]
    s = np.where(rng.random(n) < 0.5, 0.5, rng.random(n))
    tgt = v[e[:, 0]] * (1 - s[:, None]) + v[e[:, 1]] * s[:, None]
    at_vertex = rng.random(n) < 0.3
    tgt = np.where(at_vertex[:, None], v[rng.integers(0, len(v), n)], tgt).astype(np.float32)
    rnd = rng.normal(size=(n, 3))
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    o = (tgt + 3.0 * (tgt / np.linalg.norm(tgt, axis=1, keepdims=True) + 0.7 * rnd)).astype(np.float32)
    d = (tgt - o).astype(np.float32)
    lo, hi = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    hit = fns["pallas"][0](tree, o, d, lo, hi)
    prim = np.asarray(hit.prim)
    assert np.all(prim >= 0), f"{int(np.sum(prim < 0))} of {n} rays slipped through edges/vertices"
    assert np.all(np.abs(np.asarray(hit.t) - 1.0) < 1e-4)
    assert_same_hits(hit, fns["xla"][0](tree, o, d, lo, hi))


def test_brute_force_layout_gets_the_trees_hits(fns, monkeypatch):
    """The kernel's brute-force layout (every ray against every triangle; `traverse_pallas.default_layout`
    picks it for tables of at most `BRUTE_FORCE_MAX_TRIANGLES`, 0 by default) gets the XLA loop's hits
    from its tree on every kind of ray, closest and any hit (whose loop stops once a block's rays all
    have one); rays aimed exactly at edges and vertices all hit (the same watertight test)."""
    from jaxrt.accel import traverse_pallas as bvh_pallas

    monkeypatch.setattr(bvh_pallas, "BRUTE_FORCE_MAX_TRIANGLES", 64)
    assert bvh_pallas.default_layout(64, 1) == "brute" and bvh_pallas.default_layout(64, 4) == "brute"
    assert bvh_pallas.default_layout(65, 1) == "childbox" and bvh_pallas.default_layout(65, 4) == "tables"
    # new functions: jit's trace cache would keep a layout chosen before the patch
    closest = jax.jit(lambda tr, o, d, lo, hi: bvh.intersect(tr, o, d, lo, hi, impl="pallas-interpret"))
    anyhit = jax.jit(lambda tr, o, d, lo, hi: bvh.occluded(tr, o, d, hi, lo, impl="pallas-interpret"))
    m = icosphere_mesh(0)
    tree = bvh.build(m.vertices, m.faces)
    assert bvh_pallas.default_layout(len(m.faces), tree.leaf_size) == "brute"
    # 1500 rays: two of the interpreter's 1024-ray blocks, the second padded
    o, d, tmin, tmax = ray_mix(m, 1500, seed=4)
    hit_p = closest(tree, o, d, tmin, tmax)
    # the tree's hits (the XLA loop is checked against float64 brute force in test_bvh.py)
    assert_same_hits(hit_p, fns["xla"][0](tree, o, d, tmin, tmax))
    assert 0.3 < np.mean(np.asarray(hit_p.prim) >= 0) < 0.95
    occ_p = np.asarray(anyhit(tree, o, d, tmin, tmax))
    assert np.array_equal(occ_p, np.asarray(fns["xla"][1](tree, o, d, tmin, tmax)))
    assert np.array_equal(occ_p, np.asarray(hit_p.prim) >= 0)
    # aimed at vertices and edge midpoints from outside: all hit at t = 1
    v = m.vertices.astype(np.float32)
    tgt = np.concatenate([v, (v[m.faces[:, 0]] + v[m.faces[:, 1]]) / 2]).astype(np.float32)
    rng = np.random.default_rng(9)
    o2 = (tgt * 3 + rng.normal(size=tgt.shape) * 0.5).astype(np.float32)
    d2 = (tgt - o2).astype(np.float32)
    lo, hi = np.zeros(len(o2), np.float32), np.full(len(o2), np.inf, np.float32)
    hit = closest(tree, o2, d2, lo, hi)
    assert np.all(np.asarray(hit.prim) >= 0) and np.all(np.abs(np.asarray(hit.t) - 1.0) < 1e-4)
    assert np.all(np.asarray(anyhit(tree, o2, d2, lo, hi)))


def test_traversal_switch(monkeypatch):
    m = icosphere_mesh(1)
    tree = bvh.build(m.vertices, m.faces)
    o = np.zeros((4, 3), np.float32)
    d = np.eye(3, dtype=np.float32)[[0, 1, 2, 0]]
    with pytest.raises(InputError, match="JAXRT_TRAVERSAL"):
        bvh.intersect(tree, o, d, impl="cuda")
    monkeypatch.setenv("JAXRT_TRAVERSAL", "fast")
    with pytest.raises(InputError, match="'fast'"):
        bvh.occluded(tree, o, d)
    monkeypatch.delenv("JAXRT_TRAVERSAL")
    # "auto" on a CPU lowers one kernel only (no Triton call, no XLA loop): Embree
    # (jaxrt.accel.traverse_embree) where it is installed, as here and in CI, else the native kernel
    # (jaxrt.accel.traverse_cpu); "cpu" the native kernel, "xla" the portable loop.
    text = jax.jit(bvh.intersect).lower(tree, o, d).as_text()
    assert "triton" not in text.lower()
    assert "jaxrt_embree_trace" in text and "jaxrt_bvh_traverse" not in text and "while" not in text
    text = jax.jit(lambda *a: bvh.intersect(*a, impl="cpu")).lower(tree, o, d).as_text()
    assert "jaxrt_bvh_traverse" in text and "jaxrt_embree_trace" not in text and "while" not in text
    text = jax.jit(lambda *a: bvh.intersect(*a, impl="xla")).lower(tree, o, d).as_text()
    assert "while" in text and "jaxrt_bvh_traverse" not in text and "jaxrt_embree_trace" not in text
    hit = bvh.intersect(tree, o, d)
    t = np.asarray(hit.t)  # a closed polyhedron inscribed in the unit sphere, seen from its centre
    assert np.all(np.asarray(hit.prim) >= 0) and np.all((t > 0.79) & (t <= 1.0))


def plane_distance(tri9, o, d):
    """Float64 distance along each ray to the plane of its triangle (rows of 9: v0, v1, v2)."""
    v0, v1, v2 = tri9[:, 0:3], tri9[:, 3:6], tri9[:, 6:9]
    nrm = np.cross(v1 - v0, v2 - v0)
    o, d = o.astype(np.float64), d.astype(np.float64)
    return np.sum(nrm * (v0 - o), 1) / np.sum(nrm * d, 1)


@pytest.mark.slow  # (the Pallas interpreter on a CPU: ~140 s; the default suite keeps test_pallas_matches_xla_and_brute_force)
def test_pallas_layout_variants_agree():
    """The kernel's speed options (node-row layouts, exact signs always on, the triangle test in every
    warp, the order rays are taken in) give the default's hits, on rays aimed at vertices and edges (where the exact signs
    matter), with and without the tree's packed rows."""
    from jaxrt.accel import traverse_pallas as bvh_pallas

    m = icosphere_mesh(1)
    tree = bvh.build(m.vertices, m.faces)
    arrays = dict(node_box=tree.node_box, node_leaf=tree.node_leaf, links=tree.links, triangles=tree.triangles)
    v = m.vertices.astype(np.float32)
    rng = np.random.default_rng(5)
    tgt = np.concatenate([v, (v[m.faces[:, 0]] + v[m.faces[:, 1]]) / 2]).astype(np.float32)
    o = (tgt * 3 + rng.normal(size=tgt.shape) * 0.5).astype(np.float32)
    d = (tgt - o).astype(np.float32)
    lo, hi = np.zeros(len(o), np.float32), np.full(len(o), np.inf, np.float32)
    hi[::5] = 0.3  # some rays end before the mesh
    perm = rng.permutation(len(o)).astype(np.int32)
    run = lambda arr=arrays, any_hit=False, block=64, **kw: [np.asarray(x) for x in bvh_pallas.traverse(  # noqa: E731
        arr, o, d, lo, hi, any_hit=any_hit, leaf_size=1, block=block, interpret=True, **kw)]
    found, t, tri, u, v_ = run()
    assert 0.5 < found.mean() < 1
    packed = dict(arrays, **dict(zip(("rows", "skips"), bvh_pallas.pack_tables(**arrays))))
    variants = (dict(arr=packed), dict(trail=0), dict(trail=2), dict(vector_loads=False),
                dict(arr=packed, vector_loads=False), dict(layout="wide"), dict(layout="wide", trail=0),
                dict(layout="wide", trail=2, vector_loads=False), dict(gate_exact=False), dict(postpone=True),
                dict(layout="inline"), dict(layout="tables"), dict(skip_tri=False), dict(layout="tables", block=32),
                dict(layout="inline", steps_per_iter=3), dict(layout="brute"), dict(layout="brute", scalar_loads=True),
                dict(layout="brute", block=32),
                # rays taken in another order (`order`: each read and written where it is)
                dict(order=perm), dict(arr=packed, order=perm), dict(layout="brute", order=perm))
    for kw in variants:
        r = run(**kw)
        assert np.array_equal(r[0], found), kw
        # The same triangle, except where the compiler's choice of multiply-add contraction moved t by
        # an ulp at a tie (rays aimed at shared edges and vertices): there both are hit at that t.
        np.testing.assert_allclose(r[1], t, rtol=1e-6, err_msg=str(kw))
        other = np.flatnonzero(r[2] != tri)
        # (brute force keeps the lowest index of triangles tied in t, the tree the first it visits:
        # these rays, aimed at shared vertices and edges, tie by design)
        assert len(other) <= (0.5 if kw.get("layout") == "brute" else 0.1) * len(o), kw
        for tri_ids in (tri[other], r[2][other]):
            t64 = plane_distance(np.asarray(tree.triangles, np.float64)[tri_ids], o[other], d[other])
            np.testing.assert_allclose(t64, t[other], rtol=1e-5, err_msg=str(kw))
        same = r[2] == tri
        for a, b in zip(r[3:], (u, v_)):
            np.testing.assert_allclose(a[same], b[same], atol=1e-6, err_msg=str(kw))
        assert np.array_equal(run(any_hit=True, **kw)[0], found), kw


def test_node_depth_and_skip_table():
    """The kernel's node depths (pointer jumping) against a breadth-first walk in numpy, and its skip
    table decodes to the tree's miss links and their targets' depths."""
    from jaxrt.accel import builder as bvh_build
    from jaxrt.accel import traverse_pallas as bvh_pallas

    m = icosphere_mesh(2)
    rng = np.random.default_rng(2)
    v = np.concatenate([m.vertices, rng.normal(size=(60, 3)) * 0.01 + 2.0]).astype(np.float32)  # a dense clump: deep
    f = np.concatenate([m.faces, len(m.vertices) + rng.integers(0, 60, size=(200, 3))])
    tree = bvh.build(v, f)
    leaf = np.asarray(tree.node_leaf)
    links = np.asarray(tree.links)
    nn = len(leaf)
    is_leaf = leaf[:, 1] > 0
    want = np.full(nn, -1)
    frontier, d = np.array([0]), 0
    while len(frontier):
        want[frontier] = d
        inner = frontier[~is_leaf[frontier]]
        first = links[inner, 0]
        frontier = np.concatenate([first, links[first, 1]])
        d += 1
    got = np.asarray(bvh_pallas.node_depth(tree.node_leaf, tree.links))
    assert np.array_equal(got, want) and want.max() > 8
    sk = np.asarray(bvh_pallas.pack_skips(tree.node_leaf, tree.links))
    miss = links[:, 1]
    assert len(sk) == bvh_build.NUM_RAY_CLASSES * nn
    assert np.array_equal(sk >> 5, miss)
    assert np.array_equal(sk & 31, np.where(miss >= 0, np.minimum(want[np.maximum(miss, 0)], 31), 0))


def test_wide_tables_walk_the_binary_trees_order():
    """The four-wide kernel's tables (`traverse_pallas.pack_wide`) against the binary tree, in numpy:
    for every ray class, a depth-first walk of the wide rows (children in the class's order from the
    order bits) visits the binary tree's leaves in the binary walk's order, and every node's link is
    the node that follows its subtree in that walk, with that node's depth and its position among its
    parent's four slots."""
    from jaxrt.accel import builder as bvh_build
    from jaxrt.accel import traverse_pallas as bvh_pallas

    m = icosphere_mesh(2)
    rng = np.random.default_rng(2)
    v = np.concatenate([m.vertices, rng.normal(size=(60, 3)) * 0.01 + 2.0]).astype(np.float32)  # a dense clump: deep
    f = np.concatenate([m.faces, len(m.vertices) + rng.integers(0, 60, size=(200, 3))])
    tree = bvh.build(v, f)
    rows, skips = (np.asarray(x) for x in bvh_pallas.pack_wide(tree.node_box, tree.node_leaf, tree.links,
                                                                tree.triangles))
    leaf = np.asarray(tree.node_leaf)
    links = np.asarray(tree.links)
    nn, classes = len(leaf), bvh_build.NUM_RAY_CLASSES
    assert rows.shape == (nn, 32) and skips.shape == (classes * nn,)
    as_int = rows.view(np.int32)
    assert np.asarray(bvh.stats(tree).depth) > 8
    for c in range(classes):
        lk = links[c * nn:(c + 1) * nn]
        want, stack = [], [0]  # binary walk: leaves in class c's order
        while stack:
            n = stack.pop()
            if leaf[n, 1] > 0:
                want.append(int(leaf[n, 0]))
            else:
                first = lk[n, 0]
                stack += [lk[first, 1], first]  # the first child's miss link is its sibling
        order, stack = [], [(0, 0, 0)]  # wide walk: (row, depth, position)
        while stack:
            w, depth, pos = stack.pop()
            order.append((w, depth, pos))
            if as_int[w, 29] == 1:
                continue
            assert as_int[w, 29] == -(depth + 1)
            bits = (as_int[w, 28] >> (3 * c)) & 7
            pair_a = as_int[w, 24:26][::-1] if bits & 2 else as_int[w, 24:26]
            pair_b = as_int[w, 26:28][::-1] if bits & 4 else as_int[w, 26:28]
            slots = np.concatenate([pair_b, pair_a] if bits & 1 else [pair_a, pair_b])
            stack += [(int(k), depth + 1, p) for p, k in reversed(list(enumerate(slots))) if k >= 0]
        got = [int(as_int[w, 9]) for w, _, _ in order if as_int[w, 29] == 1]
        assert got == want, c
        # links: the next node of the walk outside each node's subtree (subtree ends where depth returns)
        for i, (w, depth, _) in enumerate(order):
            j = next((j for j in range(i + 1, len(order)) if order[j][1] <= depth), None)
            sk = int(skips[c * nn + w])
            if j is None:
                assert sk >> 7 == -1
            else:
                nxt, d, p = order[j]
                assert (sk >> 7, (sk >> 2) & 31, sk & 3) == (nxt, min(d, 31), p), (c, w)


def test_kernel_counts_its_steps():
    """`traverse(..., count_steps=True)` (a measurement): the same hits as the plain kernel; each
    program loops as many times as its slowest ray steps; the triangle test's iterations are at
    most all of them and at least one where a ray hits; the four-wide tree takes fewer steps."""
    from jaxrt.accel import traverse_pallas as bvh_pallas

    m = icosphere_mesh(2)
    tree = bvh.build(m.vertices, m.faces)
    arrays = dict(node_box=tree.node_box, node_leaf=tree.node_leaf, links=tree.links, triangles=tree.triangles)
    o, d, lo, hi = ray_mix(m, 256, seed=4)
    block = 64
    steps = {}
    for layout in ("childbox", "wide"):
        plain = [np.asarray(x) for x in bvh_pallas.traverse(arrays, o, d, lo, hi, any_hit=False, leaf_size=1,
                                                            block=block, interpret=True, layout=layout)]
        found, t, tri, u, v, n_steps, n_iter, n_leaf = (np.asarray(x) for x in bvh_pallas.traverse(
            arrays, o, d, lo, hi, any_hit=False, leaf_size=1, block=block, interpret=True, layout=layout,
            count_steps=True))
        for a, b in zip((found, t, tri, u, v), plain):
            np.testing.assert_array_equal(a, b)
        assert n_steps.min() >= 1
        per_block = n_steps.reshape(-1, block)
        slowest = np.broadcast_to(per_block.max(1, keepdims=True), per_block.shape)
        np.testing.assert_array_equal(n_iter.reshape(-1, block), slowest)
        assert np.all(n_leaf <= n_iter) and np.all(n_leaf.reshape(-1, block)[found.reshape(-1, block).any(1)] >= 1)
        steps[layout] = n_steps.mean()
    assert 0.4 * steps["childbox"] < steps["wide"] < 0.9 * steps["childbox"], steps
    with pytest.raises(ValueError, match="count_steps"):
        bvh_pallas.traverse(arrays, o, d, lo, hi, any_hit=False, leaf_size=1, layout="brute", count_steps=True)


def test_postponed_leaves_batch_the_triangle_tests():
    """Postponed leaves (`traverse(..., postpone=True)`): the same hits as testing each leaf where it
    is reached, for closest and any hits, and the warps run the triangle test in fewer of their loop
    iterations (counted), for about as many iterations in all."""
    from jaxrt.accel import traverse_pallas as bvh_pallas

    m = icosphere_mesh(2)
    tree = bvh.build(m.vertices, m.faces)
    arrays = dict(node_box=tree.node_box, node_leaf=tree.node_leaf, links=tree.links, triangles=tree.triangles)
    o, d, lo, hi = ray_mix(m, 512, seed=7)
    rng = np.random.default_rng(7)
    d = np.where(rng.random((len(d), 1)) < 0.5, rng.normal(size=d.shape), d).astype(np.float32)  # incoherent half
    run = lambda any_hit, postpone: [np.asarray(x) for x in bvh_pallas.traverse(  # noqa: E731
        arrays, o, d, lo, hi, any_hit=any_hit, leaf_size=1, block=32, interpret=True, layout="childbox",
        postpone=postpone, count_steps=True)]
    now, later = run(False, False), run(False, True)
    assert 0.2 < now[0].mean() < 1
    np.testing.assert_array_equal(later[0], now[0])
    np.testing.assert_allclose(later[1][now[0]], now[1][now[0]], rtol=1e-6)
    assert np.mean(later[2] != now[2]) <= 0.02  # (a tie in t may keep another triangle)
    n_iter, n_test = (later[k].reshape(-1, 32)[:, 0].sum() / now[k].reshape(-1, 32)[:, 0].sum() for k in (6, 7))
    assert n_test < 0.85 and 0.95 < n_iter < 1.2, (n_test, n_iter)
    np.testing.assert_array_equal(run(True, True)[0], run(True, False)[0])
