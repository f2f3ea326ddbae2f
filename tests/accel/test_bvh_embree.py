"""The Embree traversal (`jaxrt.accel.traverse_embree`) against independent references.

The native kernel's raw outputs on the same tree and rays (same triangle up to ties at the same
distance; t, u, v to a few ulps; the ties and ulp differences counted and bounded); brute force in
float64 and watertightness run in tests/test_bvh.py for every CPU traversal; closed-form hits at
exactly tmin / tmax; inactive rays (NaN, tmin > tmax); the scene cache (a changed triangle table is
never traced through an old scene); a direct frame equal to the native kernel's within tolerance;
N = 0, jit and vmap; the silent fallback where no Embree library is found.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from test_bvh import RTOL, check_against_reference, ray_mix

from jaxrt.accel import bvh
from jaxrt.accel import traverse_cpu
from jaxrt.accel import traverse_embree


# Embree is an optional system library (Debian: libembree-dev). CI installs it (.ci/run), so there
# these tests must run and a missing or unbuildable Embree fails them; on a developer's machine
# without it they are skipped with the reason, and the CPU uses the native kernel instead.
if not os.environ.get("CI") and not traverse_embree.available():
    pytest.skip("Embree 3 is not installed (apt-get install libembree-dev); CI runs these tests",
                allow_module_level=True)


def test_embree_builds_here():
    # CI installs Embree (.ci/run): the CPU default must be what the suite exercises, not a fallback.
    assert traverse_embree.available()


def _arrays(tree):
    return {"node_box": tree.node_box, "node_leaf": tree.node_leaf, "links": tree.links, "triangles": tree.triangles}


def _embree(tree, o, d, lo, hi, **kw):
    return tuple(map(np.asarray, jax.jit(lambda tr, *r: traverse_embree.traverse(tr, *r, **kw))(
        tree.triangles, o, d, lo, hi)))


def _native(tree, o, d, lo, hi, **kw):
    return tuple(map(np.asarray, jax.jit(lambda a, *r: traverse_cpu.traverse(a, *r, **kw))(
        _arrays(tree), o, d, lo, hi)))


@pytest.mark.data
@pytest.mark.parametrize("leaf_size", [1, 4])
def test_matches_native_kernel(bunny, leaf_size):
    """Raw outputs of Embree and the native kernel on one tree: a different triangle only as a tie,
    t (refined in double by both) to RTOL, u, v to float32 rounding of the same barycentrics."""
    tree = bvh.build(bunny.vertices, bunny.faces, leaf_size=leaf_size)
    o, d, lo, hi = ray_mix(bunny, 6000, seed=11 + leaf_size)
    fe, te, be, ue, ve = _embree(tree, o, d, lo, hi, any_hit=False, refine=True)
    fn, tn, bn, un, vn = _native(tree, o, d, lo, hi, any_hit=False, refine=True)
    # A different answer (hit or miss, or another triangle) only where float32 rounding decides:
    # ties at the same distance, rays through an edge or grazing a triangle. Few, and each one
    # must pass the float64 brute-force rules of tests/test_bvh.py.
    differ = (fe != fn) | (fe & fn & (be != bn))
    assert differ.sum() <= 0.005 * len(o), int(differ.sum())
    tri = bunny.vertices.astype(np.float64)[bunny.faces]
    pid = np.asarray(tree.prim_ids)
    for f_, t_, b_, u_, v_ in ((fe, te, be, ue, ve), (fn, tn, bn, un, vn)):
        sub = bvh.Hit(t=np.where(f_, t_, np.inf)[differ], prim=np.where(f_, pid[np.maximum(b_, 0)], -1)[differ],
                      u=u_[differ], v=v_[differ])
        check_against_reference(tri, o[differ].astype(np.float64), d[differ].astype(np.float64),
                                lo[differ].astype(np.float64), hi[differ].astype(np.float64), sub)
    same = fe & fn & (be == bn)
    # the same triangle: t is the double-precision plane distance in both, rounded to float32
    assert np.mean(te[same] == tn[same]) > 0.99
    # (u, v) against float64 barycentrics of the ray's line through the triangle's plane
    # (Moller-Trumbore, written here independently): the kernel recomputes them in double, so they are
    # the float32 rounding of those (the native kernel's float32 quotients stray by up to ~1e-4);
    # rays nearly in the plane are checked across the ray in test_bvh.py
    tri = np.asarray(tree.triangles, np.float64)[be[same]]
    o64, d64 = o[same].astype(np.float64), d[same].astype(np.float64)
    e1, e2, s0 = tri[:, 3:6] - tri[:, 0:3], tri[:, 6:9] - tri[:, 0:3], o64 - tri[:, 0:3]
    p = np.cross(d64, e2)
    det = np.sum(e1 * p, 1)
    u64, v64 = np.sum(s0 * p, 1) / det, np.sum(d64 * np.cross(s0, e1), 1) / det
    nrm = np.cross(e1, e2)
    cos = np.abs(np.sum(nrm * d64, 1)) / (np.linalg.norm(nrm, axis=1) * np.linalg.norm(d64, axis=1))
    steep = cos > 0.05
    assert steep.mean() > 0.6
    err_e = np.maximum(np.abs(ue[same] - u64), np.abs(ve[same] - v64))[steep]
    err_n = np.maximum(np.abs(un[same] - u64), np.abs(vn[same] - v64))[steep]
    assert err_e.max() < 1e-6, err_e.max()
    assert np.median(err_e) < np.median(err_n)
    # misses: t = tmax, u = v = 0 (the native kernel's contract)
    np.testing.assert_array_equal(te[~fe], hi[~fe])
    assert np.all(ue[~fe] == 0) and np.all(ve[~fe] == 0) and np.all(be[~fe] == -1)
    # any-hit: blocked exactly where Embree's own closest-hit query finds a hit
    occ = _embree(tree, o, d, lo, hi, any_hit=True)[0]
    np.testing.assert_array_equal(occ, fe)
    # one ray at a time, incoherent, own threads: only the speed changes
    for kw in ({"packet": 1}, {"coherent": "no"}, {"coherent": "yes"}, {"threads": 3}):
        other = _embree(tree, o, d, lo, hi, any_hit=False, refine=True, **kw)
        np.testing.assert_array_equal(other[0], fe, err_msg=str(kw))
        np.testing.assert_array_equal(other[1], te, err_msg=str(kw))
    with pytest.raises(ValueError, match="packet"):
        traverse_embree.traverse(tree.triangles, o, d, lo, hi, any_hit=False, packet=8)


@pytest.mark.data
def test_points_are_the_float64_hit_points(bunny):
    """points=True: the same hits, plus each hit's point and unit geometric normal, computed in
    double in the kernel: against float64 (the ray's line through the triangle's plane, Moller-Trumbore
    written here; the normalised cross product of the float32 corners' edges), in every mode."""
    tree = bvh.build(bunny.vertices, bunny.faces)
    o, d, lo, hi = ray_mix(bunny, 3000, seed=3)
    ref = _embree(tree, o, d, lo, hi, any_hit=False, refine=True)
    out = _embree(tree, o, d, lo, hi, any_hit=False, refine=True, points=True)
    for a, b in zip(ref, out[:5]):
        np.testing.assert_array_equal(a, b)
    f, _, b, _, _, p, ng = out
    assert p.shape == ng.shape == (len(o), 3) and 0.3 < f.mean() < 0.95
    assert np.all(p[~f] == 0) and np.all(ng[~f] == 0)
    tri = np.asarray(tree.triangles, np.float64)[b[f]]
    o64, d64 = o[f].astype(np.float64), d[f].astype(np.float64)
    e1, e2, s0 = tri[:, 3:6] - tri[:, 0:3], tri[:, 6:9] - tri[:, 0:3], o64 - tri[:, 0:3]
    q = np.cross(d64, e2)
    det = np.sum(e1 * q, 1)
    u64, v64 = np.sum(s0 * q, 1) / det, np.sum(d64 * np.cross(s0, e1), 1) / det
    p64 = tri[:, 0:3] + u64[:, None] * e1 + v64[:, None] * e2
    n64 = np.cross(e1, e2)
    n64 /= np.linalg.norm(n64, axis=1, keepdims=True)
    cos = np.abs(np.sum(n64 * d64, 1)) / np.linalg.norm(d64, axis=1)
    steep = cos > 0.05  # nearly parallel rays: the plane's point is ill-conditioned, the kernel clamps
    assert steep.mean() > 0.6
    scale = np.abs(bunny.vertices).max()
    err = np.abs(p[f] - p64).max(1)[steep]
    assert err.max() <= 2.0**-23 * scale, err.max() / scale  # rounded once: within an ulp
    assert np.abs(ng[f] - n64).max() <= 2.0**-24 * 2, np.abs(ng[f] - n64).max()
    # every hit point lies in its triangle's plane to float32 rounding, grazing rays included
    off = np.abs(np.sum((p[f] - tri[:, 0:3]) * n64, 1))
    assert off.max() <= 2.0**-22 * scale, off.max() / scale
    for kw in ({"packet": 1}, {"coherent": "no"}, {"coherent": "yes"}, {"threads": 3}):
        other = _embree(tree, o, d, lo, hi, any_hit=False, refine=True, points=True, **kw)
        np.testing.assert_array_equal(other[5], p, err_msg=str(kw))
        np.testing.assert_array_equal(other[6], ng, err_msg=str(kw))
    with pytest.raises(ValueError, match="points"):
        traverse_embree.traverse(tree.triangles, o, d, lo, hi, any_hit=True, points=True)


def test_t_limits_are_inclusive_and_inactive_rays_miss():
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    tree = bvh.build(v, f)
    xy = np.array([[0.3, -0.2], [-0.5, 0.4], [0.0, 0.0], [0.9, -0.9], [1.0, 1.0]], np.float32)
    o = np.concatenate([xy, np.ones((len(xy), 1), np.float32)], axis=1)
    d = np.tile(np.float32([0, 0, -1]), (len(o), 1))
    # The plane is at t = 1 exactly. Embree decides the ends of [tmin, tmax] with its own rounded t, so
    # a hit within a few ulps outside the interval may count (the native kernel's are exact ends):
    # checked at exactly the ends and 1e-5 outside them.
    below, above = np.float32(1 - 1e-5), np.float32(1 + 1e-5)
    cases = [(0.0, np.inf, True), (0.0, 1.0, True), (1.0, 1.0, True), (1.0, np.inf, True), (0.0, below, False),
             (above, np.inf, False), (1.0, 0.5, False), (np.nan, np.inf, False), (0.0, np.nan, False)]
    for lo, hi, expect in cases:
        hit = bvh.intersect(tree, o, d, lo, hi, impl="embree")
        occ = bvh.occluded(tree, o, d, hi, lo, impl="embree")
        prim = np.asarray(hit.prim)
        np.testing.assert_array_equal(prim >= 0, expect, err_msg=f"tmin {lo} tmax {hi}")
        np.testing.assert_array_equal(np.asarray(occ), expect, err_msg=f"tmin {lo} tmax {hi}")
        if expect:
            np.testing.assert_array_equal(np.asarray(hit.t), 1.0)
            p = np.asarray(hit.u)[:, None] * (v[f[prim, 1]] - v[f[prim, 0]]) + np.asarray(hit.v)[:, None] * (
                v[f[prim, 2]] - v[f[prim, 0]]) + v[f[prim, 0]]
            np.testing.assert_allclose(p[:, :2], xy, atol=1e-6)
    # NaN origins or directions and zero directions miss without being traced
    bad_o = o.copy()
    bad_o[0, 1] = np.nan
    bad_d = d.copy()
    bad_d[1] = np.nan
    bad_d[2] = 0.0
    hit = bvh.intersect(tree, bad_o, bad_d, impl="embree")
    np.testing.assert_array_equal(np.asarray(hit.prim) >= 0, [False, False, False, True, True])
    assert np.all(np.isfinite(np.asarray(hit.u))) and np.all(np.isfinite(np.asarray(hit.v)))


def test_a_changed_triangle_table_is_not_traced_through_the_old_scene():
    """The kernel keeps Embree scenes keyed by the table's bytes: moving one vertex (same triangle
    count, maybe the same buffer address) must give the moved mesh's hits."""
    s = trimesh.creation.icosphere(subdivisions=3)
    tree = bvh.build(s.vertices, s.faces)
    o = np.float32([[0, 0, 5], [0, 0, -5]])
    d = np.float32([[0, 0, -1], [0, 0, 1]])
    f = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, impl="embree"))
    t0 = np.asarray(f(tree, o, d).t)
    np.testing.assert_allclose(t0, 4.0, rtol=1e-3)  # the unit sphere, polygonised
    tri = np.asarray(tree.triangles).copy()
    tri[:, 2::3] *= 2.0  # stretch z: the sphere's poles move to +-2
    moved = bvh.BVH(**{**{k: getattr(tree, k) for k in ("node_box", "node_leaf", "links", "prim_ids", "rows",
                                                        "skips", "leaf_size")}, "triangles": jnp.asarray(tri)})
    np.testing.assert_allclose(np.asarray(f(moved, o, d).t), 3.0, rtol=1e-3)
    np.testing.assert_array_equal(np.asarray(f(tree, o, d).t), t0)  # and back


def test_a_change_in_the_last_piece_of_a_large_table_is_seen():
    """Tables over 4 MB are hashed in pieces (by several threads): a change confined to the last
    triangle of a 327,680-triangle table (11.8 MB, three pieces) must still select a new scene."""
    s = trimesh.creation.icosphere(subdivisions=7)
    tree = bvh.build(s.vertices, s.faces)
    tri = np.asarray(tree.triangles).copy()
    assert tri.nbytes > 2 * (4 << 20)
    c = tri[-1].reshape(3, 3).mean(0)
    c /= np.linalg.norm(c)
    o, d = np.float32(5 * c)[None], np.float32(-c)[None]
    f = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, impl="embree"))
    np.testing.assert_allclose(np.asarray(f(tree, o, d).t), 4.0, atol=1e-3)
    tri[-1] *= 0.5  # the last triangle moves halfway to the centre: the ray passes its hole and meets it there
    moved = eqx.tree_at(lambda t: t.triangles, tree, jnp.asarray(tri))
    hit = f(moved, o, d)
    np.testing.assert_allclose(np.asarray(hit.t), 4.5, atol=1e-3)
    assert int(hit.prim[0]) == int(np.asarray(tree.prim_ids)[-1])


def test_keyed_calls_follow_an_edit_of_the_table():
    """A key made inside the program from the table it traces (`bvh.with_table_key`) follows an
    `eqx.tree_at` edit of the triangles made before the call (a build-time key would not): the
    stretched sphere's hits, same compiled program; and keyed hits equal the per-call-hash ones."""
    s = trimesh.creation.icosphere(subdivisions=3)
    tree = bvh.build(s.vertices, s.faces)
    o = np.float32([[0.11, 0.07, 5], [-0.13, 0.05, -5], [0.3, 0.2, 5]])  # off the poles' vertices
    d = np.float32([[0, 0, -1], [0, 0, 1], [0, 0, -1]])

    def hits(tr, o, d):
        keyed = bvh.with_table_key(tr, impl="embree")
        assert keyed.table_key is not None
        h = bvh.intersect(keyed, o, d, impl="embree")
        return h, bvh.occluded(keyed, o, d, 4.4, impl="embree"), bvh.intersect(tr, o, d, impl="embree")

    f = jax.jit(hits)
    h0, occ0, plain0 = f(tree, o, d)
    np.testing.assert_allclose(np.asarray(h0.t)[:2], 4.0, rtol=1e-2)  # the unit sphere, polygonised
    np.testing.assert_array_equal(np.asarray(occ0), True)
    for a, b in zip(h0, plain0, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    tri = np.asarray(tree.triangles).copy()
    tri[:, 2::3] *= 2.0  # stretch z: the poles move to +-2
    moved = eqx.tree_at(lambda t: t.triangles, tree, jnp.asarray(tri))
    h1, occ1, plain1 = f(moved, o, d)
    np.testing.assert_allclose(np.asarray(h1.t)[:2], 3.0, rtol=1e-2)
    np.testing.assert_array_equal(np.asarray(occ1), True)
    for a, b in zip(h1, plain1, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the same against jaxrt's own XLA traversal of the moved table (independent of Embree)
    ref = bvh.intersect(moved, o, d, impl="xla")
    np.testing.assert_array_equal(np.asarray(h1.prim), np.asarray(ref.prim))
    np.testing.assert_allclose(np.asarray(h1.t), np.asarray(ref.t), rtol=1e-6)
    assert f._cache_size() == 1


def test_a_key_of_another_table_is_caught():
    """A keyed call whose key belongs to another table (a keyed tree edited afterwards) finds that
    the scene's corners differ from its table in the spot check and hashes the table instead."""
    s = trimesh.creation.icosphere(subdivisions=3)
    tree = bvh.build(s.vertices, s.faces)
    o, d = np.float32([[0, 0, 5]]), np.float32([[0, 0, -1]])
    lo, hi = np.zeros(1, np.float32), np.full(1, np.inf, np.float32)
    stale = traverse_embree.table_key(tree.triangles)
    tri = np.asarray(tree.triangles).copy()
    tri[:, 2::3] *= 2.0
    found, t, *_ = traverse_embree.traverse(jnp.asarray(tri), o, d, lo, hi, any_hit=False, refine=True, key=stale)
    assert bool(found[0])
    np.testing.assert_allclose(np.asarray(t), 3.0, rtol=1e-3)


@pytest.mark.data
def test_direct_frame_equals_native_kernel_frame(data_dir, monkeypatch):
    """The shipped bunny scene rendered with Embree and with the native kernel: the same image up to
    the few pixels whose camera or shadow ray meets a tie or an edge differently."""
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    import jaxrt

    images = {}
    for impl in ("embree", "cpu"):
        monkeypatch.setenv("JAXRT_TRAVERSAL", impl)
        scn = jaxrt.load_scene("bunny", overrides={"camera.width": 96, "camera.height": 72})
        images[impl] = np.asarray(jaxrt.render(scn))
    a, b = images["embree"], images["cpu"]
    assert np.all(np.isfinite(a))
    differ = np.any(np.abs(a - b) > 2e-5, axis=-1)
    assert differ.mean() < 0.002, f"{int(differ.sum())} pixels differ"
    assert abs(a.mean() - b.mean()) < 1e-4 * b.mean()


def test_zero_rays_jit_and_vmap():
    s = trimesh.creation.icosphere(subdivisions=2)
    tree = bvh.build(s.vertices, s.faces)
    z = jnp.zeros((0, 3), jnp.float32)
    assert bvh.intersect(tree, z, z, impl="embree").prim.shape == (0,)
    rng = np.random.default_rng(0)
    o = np.float32(rng.normal(size=(3, 5, 3)) * 4)
    d = np.float32(-o + rng.normal(size=(3, 5, 3)) * 0.1)
    f = jax.jit(jax.vmap(lambda o, d: bvh.intersect(tree, o, d, impl="embree")))
    hit = f(o, d)
    for b in range(3):
        one = bvh.intersect(tree, o[b], d[b], impl="cpu")
        np.testing.assert_array_equal(np.asarray(hit.prim[b]) >= 0, np.asarray(one.prim) >= 0)
        np.testing.assert_allclose(np.asarray(hit.t[b]), np.asarray(one.t), rtol=RTOL)


def test_silent_fallback_without_embree(monkeypatch):
    """No Embree library: "auto" traces with the native kernel without a word, "embree" (asked for by
    name) with one warning per process."""
    import warnings

    s = trimesh.creation.icosphere(subdivisions=2)
    tree = bvh.build(s.vertices, s.faces)
    o = np.float32([[0, 0, 5], [3, 3, 3]])
    d = np.float32([[0, 0, -1], [1, 0, 0]])
    monkeypatch.setattr(traverse_embree, "_library", "jaxrt-no-such-library")
    traverse_embree._reset_for_tests()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert not traverse_embree.available()
            hit = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, impl="auto"))(tree, o, d)
            text = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, impl="auto")).lower(tree, o, d).as_text()
        np.testing.assert_array_equal(np.asarray(hit.prim) >= 0, [True, False])
        assert traverse_cpu.TARGET in text and traverse_embree.TARGET not in text
        with pytest.warns(RuntimeWarning, match="no Embree 3 library") as caught:
            for _ in range(2):
                text = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, impl="embree")).lower(tree, o, d).as_text()
        assert len([w for w in caught if "Embree" in str(w.message)]) == 1
        assert traverse_cpu.TARGET in text and traverse_embree.TARGET not in text
        with pytest.raises(RuntimeError, match="not available"):
            traverse_embree.traverse(tree.triangles, o, d, jnp.zeros(2), jnp.full(2, jnp.inf), any_hit=False)
    finally:
        monkeypatch.undo()
        traverse_embree._reset_for_tests()
    assert traverse_embree.available()


def _segments_reference(tree, o, d, tmin, tmax, lights):
    """The Whitted loop's shadow segments of the closest hits (made in JAX from `intersect_points`'
    p and ng, `whitted.shadow_segments`) and their blocked flags from jaxrt's own XLA traversal
    (`occluded(from_end=True, impl="xla")`): (hit, p, ng, lit, org, dirs, smax, occ)."""
    from jaxrt.integrators.whitted import shadow_segments
    from jaxrt.lights import PointLights
    from jaxrt.shading.surface import dot, offset_scale

    @jax.jit
    def f(tree, o, d, lo, hi, lights):
        hit, p, ng = bvh.intersect_points(tree, o, d, lo, hi, impl="embree")
        ngo = jnp.where((dot(d, ng) > 0)[:, None], -ng, ng)
        wi, _, so, smax = shadow_segments(PointLights(lights, jnp.ones_like(lights)), p, ngo, offset_scale(p))
        lit = (hit.prim >= 0)[:, None] & (dot(wi, ngo[:, None, :]) > 0)
        smax = jnp.where(lit, smax, -1.0)
        n, nl = smax.shape
        occ = bvh.occluded(tree, so.reshape(-1, 3), wi.reshape(-1, 3), smax.reshape(-1), from_end=True, impl="xla")
        org = so + smax[..., None] * wi  # the segment from its light end, as from_end traces it
        return hit, p, ng, lit, org, -wi, smax, occ.reshape(n, nl)

    return tuple(jax.tree.map(np.asarray, f(tree, o, d, tmin, tmax, lights)))


@pytest.mark.data
def test_direct_call_traces_the_whitted_shadow_segments(bunny):
    """`bvh.intersect_points_shadowed` (Embree's closest hits and their shadow rays in one call):
    the hits are `intersect_points`' exactly; the blocked flags are those of the same segments made
    in JAX and traced by jaxrt's XLA traversal (up to rays that meet an edge or vertex, where the two
    watertight tests may differ), and agree with float64 brute force wherever the verdict is clear."""
    from test_bvh import brute_force

    tree = bvh.build(bunny.vertices, bunny.faces)
    o, d, tmin, tmax = ray_mix(bunny, 3000, seed=7)
    lo, hi = np.float32(tmin), np.float32(tmax)
    v = np.asarray(bunny.vertices, np.float64)
    c, r = (v.min(0) + v.max(0)) / 2, np.ptp(v, axis=0).max()
    # one light far above, one just outside the mesh, one inside its bounding box
    lights = np.float32([c + [0.3 * r, 3 * r, 0.5 * r], c + [0.7 * r, 0.1 * r, 0.0], c + [0.0, -0.05 * r, 0.02 * r]])
    hit, p, ng, occ = jax.tree.map(np.asarray, jax.jit(bvh.intersect_points_shadowed)(tree, o, d, lo, hi, lights))
    rhit, rp, rng_, lit, org, dirs, smax, rocc = _segments_reference(tree, o, d, lo, hi, lights)
    for a, b in ((hit.prim, rhit.prim), (hit.t, rhit.t), (hit.u, rhit.u), (hit.v, rhit.v), (p, rp), (ng, rng_)):
        np.testing.assert_array_equal(a, b)
    assert occ.shape == (len(o), 3) and occ.dtype == bool
    assert lit.sum() > 1500 and 0.1 < rocc[lit].mean() < 0.9  # both verdicts well represented
    assert not np.any(occ & ~lit), "a segment that is not lit was traced"
    differ = (occ != rocc) & lit
    assert differ.sum() <= 0.002 * lit.sum(), f"{int(differ.sum())} of {int(lit.sum())} segments differ"
    # float64 brute force on a sample of lit segments: blocked where a triangle's interior meets the
    # segment's interior, open where nothing comes near it; the kernel must agree on those
    i, j = np.nonzero(lit)
    pick = np.random.default_rng(0).choice(len(i), 400, replace=False)
    i, j = i[pick], j[pick]
    so, sd, sm = org[i, j].astype(np.float64), dirs[i, j].astype(np.float64), smax[i, j].astype(np.float64)
    tri = np.asarray(tree.triangles, np.float64).reshape(-1, 3, 3)
    strict = brute_force(tri, so, sd, sm * 1e-5, sm * (1 - 1e-5), slack=-1e-5)[1] >= 0
    loose = brute_force(tri, so, sd, -1e-5 * sm, sm * (1 + 1e-5), slack=1e-5)[1] >= 0
    assert strict.sum() > 50 and (~loose).sum() > 50
    np.testing.assert_array_equal(occ[i, j][strict], True)
    np.testing.assert_array_equal(occ[i, j][~loose], False)


@pytest.mark.data
@pytest.mark.parametrize("name", [pytest.param("bunny", marks=pytest.mark.slow), "spheres"])
def test_frames_with_shadows_in_the_traversal_equal_the_separate_shadow_rays(name, data_dir, monkeypatch):
    """Whitted frames whose shadow rays Embree traces with the hits (`shadows_in_traversal`) against
    the same program with them traced by `occluded`: the same image up to float rounding (the
    segments are made with the same float32 operations; a few grazing rays may go the other way). The
    spheres (mirrors, glass with opaque shadows, depth 5, a second light) trace every level so."""
    import tomllib

    import jaxrt
    from jaxrt import scene as S
    from jaxrt.geometry.triangles import TriangleGeometry
    from jaxrt.integrators import whitted

    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    doc = tomllib.loads(S.find_scene(name).read_text())
    doc["render"]["glass_shadows"] = "opaque"
    doc["lights"].append({"position": [-2.0, 3.0, 1.0], "intensity": [20.0, 15.0, 10.0]})
    scn = S.load(doc, base_dir=S.find_scene(name).parent, overrides={"camera.width": 96, "camera.height": 72})
    assert scn.geometry.shadows_in_traversal() and not whitted.transmits(scn)
    f = jax.jit(whitted.whitted)
    text = f.lower(scn).as_text()
    assert traverse_embree.DIRECT_TARGET in text
    assert "any_hit = true" not in text  # no separate shadow-ray call
    img = np.asarray(f(scn))
    monkeypatch.setattr(TriangleGeometry, "shadows_in_traversal", lambda self: False)
    g = jax.jit(lambda s: whitted.whitted(s))  # a new function: traced again
    assert traverse_embree.DIRECT_TARGET not in g.lower(scn).as_text()
    ref = np.asarray(g(scn))
    assert np.all(np.isfinite(img)) and ref.mean() > 0
    differ = np.any(np.abs(img - ref) > 2e-5, axis=-1)
    assert differ.mean() < 0.002, f"{int(differ.sum())} pixels differ"
    assert abs(img.mean() - ref.mean()) < 1e-5 * ref.mean()
    np.testing.assert_allclose(np.asarray(jaxrt.render(scn)), img, rtol=0, atol=1e-6)


def test_without_embree_the_frame_traces_shadow_rays_separately(monkeypatch):
    """No Embree library: the geometry reports no shadows in the traversal and the Whitted program
    traces them with the native kernel's any-hit call."""
    from jaxrt import scene as S
    from jaxrt.integrators import whitted

    scn = S.load("spheres", overrides={"camera.width": 16, "camera.height": 12, "render.max_depth": 1})
    monkeypatch.setattr(traverse_embree, "_library", "jaxrt-no-such-library")
    traverse_embree._reset_for_tests()
    try:
        assert not scn.geometry.shadows_in_traversal()
        text = jax.jit(whitted.whitted).lower(scn).as_text()
        assert traverse_embree.DIRECT_TARGET not in text and traverse_cpu.TARGET in text
        assert np.all(np.isfinite(np.asarray(jax.jit(whitted.whitted)(scn))))
    finally:
        monkeypatch.undo()
        traverse_embree._reset_for_tests()
        assert traverse_embree.available()
