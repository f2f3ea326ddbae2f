"""MERL .binary tables (brdfs.merl): the file layout pinned byte by byte, trilinear interpolation against a
float64 numpy re-implementation, round trips of analytic models through synthetic files (with an error
bound from the grid's resolution), missing samples, reciprocity, and malformed files."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfs
from brdfs import measured, merl
from jaxrt.errors import InputError

M = merl.MODEL
NH, ND, NP = merl.RES
HALF_PI = math.pi / 2


def _rotate(v, axis, angle):
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return v * c + axis * np.sum(axis * v, -1, keepdims=True) * (1 - c) + np.cross(axis, v) * s


def ref_directions(th, td, pd, ph=0.0):
    """(wi, wo) from half/difference angles by Rodrigues rotations: wi = R_z(φh) R_y(θh) d."""
    th, td, pd, ph = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (th, td, pd, ph)))
    d = np.stack([np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], -1)
    wi = _rotate(_rotate(d, np.array([0.0, 1, 0]), th), np.array([0.0, 0, 1]), ph)
    h = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    wo = 2 * np.sum(wi * h, -1, keepdims=True) * h - wi
    return wi, wo


def ref_angles(wi, wo):
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    th = np.arccos(np.clip(h[..., 2], -1, 1))
    ph = np.arctan2(h[..., 1], h[..., 0])
    d = _rotate(_rotate(wi, np.array([0.0, 0, 1]), -ph), np.array([0.0, 1, 0]), -th)
    return th, np.arccos(np.clip(d[..., 2], -1, 1)), np.arctan2(d[..., 1], d[..., 0])


def ref_lookup(table, wi, wo):
    """Float64 trilinear interpolation (sample (i, j, k) at θh = (i/90)² π/2, θd = j π/180, φd = k π/180;
    clamped in θh, θd, periodic in φd with period π); all corners valid. Also returns the corner indices."""
    th, td, pd = ref_angles(wi, wo)
    x = [np.clip(np.sqrt(th / HALF_PI) * NH, 0, NH - 1), np.clip(td / HALF_PI * ND, 0, ND - 1),
         np.mod(pd, math.pi) / math.pi * NP]
    lo = [np.minimum(np.floor(x[0]), NH - 2), np.minimum(np.floor(x[1]), ND - 2), np.floor(x[2]) % NP]
    t = [x[a] - lo[a] for a in range(3)]
    lo = [a.astype(int) for a in lo]
    out = 0.0
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                w = (t[0] if a else 1 - t[0]) * (t[1] if b else 1 - t[1]) * (t[2] if c else 1 - t[2])
                out = out + w[:, None] * table[lo[0] + a, lo[1] + b, (lo[2] + c) % NP].astype(np.float64)
    return out, lo


def rand_dirs(rng, n, max_deg):
    c = rng.uniform(math.cos(math.radians(max_deg)), 1.0, n)
    ph = rng.uniform(0, 2 * math.pi, n)
    s = np.sqrt(1 - c * c)
    return np.stack([s * np.cos(ph), s * np.sin(ph), c], -1)


def _eval(p, wi, wo):
    return np.asarray(M.eval(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)))


def _raw_file(path, raw, dims=merl.RES):
    with open(path, "wb") as fh:
        fh.write(np.asarray(dims, "<i4").tobytes())
        fh.write(np.asarray(raw, "<f8").tobytes())


@pytest.fixture(scope="module")
def ct_file(tmp_path_factory):
    """A synthetic MERL file of Cook-Torrance (rho_d (0.3, 0.2, 0.1), rho_s 0.6, m 0.3, eta 1.5)."""
    ct = brdfs.get("cook_torrance")
    p = ct.params(rho_d=[0.3, 0.2, 0.1], rho_s=0.6, m=0.3, eta=1.5)
    path = tmp_path_factory.mktemp("merl") / "ct.binary"
    merl.write(path, merl.tabulate(ct, p))
    return path, ct, p


# ---- the format ---------------------------------------------------------------------------------

def test_layout_and_channel_scales_pinned_by_raw_bytes(tmp_path):
    """Planar float64 after 3 int32 dims, θh slowest and φd fastest, BRDF = raw × (1, 1.15, 1.66)/1500."""
    i, j, k = np.meshgrid(np.arange(NH), np.arange(ND), np.arange(NP), indexing="ij")
    code = i * 1e4 + j * 1e2 + k * 1e-1  # distinct per sample
    raw = np.stack([code, code + 1e6, code + 2e6])  # (3, 90, 90, 180)
    path = tmp_path / "layout.binary"
    _raw_file(path, raw)
    assert path.stat().st_size == merl.FILE_BYTES == 12 + 34_992_000
    t = merl.read(path)
    assert t.shape == (90, 90, 180, 3) and t.dtype == np.float32
    for c, s in enumerate((1 / 1500, 1.15 / 1500, 1.66 / 1500)):
        np.testing.assert_allclose(t[..., c], (code + c * 1e6) * s, rtol=1e-6)
    # write() is read()'s inverse, raw values included
    merl.write(tmp_path / "again.binary", t)
    back = np.fromfile(tmp_path / "again.binary", "<f8", offset=12).reshape(raw.shape)
    np.testing.assert_allclose(back, raw, rtol=1e-6)
    assert tuple(np.fromfile(tmp_path / "again.binary", "<i4", count=3)) == (90, 90, 180)


def test_samples_sit_at_their_angles_and_interpolate_trilinearly():
    """A table that is 1 at one sample and 0 elsewhere: 1 at that sample's directions, 1/2 half-way
    (in index space, so at θh = ((i + 1/2)/90)² π/2 for the non-linear θh axis), 0 one sample away;
    φd wraps from index 179 to index 0 (φd = π)."""
    def delta_at(i, j, k):
        t = np.zeros(merl.RES + (3,), np.float32)
        t[i, j, k] = 1.0
        return {"table": jnp.asarray(t)}

    def th(i):
        return (i / NH) ** 2 * HALF_PI

    def td(j):
        return j * HALF_PI / ND

    def pd(k):
        return k * math.pi / NP

    cases = [((30, 20, 40), (th(30), td(20), pd(40)), 1.0), ((30, 20, 40), (th(30.5), td(20), pd(40)), 0.5),
             ((30, 20, 40), (th(30), td(20.5), pd(40)), 0.5), ((30, 20, 40), (th(30), td(20), pd(40.5)), 0.5),
             ((30, 20, 40), (th(30.5), td(20.5), pd(40.5)), 0.125), ((30, 20, 40), (th(31), td(20), pd(40)), 0.0),
             ((10, 50, 0), (th(10), td(50), pd(179.5)), 0.5), ((10, 50, 0), (th(10), td(50), pd(180)), 1.0),
             ((10, 50, 0), (th(10), td(50), pd(-180)), 1.0),  # φd = -π ≡ 0
             ((60, 20, 90), (th(60), td(20), pd(90 + 180)), 1.0)]  # φd + π: reciprocity
    for node, ang, want in cases:
        p = delta_at(*node)
        for ph in (0.0, 1.3):  # any φh (isotropy)
            wi, wo = ref_directions(*ang, ph)
            got = _eval(p, wi, wo)
            np.testing.assert_allclose(got, want, atol=2e-3, err_msg=f"{node} at {ang}")


def test_lookup_matches_float64_reference_interpolation():
    rng = np.random.default_rng(0)
    t = rng.uniform(0.0, 2.0, merl.RES + (3,)).astype(np.float32)
    p = {"table": jnp.asarray(t)}
    wi, wo = rand_dirs(rng, 4000, 89), rand_dirs(rng, 4000, 89)
    ref, _ = ref_lookup(t, wi, wo)
    np.testing.assert_allclose(_eval(p, wi, wo), ref, rtol=2e-3, atol=2e-3)
    # reciprocity is exact (φd mod π): swapping wi and wo changes nothing but rounding
    np.testing.assert_allclose(_eval(p, wo, wi), _eval(p, wi, wo), rtol=1e-3, atol=1e-4)
    assert brdfs.reciprocity_error(M, p) < 2e-3


def test_missing_samples_are_left_out_of_the_interpolation():
    t = np.full(merl.RES + (3,), 0.25, np.float32)
    t[30, 20, 40] = -1.0  # one missing corner: the others (all 0.25) give 0.25
    t[30, 20, 41, 1] = -1.0  # a missing channel only
    t[50:52, 60:62, 100:102] = -1.0  # a whole cell missing: 0
    p = merl.from_table(t)
    th, td = ((30.5 / NH) ** 2 * HALF_PI, 20.5 * HALF_PI / ND)
    wi, wo = ref_directions(th, td, 40.5 * math.pi / NP)
    np.testing.assert_allclose(_eval(p, wi, wo), 0.25, rtol=1e-5)
    wi, wo = ref_directions((50.5 / NH) ** 2 * HALF_PI, 60.5 * HALF_PI / ND, 100.5 * math.pi / NP)
    np.testing.assert_array_equal(_eval(p, wi, wo), 0.0)
    # a varying table with one missing corner: the renormalised mean of the seven others
    rng = np.random.default_rng(1)
    t = rng.uniform(0.1, 1.0, merl.RES + (3,)).astype(np.float32)
    t[30, 20, 40] = -1
    frac = np.array([0.3, 0.6, 0.2])
    ang = (((30 + frac[0]) / NH) ** 2 * HALF_PI, (20 + frac[1]) * HALF_PI / ND, (40 + frac[2]) * math.pi / NP)
    wi, wo = ref_directions(*ang)
    num = den = 0.0
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                if (a, b, c) == (0, 0, 0):
                    continue
                w = np.prod([f if s else 1 - f for f, s in zip(frac, (a, b, c))])
                num, den = num + w * t[30 + a, 20 + b, 40 + c].astype(np.float64), den + w
    np.testing.assert_allclose(_eval({"table": jnp.asarray(t)}, wi, wo), num / den, rtol=1e-3)


# ---- round trips of analytic models -----------------------------------------------------------------

def test_lambert_round_trip_is_exact(tmp_path):
    lam = brdfs.get("lambert")
    p = lam.params(rho_d=[0.5, 0.3, 0.2])
    tab = merl.tabulate(lam, p)
    assert 0.1 < (tab < 0).mean() < 0.5  # samples with wi or wo below the horizon are marked missing
    merl.write(tmp_path / "lam.binary", tab)
    model, q = measured.load("lam.binary", base=tmp_path)
    assert model is M
    rng = np.random.default_rng(2)
    wi, wo = rand_dirs(rng, 20000, 88), rand_dirs(rng, 20000, 88)
    np.testing.assert_allclose(_eval(q, wi, wo), np.broadcast_to(np.array([0.5, 0.3, 0.2]) / math.pi, (20000, 3)),
                               rtol=1e-5)
    np.testing.assert_allclose(np.asarray(brdfs.albedo(M, q, jnp.asarray(wo[:8], jnp.float32))), [[0.5, 0.3, 0.2]] * 8,
                               rtol=2e-3)


def test_cook_torrance_round_trip_within_the_grid_bound(ct_file):
    """|f - interpolated| <= (1/8) Σ_axes max over the cell of |∂²f/∂x²| (x in index units): the error
    bound of tensor-product linear interpolation, with the second derivatives estimated by the table's
    own second differences at the cell's corners, × 3 because that is an estimate (and the V-cavity G
    has kinks, where f'' does not exist; the largest ratio err/estimate seen is 2.1), plus float32
    rounding. The largest error/bound must also exceed 1/2, so the bound is not vacuous."""
    path, ct, p = ct_file
    q = merl.load(path)
    t = np.asarray(q["table"])
    rng = np.random.default_rng(3)
    wi, wo = rand_dirs(rng, 20000, 75), rand_dirs(rng, 20000, 75)
    fa = np.asarray(ct.eval(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32))).astype(np.float64)
    fm = _eval(q, wi, wo)
    ref, lo = ref_lookup(t, wi, wo)
    # keep points whose cell and its second-difference stencil are measured and inside the table
    i0, j0, k0 = lo
    inner = (i0 >= 1) & (i0 <= NH - 3) & (j0 >= 1) & (j0 <= ND - 3)
    i0, j0, k0, sel = i0[inner], j0[inner], k0[inner], np.flatnonzero(inner)
    bound = np.zeros((len(sel), 3))
    ok = np.ones(len(sel), bool)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                ii, jj, kk = i0 + a, j0 + b, (k0 + c) % NP
                ctr = t[ii, jj, kk]
                d2 = [t[ii + 1, jj, kk] + t[ii - 1, jj, kk] - 2 * ctr, t[ii, jj + 1, kk] + t[ii, jj - 1, kk] - 2 * ctr,
                      t[ii, jj, (kk + 1) % NP] + t[ii, jj, (kk - 1) % NP] - 2 * ctr]
                stencil = [t[ii + 1, jj, kk], t[ii - 1, jj, kk], t[ii, jj + 1, kk], t[ii, jj - 1, kk], ctr]
                ok &= np.all([np.all(s >= 0, -1) for s in stencil], 0)
                bound = np.maximum(bound, sum(np.abs(d) for d in d2))
    bound = 3 * bound / 8 + 1e-5 * np.abs(fa[sel]) + 1e-6
    err = np.abs(fm[sel] - fa[sel])
    assert ok.mean() > 0.9
    ratio = np.max(err[ok] / bound[ok])
    assert 0.5 < ratio <= 1.0, f"max err/bound {ratio:.3g}"
    np.testing.assert_allclose(fm, ref, rtol=2e-3, atol=1e-4)  # and the JAX lookup is the interpolation
    # the grid is fine: at 75° and below the table reproduces the model to ~1 % of its value
    rel = np.abs(fm - fa) / np.maximum(fa, 1e-3)
    assert np.median(rel) < 1e-3 and rel.max() < 0.03, (np.median(rel), rel.max())
    assert err[ok].max() > 1e-3 * fa.max()  # the comparison sees interpolation error (not vacuous)


# ---- malformed files --------------------------------------------------------------------------------

def _check_one_line(path, match):
    with pytest.raises(InputError, match=match) as e:
        merl.read(path)
    assert "\n" not in str(e.value) and str(path) in str(e.value)
    with pytest.raises(InputError):
        measured.load(path)


def test_malformed_files(tmp_path, ct_file):
    good = ct_file[0].read_bytes()
    short = tmp_path / "short.binary"
    short.write_bytes(good[:-8])
    _check_one_line(short, "34992004 bytes, expected 34992012")
    tiny = tmp_path / "tiny.binary"
    tiny.write_bytes(b"\x01\x02")
    _check_one_line(tiny, "2 bytes")
    dims = tmp_path / "dims.binary"  # same size, axes permuted in the header
    dims.write_bytes(np.asarray((180, 90, 90), "<i4").tobytes() + good[12:])
    _check_one_line(dims, r"dims \(180, 90, 90\), expected \(90, 90, 180\)")
    raw = np.frombuffer(good[12:], "<f8").copy()
    raw[12345] = np.nan
    raw[777] = np.inf
    bad = tmp_path / "nan.binary"
    bad.write_bytes(good[:12] + raw.tobytes())
    _check_one_line(bad, "2 non-finite")
    _check_one_line(tmp_path / "absent.binary", "cannot read")
    with pytest.raises(InputError, match="not found"):
        measured.load("absent.binary", base=tmp_path)
    with pytest.raises(InputError, match="shape"):
        merl.from_table(np.zeros((90, 90, 90, 3)))


def test_gradients_finite_and_jit():
    rng = np.random.default_rng(4)
    p = {"table": jnp.asarray(rng.uniform(0.1, 1, merl.RES + (3,)).astype(np.float32))}
    n = np.array([0, 0, 1.0])
    wi = jnp.asarray(np.vstack([rand_dirs(rng, 30, 89), n, n]), jnp.float32)
    wo = jnp.asarray(np.vstack([rand_dirs(rng, 30, 89), n, [1.0, 0, 0]]), jnp.float32)
    g = jax.jit(jax.grad(lambda a, b: jnp.sum(M.eval(p, a, b)), argnums=(0, 1)))(wi, wo)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
