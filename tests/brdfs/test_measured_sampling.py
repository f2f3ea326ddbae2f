"""Importance sampling of measured models (brdfs._measured_sampling): chi-square goodness of fit of
`sample` against `pdf` (in the manner of tests/test_brdf_sampling.py, with the expected cell
probabilities from adaptive float64 quadrature of `pdf`, since the tabulated density is piecewise
constant and sharp lobes defeat a fixed rule), a zoomed histogram around the mirror direction for
sharp lobes, weight == f cos / pdf, the mixture's form, and the mean weight == the albedo."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import brdfs
from brdfs import _measured_sampling as S
from brdfs import measured, merl, nbrdf

N_SAMPLES = 200_000
N_COS, N_PHI = 10, 20
ALPHA = 0.01
# (material, view polar angle [deg], cap radius around the mirror direction [deg] for a zoomed
# histogram, or None)
DATA_CASES = [
    ("merl/white-paint", 40, None),  # nearly diffuse
    ("merl/gold-metallic-paint", 60, None),
    ("merl/alum-bronze", 30, None),  # glossy with long tails
    ("rgl/cg_sunflower_rgb", 20, None),
    ("nielsen/paintedmetal", 70, None),
    ("merl/blue-acrylic", 50, 5.0),  # sharp coat over a diffuse base
    ("merl/chrome", 45, 3.0),  # near-mirror: half of the lobe samples within 0.7° of the mirror direction
]
N_TESTS = len(DATA_CASES) + sum(c[2] is not None for c in DATA_CASES) + 1
ALPHA_SIDAK = 1 - (1 - ALPHA) ** (1 / N_TESTS)


def _wo(theta_deg):
    t = math.radians(theta_deg)
    return np.array([math.sin(t), 0.0, math.cos(t)])


def _frame(z):
    """Orthonormal columns (t1, t2, z)."""
    a = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    t1 = np.cross(a, z)
    t1 /= np.linalg.norm(t1)
    return np.stack([t1, np.cross(z, t1), z], -1)


def cell_probs(pdf_fn, c_edges, phi_edges, frame=None, nq=8, tol=1e-6, max_depth=16):
    """∫ pdf dω over each (cos θ, φ) cell (coordinates in `frame`'s columns, default the shading frame)
    by adaptive float64 Gauss-Legendre: a rectangle is split in four until its nq x nq estimate and its
    children's agree to `tol`."""
    x, w = np.polynomial.legendre.leggauss(nq)
    R = np.eye(3) if frame is None else frame

    def gl(r):
        c = 0.5 * (r[:, 1:2] - r[:, 0:1]) * x + 0.5 * (r[:, 1:2] + r[:, 0:1])
        ph = 0.5 * (r[:, 3:4] - r[:, 2:3]) * x + 0.5 * (r[:, 3:4] + r[:, 2:3])
        C, P = c[:, :, None], ph[:, None, :]
        s = np.sqrt(np.maximum(1 - C**2, 0))
        loc = np.stack(np.broadcast_arrays(s * np.cos(P), s * np.sin(P), C), -1)
        v = pdf_fn(loc @ R.T)
        return np.einsum("rij,i,j->r", v, w, w) * 0.25 * (r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2])

    nc, nph = len(c_edges) - 1, len(phi_edges) - 1
    I, J = (a.ravel() for a in np.meshgrid(np.arange(nc), np.arange(nph), indexing="ij"))
    rects = np.stack([c_edges[I], c_edges[I + 1], phi_edges[J], phi_edges[J + 1]], -1)
    owner = np.arange(nc * nph)
    out = np.zeros(nc * nph)
    est = gl(rects)
    for _ in range(max_depth):
        cm, pm = 0.5 * (rects[:, 0] + rects[:, 1]), 0.5 * (rects[:, 2] + rects[:, 3])
        kids = np.concatenate([np.stack([rects[:, 0], cm, rects[:, 2], pm], -1),
                               np.stack([cm, rects[:, 1], rects[:, 2], pm], -1),
                               np.stack([rects[:, 0], cm, pm, rects[:, 3]], -1),
                               np.stack([cm, rects[:, 1], pm, rects[:, 3]], -1)])
        kest = gl(kids)
        ksum = kest.reshape(4, -1).sum(0)
        done = np.abs(ksum - est) < tol
        np.add.at(out, owner[done], ksum[done])
        keep = np.tile(~done, 4)
        rects, est, owner = kids[keep], kest[keep], np.tile(owner, 4)[keep]
        if len(rects) == 0:
            break
    np.add.at(out, owner, est)
    return out.reshape(nc, nph)


def _pdf64(model, p, wo, chunk=1 << 15):
    """w (..., 3) -> model.pdf(p, wo, w) in float64, evaluated in fixed-size chunks (one compilation)."""
    with jax.enable_x64(True):
        p64 = {k: jnp.asarray(np.asarray(v), jnp.float64) for k, v in p.items()}
        f = jax.jit(lambda w: model.pdf(p64, jnp.asarray(wo, jnp.float64), w))

    def pdf_fn(w):
        flat = w.reshape(-1, 3)
        n = len(flat)
        pad = np.concatenate([flat, np.tile([0.0, 0.0, 1.0], ((-n) % chunk, 1))])
        with jax.enable_x64(True):
            out = np.concatenate([np.asarray(f(jnp.asarray(pad[i:i + chunk], jnp.float64)))
                                  for i in range(0, len(pad), chunk)])
        assert out.dtype == np.float64
        return out[:n].reshape(w.shape[:-1])

    return pdf_fn


def _hist(loc, ok, c_edges, phi_edges):
    c = loc[ok, 2]
    ph = np.mod(np.arctan2(loc[ok, 1], loc[ok, 0]), 2 * math.pi)
    h, _, _ = np.histogram2d(c, ph, bins=[c_edges, phi_edges])
    return h


def chi2_pvalue(observed, expected):
    """Pearson chi-square over all bins (counts and expected counts), pooling bins expecting < 5."""
    small = expected < 5
    obs = np.append(observed[~small], observed[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    if exp[-1] == 0:
        obs, exp = obs[:-1], exp[:-1]
    assert abs(exp.sum() - obs.sum()) < 1e-3 * obs.sum(), (exp.sum(), obs.sum())
    return stats.chi2.sf(np.sum((obs - exp) ** 2 / exp), len(obs) - 1)


def _draw(model, p, wo, n=N_SAMPLES, seed=0):
    u = jax.random.uniform(jax.random.PRNGKey(seed), (n, 2), jnp.float32)
    wo32 = jnp.asarray(wo, jnp.float32)
    wi, weight, pdf = jax.jit(model.sample)(p, wo32, u)
    return np.asarray(wi), np.asarray(weight), np.asarray(pdf), wo32


def check_sampler(model, p, theta, cap_deg=None, seed=0, pdf_params=None):
    """Chi-square p-values (hemisphere histogram, and the zoomed cap if asked) of `model.sample(p)`
    against `model.pdf(pdf_params or p)`, after checking weights and pdf consistency."""
    wo = _wo(theta)
    wi, weight, pdf, wo32 = _draw(model, p, wo, seed=seed)
    ok = pdf > 0
    n = len(wi)
    q = pdf_params if pdf_params is not None else p
    pdf_fn = _pdf64(model, q, wo)
    ce, pe = np.linspace(0, 1, N_COS + 1), np.linspace(0, 2 * math.pi, N_PHI + 1)
    probs = cell_probs(pdf_fn, ce, pe)
    total = probs.sum()
    obs = np.append(_hist(wi, ok, ce, pe).ravel(), (~ok).sum())
    pvals = [chi2_pvalue(obs, np.append(probs.ravel(), max(1 - total, 0)) * n)]
    if cap_deg is not None:
        r = wo * np.array([-1, -1, 1])
        fr = _frame(r)
        cc = np.linspace(math.cos(math.radians(cap_deg)), 1, 7)
        pc = np.linspace(0, 2 * math.pi, 9)
        cap = cell_probs(pdf_fn, cc, pc, frame=fr)
        loc = wi @ fr
        inside = ok & (loc[:, 2] >= cc[0])
        obs = np.concatenate([_hist(loc, inside, cc, pc).ravel(), [(ok & ~inside).sum(), (~ok).sum()]])
        exp = np.concatenate([cap.ravel(), [total - cap.sum(), max(1 - total, 0)]]) * n
        pvals.append(chi2_pvalue(obs, exp))
    if pdf_params is None:
        # weight == f cos / pdf where pdf > 0, 0 elsewhere; the returned pdf is pdf(wo, wi)
        k = slice(0, 20_000)
        f = np.asarray(model.eval(p, jnp.asarray(wi[k]), wo32))
        np.testing.assert_allclose(pdf[k], np.asarray(model.pdf(p, wo32, jnp.asarray(wi[k]))), rtol=2e-5, atol=1e-30)
        okk = ok[k]
        # (rtol: a network's f = exp(z) - 1 turns float32 rounding of z, which differs between the
        # jitted sample and this eager eval, into ~1e-4 relative error where f is small)
        np.testing.assert_allclose(weight[k][okk], f[okk] * (wi[k][okk, 2] / pdf[k][okk])[:, None],
                                   rtol=2e-4, atol=1e-7)
        assert np.all(weight[k][~okk] == 0) and np.all(wi[k][~okk, 2] <= 1e-7)
        np.testing.assert_allclose(np.linalg.norm(wi, axis=-1), 1.0, atol=1e-5)
        # the mixture: pdf = (1 - ps) cos/π + ps spec_pdf above the horizon
        ps = np.asarray(S.lobe_prob(p, wo32))
        assert ps.shape == () and 0 <= ps < 1
        mix = (1 - ps) * np.maximum(wi[k, 2], 0) / math.pi + ps * np.asarray(S.spec_pdf(p, wo32, jnp.asarray(wi[k])))
        np.testing.assert_allclose(pdf[k][okk], mix[okk], rtol=1e-5)
        # the mean weight is the albedo
        np.testing.assert_allclose(weight.mean(0), np.asarray(brdfs.albedo(model, p, wo32)), rtol=0.03, atol=2e-3)
    return pvals


@pytest.fixture(scope="module")
def ct_merl(tmp_path_factory):
    """A MERL table of a glossy Cook-Torrance (m = 0.15) written to and read from a .binary file."""
    ct = brdfs.get("cook_torrance")
    p = ct.params(rho_d=[0.2, 0.3, 0.4], rho_s=0.7, m=0.15, eta=2.0)
    path = tmp_path_factory.mktemp("merl") / "ct.binary"
    merl.write(path, merl.tabulate(ct, p))
    return merl.load(path)


def test_chi2_merl_table(ct_merl):
    for pv in check_sampler(merl.MODEL, ct_merl, 55, cap_deg=25.0, seed=1):
        assert pv > ALPHA_SIDAK, f"chi-square rejects sample() vs pdf(): p = {pv:.3g}"


def test_chi2_rejects_a_wrong_pdf(ct_merl):
    """The test can fail: samples checked against a pdf whose lobe probability is 10 % lower, and against
    one whose half-vector bins are shifted by one bin."""
    low_ps = {**ct_merl, "ps": ct_merl["ps"] * 0.9}
    assert min(check_sampler(merl.MODEL, ct_merl, 55, cap_deg=25.0, seed=2, pdf_params=low_ps)) < 1e-6
    pmf = ct_merl["pmf"]
    shifted = {**ct_merl, "pmf": jnp.concatenate([pmf[:, 1:], jnp.zeros_like(pmf[:, :1])], axis=-1)}
    assert min(check_sampler(merl.MODEL, ct_merl, 55, cap_deg=25.0, seed=2, pdf_params=shifted)) < 1e-6


def test_sampler_table_shapes_and_probabilities(ct_merl):
    cdf, pmf, ps = (np.asarray(ct_merl[k]) for k in ("cdf", "pmf", "ps"))
    assert cdf.shape == (S.K, S.N_H + 1) and pmf.shape == (S.K, S.N_H) and np.all(pmf >= 0)
    np.testing.assert_array_equal(cdf[:, 0], 0)
    np.testing.assert_allclose(cdf[:, -1], 1, rtol=1e-6)
    np.testing.assert_allclose(np.diff(cdf, axis=-1), pmf, atol=2e-7)
    # a glossy lobe over a diffuse base: both lobes used, the glossy one more towards grazing (Fresnel)
    assert np.all(np.isin(ps, S.PS_CANDIDATES)) and np.all(ps >= 0.1) and ps[-1] > ps[0] + 0.3, ps
    # the glossy lobe's mass sits in the first bins (θh up to ~10° for m = 0.15) at normal view
    assert cdf[0, np.searchsorted(S.V_EDGES, 1 - math.cos(math.radians(20)))] > 0.8
    # a Lambertian table has no specular part: plain cosine sampling, whose weights are exact
    q = merl.from_table(np.full(merl.RES + (3,), 0.2, np.float32))
    np.testing.assert_array_equal(np.asarray(q["ps"]), 0.0)
    wo = jnp.asarray(_wo(50), jnp.float32)
    _, w, _ = merl.MODEL.sample(q, wo, jax.random.uniform(jax.random.PRNGKey(0), (1000, 2)))
    ok = np.asarray(w)[:, 0] > 0
    assert ok.mean() > 0.99
    np.testing.assert_allclose(np.asarray(w)[ok], 0.2 * math.pi, rtol=1e-5)


@pytest.mark.data
@pytest.mark.parametrize("name,theta,cap", DATA_CASES, ids=[c[0] for c in DATA_CASES])
def test_chi2_neural_brdfs(brdf_data, name, theta, cap):
    model, p = measured.load(name)
    assert model is nbrdf.MODEL
    for pv in check_sampler(model, p, theta, cap_deg=cap, seed=theta):
        assert pv > ALPHA_SIDAK, f"{name}: chi-square rejects sample() vs pdf(): p = {pv:.3g}"


def test_batched_materials_sample_and_pdf(ct_merl):
    """Per-direction material parameters (batch dims) give what one material at a time gives."""
    lam_p = merl.from_table(np.full(merl.RES + (3,), 0.1, np.float32))
    st = measured.stack([ct_merl, lam_p])
    u = jax.random.uniform(jax.random.PRNGKey(3), (2, 500, 2))
    wo = jnp.asarray(_wo(35), jnp.float32)
    pb = {k: v[:, None] for k, v in st.items()}
    sample = jax.jit(merl.MODEL.sample)
    wi, _, pdf = sample(pb, wo, u)
    for i, q in enumerate((ct_merl, lam_p)):
        wi1, _, pdf1 = sample(q, wo, u[i])
        np.testing.assert_allclose(np.asarray(wi[i]), np.asarray(wi1), atol=1e-6)
        np.testing.assert_allclose(np.asarray(pdf[i]), np.asarray(pdf1), rtol=1e-5)
    a = brdfs.albedo(merl.MODEL, st, jnp.stack([wo, wo]), n=64)
    np.testing.assert_allclose(np.asarray(a[1]), 0.1 * math.pi, rtol=1e-3)


# ---- albedo and lobe slices (brdfs.analysis) of measured models ------------------------------------

def _albedo_reference(model, p, wo, tol=1e-6):
    """Float64 adaptive quadrature of ∫ f cos θi dω_i (channel mean), independent of the sampler."""
    with jax.enable_x64(True):
        p64 = {k: jnp.asarray(np.asarray(v), jnp.float64) for k, v in p.items()}
        f = jax.jit(lambda w: jnp.mean(model.eval(p64, w, jnp.asarray(wo, jnp.float64)), -1)
                    * jnp.maximum(w[..., 2], 0.0))

    def fn(w):
        with jax.enable_x64(True):
            return np.asarray(f(jnp.asarray(w, jnp.float64)))

    return cell_probs(fn, np.linspace(0, 1, 5), np.linspace(0, 2 * math.pi, 9), tol=tol).sum()


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_albedo_and_slices_of_a_merl_table(ct_merl):
    """brdfs.albedo of a tabulated Cook-Torrance: the float64 quadrature of the same table, and the
    analytic model's albedo to the table's interpolation error; lobe slices are eval along the slice."""
    ct = brdfs.get("cook_torrance")
    pc = ct.params(rho_d=[0.2, 0.3, 0.4], rho_s=0.7, m=0.15, eta=2.0)
    for th in (0, 70):
        wo = _wo(th)
        a = float(np.asarray(brdfs.albedo(merl.MODEL, ct_merl, jnp.asarray(wo, jnp.float32))).mean())
        assert a == pytest.approx(_albedo_reference(merl.MODEL, ct_merl, wo), rel=2e-3, abs=1e-4), th
        a_ct = float(np.asarray(brdfs.albedo(ct, pc, jnp.asarray(wo, jnp.float32))).mean())
        assert a == pytest.approx(a_ct, rel=0.02), th
    t, f = brdfs.lobe_slice(merl.MODEL, ct_merl, math.radians(30), n=91)
    _, fa = brdfs.lobe_slice(ct, pc, math.radians(30), n=91)
    assert f.shape == (91, 3) and np.all(np.isfinite(f))
    assert np.argmax(f.mean(-1)) == np.argmax(fa.mean(-1))  # the peak in the mirror direction
    assert abs(t[np.argmax(f.mean(-1))] - math.radians(30)) < 0.05


@pytest.mark.data
@pytest.mark.parametrize("name", ["merl/gold-metallic-paint", "merl/white-paint", "nielsen/paintedmetal"])
def test_albedo_of_neural_brdfs_against_quadrature(brdf_data, name, tmp_path):
    model, p = measured.load(name)
    for th in (0, 60):
        wo = _wo(th)
        a = float(np.asarray(brdfs.albedo(model, p, jnp.asarray(wo, jnp.float32))).mean())
        assert a == pytest.approx(_albedo_reference(model, p, wo), rel=2e-3, abs=1e-4), (name, th)
    t, f = brdfs.lobe_slice(model, p, math.radians(40), n=91)
    np.testing.assert_allclose(f, np.asarray(model.eval(p, jnp.asarray([-math.sin(math.radians(40)), 0,
                                                                          math.cos(math.radians(40))]),
                                                        jnp.asarray(np.stack([np.sin(t), 0 * t, np.cos(t)], -1),
                                                                    jnp.float32))), rtol=1e-6)
    brdfs.plot_lobe(model, p, [0.0, math.radians(45)], tmp_path / "lobe.png")
    assert (tmp_path / "lobe.png").stat().st_size > 1000
