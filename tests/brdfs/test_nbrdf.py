"""Neural BRDFs (brdfs.nbrdf) and the half/difference transform (brdfs.halfdiff).

References used here, independent of the code under test: a float64 numpy Rusinkiewicz transform
built from Rodrigues rotations (as Rusinkiewicz 1998 defines it), its closed-form properties, the
wi_z formula of Sztrajman et al.'s training loss, and a float64 numpy forward pass of the MLP.
"""

from __future__ import annotations

import io
import math
import zipfile

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfs
from brdfs import halfdiff, measured, nbrdf
from jaxrt.errors import InputError

M = nbrdf.MODEL


# ---- float64 numpy references -------------------------------------------------------------------

def _rotate(v, axis, angle):
    """Rodrigues: v rotated right-handedly by `angle` about the unit `axis` (rows of v)."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return v * c + axis * np.sum(axis * v, -1, keepdims=True) * (1 - c) + np.cross(axis, v) * s


def ref_half_diff(wi, wo):
    """(θh, φh, d) by Rusinkiewicz's definition: h = normalize(wi + wo), d = R_y(-θh) R_z(-φh) wi."""
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    th = np.arccos(np.clip(h[..., 2], -1, 1))
    ph = np.arctan2(h[..., 1], h[..., 0])
    z, y = np.array([0.0, 0, 1]), np.array([0.0, 1, 0])
    d = _rotate(_rotate(wi, z, -ph), y, -th)
    return th, ph, d


def ref_mlp(w, x):
    """Float64 forward pass x (..., 6) -> max(exp(z) - 1, 0) with ReLU hidden layers."""
    w = {k: np.asarray(v, np.float64) for k, v in w.items()}
    a = np.maximum(x @ w["W1"] + w["b1"], 0)
    a = np.maximum(a @ w["W2"] + w["b2"], 0)
    return np.maximum(np.expm1(a @ w["W3"] + w["b3"]), 0)


def rand_dirs(rng, n, max_deg=89.0):
    c = rng.uniform(math.cos(math.radians(max_deg)), 1.0, n)
    ph = rng.uniform(0, 2 * math.pi, n)
    s = np.sqrt(1 - c * c)
    return np.stack([s * np.cos(ph), s * np.sin(ph), c], -1)


def random_weights(seed=0, scale=0.4):
    rng = np.random.default_rng(seed)
    return {k: (scale * rng.standard_normal(s)).astype(np.float32) for k, _, s in nbrdf.LAYOUT}


def write_h5(path, weights, layout=nbrdf.LAYOUT, extra=None):
    with h5py.File(path, "w") as f:
        for k, ds, _ in layout:
            f.create_dataset(ds, data=weights[k])
        for ds, arr in (extra or {}).items():
            f.create_dataset(ds, data=arr)


# ---- the transform --------------------------------------------------------------------------------

def test_half_diff_matches_rodrigues_reference_and_closed_forms():
    rng = np.random.default_rng(1)
    wi, wo = rand_dirs(rng, 5000), rand_dirs(rng, 5000)
    th, ph, d = ref_half_diff(wi, wo)
    with jax.enable_x64(True):
        s, c, dj = (np.asarray(a) for a in halfdiff.half_diff(jnp.asarray(wi), jnp.asarray(wo)))
        thj, tdj, pdj = (np.asarray(a) for a in halfdiff.angles(jnp.asarray(wi), jnp.asarray(wo)))
    np.testing.assert_allclose(dj, d, atol=1e-12)
    np.testing.assert_allclose(s, np.sin(th), atol=1e-12)
    np.testing.assert_allclose(c, np.cos(th), atol=1e-12)
    # closed forms: |d| = 1, cos θd = wi·h = wo·h, d lies on the far side of the pole from wo's image
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-12)
    np.testing.assert_allclose(d[:, 2], np.sum(wi * h, -1), atol=1e-12)
    np.testing.assert_allclose(np.cos(tdj), np.sum(wo * h, -1), atol=1e-12)
    np.testing.assert_allclose(thj, th, atol=1e-9)
    # the training loss of Sztrajman et al. recovers wi_z = cosθd cosθh - sinθd cosφd sinθh from x
    np.testing.assert_allclose(np.cos(tdj) * np.cos(thj) - np.sin(tdj) * np.cos(pdj) * np.sin(thj), wi[:, 2],
                               atol=1e-12)
    # reciprocity: swapping wi and wo keeps θh, θd and maps φd -> φd + π
    with jax.enable_x64(True):
        th2, td2, pd2 = (np.asarray(a) for a in halfdiff.angles(jnp.asarray(wo), jnp.asarray(wi)))
    np.testing.assert_allclose(th2, thj, atol=1e-12)
    np.testing.assert_allclose(td2, tdj, atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (pd2 - pdj - math.pi))), 0, atol=1e-9)
    # the inverse map recovers the directions (given the true φh)
    wi2, wo2 = halfdiff.directions(thj, tdj, pdj, ph, xp=np)
    np.testing.assert_allclose(wi2, wi, atol=1e-12)
    np.testing.assert_allclose(wo2, wo, atol=1e-12)


def test_encoding_and_network_against_numpy_forward_pass():
    w = random_weights()
    p = {k: jnp.asarray(v) for k, v in w.items()}
    rng = np.random.default_rng(2)
    wi, wo = rand_dirs(rng, 3000), rand_dirs(rng, 3000)
    th, _, d = ref_half_diff(wi, wo)
    x = np.concatenate([np.stack([np.sin(th), 0 * th, np.cos(th)], -1), d], -1)
    np.testing.assert_allclose(np.asarray(nbrdf.encode(jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32))),
                               x, atol=2e-6)
    f = np.asarray(M.eval(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)))
    np.testing.assert_allclose(f, ref_mlp(w, x), rtol=2e-4, atol=1e-6)
    # wi = wo = normal: x = (0, 0, 1, 0, 0, 1) exactly
    n = jnp.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(np.asarray(M.eval(p, n, n)), ref_mlp(w, np.array([0, 0, 1, 0, 0, 1.0])), rtol=1e-5)


def test_zero_below_horizon_and_finite_at_degenerate_directions():
    p = {k: jnp.asarray(v) for k, v in random_weights(3).items()}
    n = np.array([0, 0, 1.0])
    g = np.array([1.0, 0, 0])  # grazing
    b = np.array([0.3, 0.1, -0.9]) / np.linalg.norm([0.3, 0.1, -0.9])
    wi = jnp.asarray(np.array([n, g, b, n, -g, g, n]), jnp.float32)
    wo = jnp.asarray(np.array([n, g, n, b, g, -g, g]), jnp.float32)
    f = np.asarray(M.eval(p, wi, wo))
    assert np.all(np.isfinite(f)) and np.all(f[1:] == 0) and np.all(f[0] >= 0)

    def total(wi, wo):
        return jnp.sum(M.eval(p, wi, wo))

    gi, go = jax.grad(total, argnums=(0, 1))(wi, wo)
    assert np.all(np.isfinite(np.asarray(gi))) and np.all(np.isfinite(np.asarray(go)))


def test_gradients_match_finite_differences_and_vmap_jit():
    p = {k: jnp.asarray(v) for k, v in random_weights(4).items()}
    rng = np.random.default_rng(5)
    wi, wo = rand_dirs(rng, 64, 80), rand_dirs(rng, 64, 80)
    with jax.enable_x64(True):
        p64 = {k: jnp.asarray(v, jnp.float64) for k, v in p.items()}

        def f(a, b):
            return jnp.sum(M.eval(p64, a, b) * jnp.array([0.3, 0.5, 0.2]))

        gi = np.asarray(jax.vmap(jax.grad(f, argnums=0))(jnp.asarray(wi), jnp.asarray(wo)))
        eps = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = eps
            fd = (np.asarray(jax.vmap(f)(jnp.asarray(wi + e), jnp.asarray(wo)))
                  - np.asarray(jax.vmap(f)(jnp.asarray(wi - e), jnp.asarray(wo)))) / (2 * eps)
            np.testing.assert_allclose(gi[:, k], fd, rtol=1e-5, atol=1e-7)
    # jit and vmap over directions agree with the broadcasting call
    a = np.asarray(jax.jit(M.eval)(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)))
    b = np.asarray(jax.vmap(M.eval, in_axes=(None, 0, 0))(p, jnp.asarray(wi, jnp.float32),
                                                           jnp.asarray(wo, jnp.float32)))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_batched_materials_broadcast_and_vmap():
    ps = [{k: jnp.asarray(v) for k, v in random_weights(s).items()} for s in (6, 7, 8)]
    st = {k: jnp.stack([q[k] for q in ps]) for k in ps[0]}
    rng = np.random.default_rng(9)
    wi = jnp.asarray(rand_dirs(rng, 10), jnp.float32)
    wo = jnp.asarray(rand_dirs(rng, 10), jnp.float32)
    one = np.stack([np.asarray(M.eval(q, wi, wo)) for q in ps])  # (3, 10, 3)
    batched = np.asarray(M.eval({k: v[:, None] for k, v in st.items()}, wi, wo))  # params (3, 1, ...)
    vm = np.asarray(jax.vmap(M.eval, in_axes=(0, None, None))(st, wi, wo))
    np.testing.assert_allclose(batched, one, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(vm, one, rtol=1e-5, atol=1e-7)


# ---- reading weights ------------------------------------------------------------------------------

def test_reads_h5_file_and_bytes(tmp_path):
    w = random_weights(10)
    path = tmp_path / "m.h5"
    write_h5(path, w)
    for src in (path, str(path), path.read_bytes()):
        got = nbrdf.read_weights(src, "m.h5")
        assert set(got) == set(w)
        for k in w:
            np.testing.assert_array_equal(got[k], w[k])
    p = nbrdf.load(path)
    assert set(p) == set(nbrdf.SHAPES)
    assert all(p[k].shape == s for k, s in nbrdf.SHAPES.items())


@pytest.mark.parametrize("case", ["shape", "extra_layer", "missing", "nan", "not_hdf5", "int"])
def test_refuses_other_architectures_in_one_line(tmp_path, case):
    w = random_weights(11)
    path = tmp_path / f"{case}.h5"
    if case == "shape":
        w["W2"] = np.zeros((21, 20), np.float32)
        write_h5(path, w)
    elif case == "extra_layer":
        write_h5(path, w, extra={"dense_4/dense_4/kernel:0": np.zeros((3, 3), np.float32)})
    elif case == "missing":
        write_h5(path, w, layout=nbrdf.LAYOUT[:-1])
    elif case == "nan":
        w["b2"][3] = np.nan
        write_h5(path, w)
    elif case == "int":
        w["b3"] = np.zeros(3, np.int32)
        write_h5(path, w)
    else:
        path.write_bytes(b"not an hdf5 file")
    with pytest.raises(InputError) as e:
        nbrdf.read_weights(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg
    with pytest.raises(InputError):
        measured.load(path)


def test_json_is_never_read():
    with pytest.raises(InputError, match="not read"):
        measured.load("merl_nbrdf/alum-bronze.json")


# ---- the real networks ----------------------------------------------------------------------------

@pytest.mark.data
def test_real_network_matches_numpy_forward_pass(brdf_data):
    m = brdfs.measured_data.find_material("merl/alum-bronze")
    w = nbrdf.read_weights(m.read_bytes())
    with h5py.File(io.BytesIO(m.read_bytes()), "r") as f:  # an independent read of the same datasets
        np.testing.assert_array_equal(w["W2"], f["dense_2/dense_2/kernel:0"][()])
    mdl, p = measured.load("merl/alum-bronze")
    assert mdl is M
    rng = np.random.default_rng(12)
    wi, wo = rand_dirs(rng, 2000, 85), rand_dirs(rng, 2000, 85)
    th, _, d = ref_half_diff(wi, wo)
    x = np.concatenate([np.stack([np.sin(th), 0 * th, np.cos(th)], -1), d], -1)
    f = np.asarray(M.eval(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)))
    np.testing.assert_allclose(f, ref_mlp(w, x), rtol=1e-3, atol=1e-5)
    n = jnp.array([0.0, 0, 1])
    np.testing.assert_allclose(np.asarray(M.eval(p, n, n)), ref_mlp(w, np.array([0, 0, 1, 0, 0, 1.0])), rtol=1e-5)
    # the archive's Mitsuba-plugin copy of one material (npy, allow_pickle=False) holds the same weights
    with zipfile.ZipFile(brdf_data / "merl_nbrdf.zip") as zf:
        w2 = nbrdf.read_weights(zf.read("merl_nbrdf/blue-acrylic.h5"))
        for k, f in (("W1", "fc1"), ("b1", "b1"), ("W2", "fc2"), ("b2", "b2"), ("W3", "fc3"), ("b3", "b3")):
            a = np.load(io.BytesIO(zf.read(f"merl_nbrdf/npy/blue-acrylic_{f}.npy")), allow_pickle=False)
            np.testing.assert_array_equal(a, w2[k])


@pytest.mark.data
def test_all_materials_finite_albedo_at_most_about_one_and_nearly_reciprocal(brdf_data):
    """Every one of the 159 networks: finite and >= 0 on a direction grid reaching the horizon, albedo
    (brdfs.albedo with the tabulated sampler) at most 1.15 (the RGL scans reach 1.10 at 80°,
    the networks are unconstrained fits), and reciprocal to a few per cent in the median."""
    names = measured.names()
    assert len(names) == 159
    rng = np.random.default_rng(13)
    wi, wo = (jnp.asarray(rand_dirs(rng, 2048, 89.9), jnp.float32) for _ in range(2))
    wi80, wo80 = (jnp.asarray(rand_dirs(rng, 2048, 80), jnp.float32) for _ in range(2))
    th = np.radians([0, 30, 60, 80])
    wv = jnp.asarray(np.stack([np.sin(th), 0 * th, np.cos(th)], -1), jnp.float32)
    meds, worst = [], 0.0
    for name in names:
        _, p = measured.load(name)
        f = np.asarray(M.eval(p, wi, wo))
        assert np.all(np.isfinite(f)) and np.all(f >= 0), name
        a = np.asarray(brdfs.albedo(M, p, wv, n=64))
        assert np.all(np.isfinite(a)) and np.all(a > 0), name
        worst = max(worst, float(a.max()))
        assert a.max() <= 1.15, (name, a.max())
        fa, fb = np.asarray(M.eval(p, wi80, wo80)).mean(-1), np.asarray(M.eval(p, wo80, wi80)).mean(-1)
        meds.append(np.median(np.abs(fa - fb) / np.maximum(np.maximum(fa, fb), 1e-6)))
    assert worst > 0.9  # bright materials exist (the bound is not vacuous)
    assert np.median(meds) < 0.05, np.median(meds)
