"""`geometry.intersect_surface`: the hit and its surface in one call, for passes that are not
differentiated. `TriangleGeometry` builds the surface from the traversal's own hit points and
geometric normals (`jaxrt.accel.intersect_points`); checked against the differentiable
`surface(prim, u, v)` that the renderer used before, on every CPU traversal, and the instanced
geometry's default (intersect, then surface) against its own pieces."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import camera
from jaxrt import scene as S

REPO = Path(__file__).resolve().parents[2]
SMALL = {"camera.width": 64, "camera.height": 48}


def _rays(scn):
    o, d = camera.generate_rays(scn.camera, 1, 0)
    return o, d / jnp.linalg.norm(d, axis=-1, keepdims=True)


@pytest.mark.parametrize("impl", ["embree", "cpu", "xla"])
def test_surface_from_the_traversal_is_the_surface_of_the_hit(monkeypatch, impl):
    monkeypatch.setenv("JAXRT_TRAVERSAL", impl)
    scn = S.load(REPO / "scenes" / "spheres.toml", overrides=SMALL)
    geo = scn.geometry
    o, d = _rays(scn)
    hit, s = jax.jit(lambda g, o, d: g.intersect_surface(o, d))(geo, o, d)
    ref_hit = jax.jit(lambda g, o, d: g.intersect(o, d))(geo, o, d)
    for a, b in zip(hit, ref_hit):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ref = jax.jit(lambda g, h: g.surface(h.prim, h.u, h.v))(geo, hit)
    found = np.asarray(hit.prim) >= 0
    assert 0.2 < found.mean() < 1.0
    scale = float(np.abs(np.asarray(geo.vertices)).max())
    tol = {"p": 4 * 2.0**-24 * scale, "ng": 4 * 2.0**-24, "ns": 8 * 2.0**-24, "tangent": 0.0, "uv": 0.0}
    for name, t in tol.items():
        a, b = np.asarray(getattr(s, name))[found], np.asarray(getattr(ref, name))[found]
        assert np.abs(a - b).max() <= t, (name, np.abs(a - b).max())
    np.testing.assert_array_equal(np.asarray(s.material)[found], np.asarray(ref.material)[found])


@pytest.mark.slow  # 20 s on 2 cores
def test_instanced_default_is_intersect_then_surface():
    scn = S.load(REPO / "scenes" / "instances.toml", overrides=SMALL)
    geo = scn.geometry
    o, d = _rays(scn)
    hit, s = jax.jit(lambda g, o, d: g.intersect_surface(o, d))(geo, o, d)
    ref_hit = jax.jit(lambda g, o, d: g.intersect(o, d))(geo, o, d)
    ref = jax.jit(lambda g, h: g.surface(h.prim, h.u, h.v))(geo, ref_hit)
    assert (np.asarray(hit.prim) >= 0).mean() > 0.2
    for a, b in zip(jax.tree.leaves((hit, s)), jax.tree.leaves((ref_hit, ref))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
