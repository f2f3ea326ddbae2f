"""Lobe flags, the diffuse-albedo hook and the delta model's `Dielectric` record, registry-wide:
each model's declared flags must agree with what its functions do."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfs
from brdfs import Lobe
from brdfs.base import Dielectric, Model, Param

NAMES = brdfs.names()
# The parameter `diffuse_albedo` returns for each Lobe.DIFFUSE model.
COLOUR = {"disney": "base_color"}


def _hemi(rng, n, lo=0.05):
    ct = rng.uniform(lo, 1, n)
    ph = rng.uniform(0, 2 * math.pi, n)
    st = np.sqrt(1 - ct**2)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).astype(np.float32)


@pytest.mark.parametrize("name", NAMES)
def test_flags_are_consistent_with_the_record(name):
    m = brdfs.get(name)
    f = m.flags
    assert isinstance(f, Lobe)
    assert f & (Lobe.REFLECTION | Lobe.TRANSMISSION)
    # delta iff there is no eval iff the Dielectric record is there
    assert m.delta == (Lobe.DELTA in f) == (m.eval is None) == (m.dielectric is not None)
    if m.delta:
        assert not f & (Lobe.DIFFUSE | Lobe.GLOSSY) and m.mixture == ()
        assert m.sample is not None and m.pdf is not None
    else:
        assert f & (Lobe.DIFFUSE | Lobe.GLOSSY)
        assert Lobe.TRANSMISSION not in f  # every non-delta model here is a BRDF
        assert len(m.mixture) >= 1 and all(isinstance(c, brdfs.Component) for c in m.mixture)
    assert (m.diffuse is not None) == (Lobe.DIFFUSE in f)


@pytest.mark.parametrize("name", [n for n in NAMES if not brdfs.get(n).delta])
def test_flags_match_the_brdf(name):
    """REFLECTION only: zero for wi below the horizon, and samples stay above it. GLOSSY: the BRDF
    varies with direction; not GLOSSY (Lambert): constant. DIFFUSE: raising the diffuse colour raises
    f for every direction pair. The mixture probabilities sum to 1."""
    m = brdfs.get(name)
    p = m.params()
    rng = np.random.default_rng(3)
    wo = _hemi(rng, 512)
    wi = _hemi(rng, 512)
    wi[:128] = wo[:128] * np.array([-1, -1, 1], np.float32)  # mirror pairs: where glossy lobes peak
    f = np.asarray(m.eval(p, jnp.asarray(wi), jnp.asarray(wo)))
    assert np.all(np.isfinite(f)) and np.all(f >= 0) and np.any(f > 0)
    below = wi * np.array([1, 1, -1], np.float32)
    assert np.all(np.asarray(m.eval(p, jnp.asarray(below), jnp.asarray(wo))) == 0)
    u = np.asarray(jax.random.uniform(jax.random.PRNGKey(0), (512, 2)))
    ws, _, pdf = m.sample(p, jnp.asarray(wo), jnp.asarray(u))
    assert np.all(np.asarray(ws)[np.asarray(pdf) > 0, 2] > 0)
    spread = f.mean(-1).max() / f.mean(-1).min()
    if Lobe.GLOSSY in m.flags:
        assert spread > 1.5, spread
    else:
        assert spread < 1 + 1e-5, spread
    if Lobe.DIFFUSE in m.flags:
        key = COLOUR.get(name, "rho_d")
        lo = np.asarray(m.eval({**p, key: jnp.full(3, 0.1)}, jnp.asarray(wi), jnp.asarray(wo)))
        hi = np.asarray(m.eval({**p, key: jnp.full(3, 0.9)}, jnp.asarray(wi), jnp.asarray(wo)))
        assert np.all(hi > lo)
    total = sum(c.prob(p, jnp.asarray(wo)) for c in m.mixture)
    np.testing.assert_allclose(np.asarray(total), 1.0, rtol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_diffuse_albedo_shape_and_value(name):
    m = brdfs.get(name)
    p = m.params()
    a = np.asarray(m.diffuse_albedo(p))
    assert a.shape == (3,)
    if m.delta:
        np.testing.assert_array_equal(a, 1.0)
    else:
        assert Lobe.DIFFUSE in m.flags  # every opaque model here has a diffuse lobe
        np.testing.assert_array_equal(a, np.asarray(p[COLOUR.get(name, "rho_d")]))
        assert np.all(a > 0)  # non-zero at the defaults
    # per-pixel (H, W) parameters give (H, W, 3), under jit as well
    rng = np.random.default_rng(0)
    rows = [m.params(**{s.name: (rng.uniform(0, 1, 3) if s.rgb else s.default) for s in m.spec}) for _ in range(6)]
    st = m.stack(rows)
    st = {k: v.reshape((2, 3) + v.shape[1:]) for k, v in st.items()}
    b = np.asarray(jax.jit(m.diffuse_albedo)(st))
    assert b.shape == (2, 3, 3)
    if not m.delta:
        np.testing.assert_array_equal(b, np.asarray(st[COLOUR.get(name, "rho_d")]))


def test_model_without_a_diffuse_lobe_reports_black_and_bad_flags_are_refused():
    lam = brdfs.get("lambert")
    glossy = dataclasses.replace(lam, name="glossy_only", flags=Lobe.REFLECTION | Lobe.GLOSSY, diffuse=None)
    np.testing.assert_array_equal(np.asarray(glossy.diffuse_albedo(glossy.params())), 0.0)
    spec = (Param("x", 0.5, 0.0, 1.0),)
    ev = lam.eval
    with pytest.raises(ValueError, match="DELTA model has no eval"):
        Model("bad", spec, ev, None, None, flags=Lobe.REFLECTION | Lobe.DELTA)
    with pytest.raises(ValueError, match="needs eval"):
        Model("bad", spec, None, None, None, flags=Lobe.REFLECTION | Lobe.GLOSSY)
    with pytest.raises(ValueError, match="needs a `diffuse`"):
        Model("bad", spec, ev, None, None, flags=Lobe.REFLECTION | Lobe.DIFFUSE)
    with pytest.raises(ValueError, match="REFLECTION and/or TRANSMISSION"):
        Model("bad", spec, ev, None, None, flags=Lobe.GLOSSY)
    with pytest.raises(ValueError, match="no DIFFUSE or GLOSSY"):
        Model("bad", spec, None, None, None, flags=Lobe.REFLECTION | Lobe.GLOSSY | Lobe.DELTA)


def test_glass_dielectric_record_and_split():
    g = brdfs.get("glass")
    assert isinstance(g.dielectric, Dielectric)
    assert g.flags == Lobe.REFLECTION | Lobe.TRANSMISSION | Lobe.DELTA
    p = g.params(n_t=1.5)
    rng = np.random.default_rng(2)
    wo = _hemi(rng, 400, lo=0.01)
    wo[200:, 2] *= -1  # inside the glass: total internal reflection beyond 41.8 deg
    r, wr, wt, tr = (np.asarray(a) for a in g.dielectric.split(p, jnp.asarray(wo)))
    entering = wo[:, 2] > 0
    np.testing.assert_array_equal(r, np.asarray(g.dielectric.fresnel(p, jnp.abs(wo[:, 2]), jnp.asarray(entering))))
    np.testing.assert_array_equal(wr, wo * np.array([-1, -1, 1], np.float32))
    wt_ref, ok = (np.asarray(a) for a in g.dielectric.refract(p, jnp.asarray(wo)))
    np.testing.assert_array_equal(wt, wt_ref)
    sin_inside = np.linalg.norm(wo[:, :2], axis=-1)
    tir = ~entering & (1.5 * sin_inside > 1)
    assert tir.sum() > 20
    np.testing.assert_array_equal(tr, ~tir & (r < 1))
    assert np.all(r[tir] == 1) and np.all(r[~tir] < 1)
    # TRANSMISSION: some samples cross the interface; REFLECTION: some stay on wo's side
    u = np.asarray(jax.random.uniform(jax.random.PRNGKey(1), (400, 2)))
    wi, _, _ = g.sample(p, jnp.asarray(wo), jnp.asarray(u))
    same = np.sign(np.asarray(wi)[:, 2]) == np.sign(wo[:, 2])
    assert same.any() and (~same).any()
