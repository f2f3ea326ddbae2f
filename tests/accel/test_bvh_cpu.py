"""The native CPU traversal kernel (`jaxrt.accel.traverse_cpu`) against independent references.

Brute force (float64, tests/test_bvh.py's checker) for leaf sizes the default tree does not use;
the XLA loop (`jaxrt.accel.traverse_xla`) for the same tree and rays (same results up to ties between
triangles at the same distance); closed-form hits at exactly tmin / tmax; N = 0; jit and vmap; the
fallback to the XLA loop where no compiler exists. tests/test_bvh.py runs its brute-force,
watertightness and jit checks on both implementations.
"""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from test_bvh import RTOL, brute_force, check_against_reference, ray_mix

from jaxrt.accel import bvh
from jaxrt.accel import traverse_cpu as bvh_cpu
from jaxrt.accel import traverse_xla as bvh_traverse


def test_kernel_builds_here():
    # CI and this machine have a C++ compiler: the fast path must be what the suite exercises.
    assert bvh_cpu.available()


def _arrays(tree):
    return {"node_box": tree.node_box, "node_leaf": tree.node_leaf, "links": tree.links, "triangles": tree.triangles}


@pytest.mark.data
@pytest.mark.parametrize("leaf_size", [4, 16])
def test_leaf_sizes_match_brute_force(bunny, leaf_size):
    tree = bvh.build(bunny.vertices, bunny.faces, leaf_size=leaf_size)
    o, d, tmin, tmax = ray_mix(bunny, 300, seed=leaf_size)
    f = jax.jit(lambda tr, o, d, lo, hi: (bvh.intersect(tr, o, d, lo, hi, impl="cpu"),
                                         bvh.occluded(tr, o, d, hi, lo, impl="cpu")))
    hit, occ = f(tree, o, d, tmin, tmax)
    tri = bunny.vertices.astype(np.float64)[bunny.faces]
    _, ref_p = check_against_reference(tri, o.astype(np.float64), d.astype(np.float64), tmin.astype(np.float64),
                                       tmax.astype(np.float64), hit)
    assert 0.3 < np.mean(ref_p >= 0) < 0.95
    # any-hit with early exit finds a hit exactly where the closest-hit query does
    np.testing.assert_array_equal(np.asarray(occ), np.asarray(hit.prim) >= 0)


def _plane_t(tri9, o, d):
    v0, v1, v2 = tri9[:, 0:3], tri9[:, 3:6], tri9[:, 6:9]
    nrm = np.cross(v1 - v0, v2 - v0)
    return np.sum(nrm * (v0 - o), 1) / np.sum(nrm * d.astype(np.float64), 1)


@pytest.mark.data
def test_kernel_matches_xla_loop(bunny):
    """Raw traversal outputs of both paths on one tree with 4-triangle leaves (ties inside leaves)."""
    tree = bvh.build(bunny.vertices, bunny.faces, leaf_size=4)
    o, d, tmin, tmax = ray_mix(bunny, 2000, seed=3)
    arrays = _arrays(tree)
    xla = jax.jit(lambda a, *r: bvh_traverse.traverse(a, *r, any_hit=False, leaf_size=4, steps_per_iter=2,
                                                      lanes=256)[:5])(arrays, o, d, tmin, tmax)
    nat = jax.jit(lambda a, *r: bvh_cpu.traverse(a, *r, any_hit=False))(arrays, o, d, tmin, tmax)
    fx, tx, bx, ux, vx = map(np.asarray, xla)
    fn, tn, bn, un, vn = map(np.asarray, nat)
    np.testing.assert_array_equal(fn, fx)
    same = bn == bx
    assert same.mean() > 0.99
    # a different triangle only as a tie: hit at the same distance
    np.testing.assert_allclose(tn[~same], tx[~same], rtol=RTOL)
    np.testing.assert_allclose(tn[fx], tx[fx], rtol=RTOL)
    np.testing.assert_array_equal(tn[~fx], tmax[~fx])  # a miss leaves t at tmax
    # barycentrics are the same float32 quotients of the same edge functions
    np.testing.assert_array_equal(un[same], ux[same])
    np.testing.assert_array_equal(vn[same], vx[same])
    assert np.all(un[~fn] == 0) and np.all(vn[~fn] == 0)
    # Threads (own std::threads instead of XLA's pool) and lanes only change the speed.
    for kw in ({"threads": 3, "lanes": 1}, {"threads": 1, "lanes": 32}):
        other = jax.jit(lambda a, *r, kw=kw: bvh_cpu.traverse(a, *r, any_hit=False, **kw))(arrays, o, d, tmin, tmax)
        for x, y in zip(other, (fn, tn, bn, un, vn)):
            np.testing.assert_array_equal(np.asarray(x), y, err_msg=str(kw))
    with pytest.raises(ValueError, match="lanes"):
        bvh_cpu.traverse(arrays, o, d, tmin, tmax, any_hit=False, lanes=33)
    # refine: the kernel's double-precision t of each hit = the XLA path's double-float refine_t of the
    # same triangle (both the float32 nearest the plane distance, to an ulp), also on grazing rays
    _, tr, br, ur, vr = map(np.asarray, jax.jit(lambda a, *r: bvh_cpu.traverse(a, *r, any_hit=False, refine=True))(
        arrays, o, d, tmin, tmax))
    np.testing.assert_array_equal(br, bn)
    np.testing.assert_array_equal(ur, un)
    np.testing.assert_array_equal(tr[~fn], tn[~fn])
    ref = np.asarray(bvh_traverse.refine_t(np.asarray(tree.triangles)[bn[fn]], o[fn], d[fn], tn[fn]))
    np.testing.assert_allclose(tr[fn], ref, rtol=2.5e-7)
    t64 = _plane_t(np.asarray(tree.triangles, np.float64)[bn[fn]], o[fn], d[fn])
    assert np.mean(np.abs(tr[fn] - t64) <= 1e-7 * np.abs(t64)) > 0.99


def test_exact_ties_keep_the_earlier_triangle_and_t_limits_are_inclusive():
    # Two copies of a unit quad at z = 0: every hit is an exact tie between a triangle and its copy.
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    tree = bvh.build(np.concatenate([v, v]), np.concatenate([f, f + 4]), leaf_size=4)
    xy = np.array([[0.3, -0.2], [-0.5, 0.4], [0.0, 0.0], [0.9, -0.9], [1.0, 1.0]], np.float32)
    o = np.concatenate([xy, np.ones((len(xy), 1), np.float32)], axis=1)
    d = np.tile(np.float32([0, 0, -1]), (len(o), 1))
    # The plane is at t = 1 exactly (every quantity of the watertight test is exact here).
    below, above = np.nextafter(np.float32(1), np.float32(0)), np.nextafter(np.float32(1), np.float32(2))
    cases = [(0.0, np.inf, True), (0.0, 1.0, True), (1.0, 1.0, True), (0.0, below, False), (above, np.inf, False),
             (1.0, 0.5, False)]
    for lo, hi, expect in cases:
        hit = bvh.intersect(tree, o, d, lo, hi, impl="cpu")
        occ = bvh.occluded(tree, o, d, hi, lo, impl="cpu")
        prim = np.asarray(hit.prim)
        np.testing.assert_array_equal(prim >= 0, expect, err_msg=f"tmin {lo} tmax {hi}")
        np.testing.assert_array_equal(np.asarray(occ), expect)
        if expect:
            np.testing.assert_array_equal(np.asarray(hit.t), 1.0)
            # the copy (faces 2, 3) ties exactly with the original (faces 0, 1): the first one wins
            assert np.all(prim < 2), prim
            p = np.asarray(hit.u)[:, None] * (v[f[prim, 1]] - v[f[prim, 0]]) + np.asarray(hit.v)[:, None] * (
                v[f[prim, 2]] - v[f[prim, 0]]) + v[f[prim, 0]]
            np.testing.assert_allclose(p[:, :2], xy, atol=1e-6)


def test_zero_rays_jit_and_vmap():
    s = trimesh.creation.icosphere(subdivisions=2)
    tree = bvh.build(s.vertices, s.faces)
    arrays = _arrays(tree)
    z = jnp.zeros((0, 3), jnp.float32)
    found, t, best, u, v = bvh_cpu.traverse(arrays, z, z, jnp.zeros(0), jnp.zeros(0), any_hit=False)
    assert found.shape == t.shape == best.shape == u.shape == v.shape == (0,)
    assert bvh.intersect(tree, z, z, impl="cpu").prim.shape == (0,)
    # A batch of 3 ray sets under vmap (and jit) equals three separate calls.
    rng = np.random.default_rng(0)
    o = rng.normal(size=(3, 50, 3)).astype(np.float32) * 3
    d = (rng.normal(size=(3, 50, 3)) * 0.6 - o).astype(np.float32)
    f = jax.jit(jax.vmap(lambda o, d: bvh.intersect(tree, o, d, impl="cpu")))
    batched = f(o, d)
    occ = jax.jit(jax.vmap(lambda o, d: bvh.occluded(tree, o, d, 10.0, impl="cpu")))(o, d)
    hits = 0
    for b in range(3):
        one = bvh.intersect(tree, o[b], d[b], impl="cpu")
        np.testing.assert_array_equal(np.asarray(batched.prim[b]), np.asarray(one.prim))
        np.testing.assert_array_equal(np.asarray(batched.t[b]), np.asarray(one.t))
        np.testing.assert_array_equal(np.asarray(occ[b]), np.asarray(one.t) <= 10.0)
        hits += int(np.sum(np.asarray(one.prim) >= 0))
        # the icosphere's faces lie within the unit sphere: a hit is at distance <= 1 from the centre
        p = o[b] + np.asarray(one.t)[:, None] * d[b]
        ok = np.asarray(one.prim) >= 0
        assert np.all(np.linalg.norm(p[ok], axis=1) <= 1.0 + 1e-5)
        tri = s.vertices.astype(np.float32).astype(np.float64)[s.faces]
        _, ref_p = brute_force(tri, o[b].astype(np.float64), d[b].astype(np.float64), np.zeros(50),
                               np.full(50, np.inf))
        np.testing.assert_array_equal(np.asarray(one.prim) >= 0, ref_p >= 0)
    assert 10 < hits < 145  # hits and misses


def test_fallback_without_compiler(monkeypatch, tmp_path):
    """No compiler: one warning, then the XLA loop's results (never an error)."""
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(tmp_path))  # nothing cached there
    monkeypatch.setattr(bvh_cpu, "_compiler", str(tmp_path / "no-such-c++"))
    bvh_cpu._reset_for_tests()
    try:
        with pytest.warns(RuntimeWarning, match="native CPU traversal kernel is unavailable"):
            assert not bvh_cpu.available()
        box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
        tree = bvh.build(box.vertices, box.faces)
        o = np.array([[0.2, 0.1, 5.0], [3.0, 0.0, 5.0]], np.float32)
        d = np.tile(np.float32([0, 0, -1]), (2, 1))
        hit = bvh.intersect(tree, o, d, impl="cpu")  # the XLA loop now
        np.testing.assert_array_equal(np.asarray(hit.t), [4.75, np.inf])  # box top at z = 0.25
        with pytest.raises(RuntimeError, match="could not be built"):
            bvh_cpu.traverse(_arrays(tree), o, d, jnp.zeros(2), jnp.full(2, jnp.inf), any_hit=False)
    finally:
        monkeypatch.undo()
        bvh_cpu._reset_for_tests()
    assert bvh_cpu.available()


@pytest.mark.slow
def test_concurrent_compiles_into_an_empty_cache(tmp_path, monkeypatch):
    """Two compiles of the same key at once (pytest-xdist workers) both return a loadable library."""
    import ctypes

    monkeypatch.setenv("JAXRT_CACHE_DIR", str(tmp_path))  # the kernel goes to <cache>/native
    src = bvh_cpu._source()
    out, errors = [], []

    def run():
        try:
            out.append(bvh_cpu._compile(src, "c++"))
        except Exception as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=run) for _ in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors and len(out) == 2 and out[0] == out[1]
    assert [p.name for p in (tmp_path / "native").iterdir()] == [out[0].name]  # no temporary left behind
    assert hasattr(ctypes.CDLL(str(out[0])), "JaxrtBvhTraverse")


@pytest.mark.parametrize("impl", ["cpu", "xla"])
def test_edge_sign_is_exact_where_rounded_products_tie(impl):
    """A ray passing 2**-47 beside the shared edge of two triangles hits exactly one, the right one.

    Edge A-C's function at the ray is ax*cy - ay*cx = -2**-46 exactly, but both float32 products
    round to -(1 + 2**-22): only an exact evaluation of the sign decides the side (a rounded one
    calls it 0, 'on the edge', and both triangles are hit).
    """
    from fractions import Fraction

    e = np.float32(2.0**-23)
    a = np.array([-(1 + e), -1, 0], np.float32)
    c = np.array([1 + 2 * e, 1 + e, 0], np.float32)
    assert np.float32(a[0] * c[1]) == np.float32(a[1] * c[0])  # the rounded products tie
    o = np.float32([[0, 0, 1]])
    d = np.float32([[0, 0, -1]])

    def side(p):  # exact sign of cross(c - a, p - a) in 2D
        ax, ay, cx, cy = (Fraction(float(x)) for x in (a[0], a[1], c[0], c[1]))
        return np.sign((cx - ax) * (Fraction(float(p[1])) - ay) - (cy - ay) * (Fraction(float(p[0])) - ax))

    origin_side = side(np.zeros(2))
    assert origin_side != 0
    hits = []
    # the tree as a traced argument: one compile serves both trees
    f = jax.jit(lambda tr, o, d: (bvh.intersect(tr, o, d, impl=impl).prim, bvh.occluded(tr, o, d, impl=impl)))
    for b in (np.float32([-5, 5, 0]), np.float32([5, -5, 0])):  # one triangle on each side of the edge
        prim, occ = f(bvh.build(np.stack([a, c, b]), np.array([[0, 1, 2]])), o, d)
        hits.append(int(prim[0]) == 0)
        assert hits[-1] == (side(b) == origin_side)
        assert bool(occ[0]) == hits[-1]
    assert sum(hits) == 1
