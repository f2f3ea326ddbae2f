"""Sampling: chi-square goodness of fit of `sample` against `pdf` for every model (in the manner of
Mitsuba 3's and pbrt-v4's BSDF tests), weight == f cos / pdf, and the glass model's sampling,
Snell refraction and Fresnel reflectance against textbook closed forms."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import brdfs

DEG = math.pi / 180
N_SAMPLES = 200_000
N_COS, N_PHI = 10, 20
ALPHA = 0.01

# (model, parameters, view polar angle, view azimuth) -- moderately sharp lobes so that the
# 10 x 20 (cos theta, phi) histogram resolves them; wo off the x axis for the anisotropic models.
CASES = [
    ("lambert", dict(rho_d=0.7), 40, 0),
    ("phong", dict(rho_d=0.3, rho_s=0.7, s=20.0), 30, 0),
    ("phong", dict(rho_d=0.0, rho_s=1.0, s=5.0), 70, 0),  # many lobe samples below the horizon
    ("blinn_phong", dict(rho_d=0.4, rho_s=0.6, s=30.0), 45, 0),
    ("cook_torrance", dict(rho_d=0.3, rho_s=0.7, m=0.2, eta=1.5), 60, 0),
    ("cook_torrance", dict(rho_d=0.5, rho_s=0.5, m=0.6, eta=3.0), 20, 0),
    ("ward", dict(rho_d=0.2, rho_s=0.8, alpha_x=0.3, alpha_y=0.1), 50, 30),
    ("ward_1992", dict(rho_d=0.2, rho_s=0.8, alpha_x=0.3, alpha_y=0.1), 50, 30),
    ("ward_duer", dict(rho_d=0.3, rho_s=0.7, alpha_x=0.15, alpha_y=0.4), 70, 60),
    ("ashikhmin_shirley", dict(rho_d=0.5, rho_s=0.3, n_u=50.0, n_v=5.0), 45, 60),
    ("ashikhmin_shirley", dict(rho_d=0.6, rho_s=0.0, n_u=10.0, n_v=200.0), 30, 100),
    # Disney: all three lobes (diffuse+sheen, anisotropic GGX visible normals, GTR1 clearcoat) ...
    ("disney", dict(base_color=[0.7, 0.4, 0.2], metallic=0.3, roughness=0.5, anisotropic=0.8, sheen=0.5,
                    subsurface=0.5, clearcoat=1.0, clearcoat_gloss=0.0, specular_tint=0.5), 45, 30),
    # ... and a rough metal at a grazing view (many lobe samples below the horizon).
    ("disney", dict(base_color=0.9, metallic=1.0, roughness=0.7, anisotropic=0.3), 75, 120),
]
ALPHA_SIDAK = 1 - (1 - ALPHA) ** (1 / len(CASES))


def _wo(theta_deg, phi_deg):
    t, f = theta_deg * DEG, phi_deg * DEG
    return np.array([math.sin(t) * math.cos(f), math.sin(t) * math.sin(f), math.cos(t)])


def _expected_cell_probs(model, p, wo, nq=12):
    """∫ pdf dω over each (cos theta, phi) cell by float64 tensor Gauss-Legendre (nq x nq per cell)."""
    x, w = np.polynomial.legendre.leggauss(nq)
    ce = np.linspace(0, 1, N_COS + 1)
    pe = np.linspace(0, 2 * math.pi, N_PHI + 1)
    c = (0.5 * (ce[1:, None] - ce[:-1, None]) * x + 0.5 * (ce[1:, None] + ce[:-1, None]))  # (N_COS, nq)
    ph = (0.5 * (pe[1:, None] - pe[:-1, None]) * x + 0.5 * (pe[1:, None] + pe[:-1, None]))  # (N_PHI, nq)
    C = c[:, None, :, None]
    P = ph[None, :, None, :]
    S = np.sqrt(1 - C**2)
    wi = np.stack(np.broadcast_arrays(S * np.cos(P), S * np.sin(P), C), -1)  # (N_COS, N_PHI, nq, nq, 3)
    with jax.enable_x64(True):
        p64 = {k: jnp.asarray(np.asarray(v), jnp.float64) for k, v in p.items()}
        pdf = np.asarray(model.pdf(p64, jnp.asarray(wo), jnp.asarray(wi)))
    jac = 0.25 * (ce[1] - ce[0]) * (pe[1] - pe[0])  # both GL maps
    return np.einsum("abij,i,j->ab", pdf, w, w) * jac


def _histogram(wi, ok):
    c = np.clip(wi[ok, 2], 0, 1 - 1e-9)
    ph = np.mod(np.arctan2(wi[ok, 1], wi[ok, 0]), 2 * math.pi)
    ic = np.minimum((c * N_COS).astype(int), N_COS - 1)
    ip = np.minimum((ph / (2 * math.pi) * N_PHI).astype(int), N_PHI - 1)
    h = np.zeros((N_COS, N_PHI))
    np.add.at(h, (ic, ip), 1)
    return h


def chi2_pvalue(observed, expected_probs, n):
    """Pearson chi-square with pooling of cells whose expected count is < 5 (and a 'failed sample'
    cell for the probability mass the pdf does not cover)."""
    obs = np.append(observed.ravel(), n - observed.sum())
    exp = np.append(expected_probs.ravel(), max(1 - expected_probs.sum(), 0.0)) * n
    small = exp < 5
    obs = np.append(obs[~small], obs[small].sum())
    exp = np.append(exp[~small], exp[small].sum())
    if exp[-1] == 0:
        obs, exp = obs[:-1], exp[:-1]
    assert abs(exp.sum() - n) < 1e-3 * n, "pdf does not integrate to <= 1 over the hemisphere"
    stat = np.sum((obs - exp) ** 2 / np.maximum(exp, 1e-300))
    return stats.chi2.sf(stat, len(obs) - 1)


def _draw(model, p, wo, n, seed):
    u = jax.random.uniform(jax.random.PRNGKey(seed), (n, 2), jnp.float32)
    wo32 = jnp.asarray(wo, jnp.float32)
    wi, weight, pdf = jax.jit(model.sample)(p, wo32, u)
    return np.asarray(wi), np.asarray(weight), np.asarray(pdf), wo32


@pytest.mark.parametrize("name,kw,theta,phi", CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_chi2_sample_matches_pdf(name, kw, theta, phi):
    m = brdfs.get(name)
    p = m.params(**kw)
    wo = _wo(theta, phi)
    wi, weight, pdf, wo32 = _draw(m, p, wo, N_SAMPLES, seed=hash(name) % 1000 + theta)
    ok = pdf > 0
    probs = _expected_cell_probs(m, p, wo)
    pval = chi2_pvalue(_histogram(wi, ok), probs, N_SAMPLES)
    assert pval > ALPHA_SIDAK, f"chi-square rejects sample() vs pdf(): p = {pval:.3g}"

    # weight == f cos / pdf exactly where pdf > 0, 0 elsewhere; the returned pdf is pdf(wo, wi).
    k = slice(0, 20_000)
    f = np.asarray(m.eval(p, jnp.asarray(wi[k]), wo32))
    pdf_again = np.asarray(m.pdf(p, wo32, jnp.asarray(wi[k])))
    np.testing.assert_allclose(pdf[k], pdf_again, rtol=2e-5, atol=1e-30)
    okk = ok[k]
    expect = f[okk] * (wi[k][okk, 2] / pdf[k][okk])[:, None]
    np.testing.assert_allclose(weight[k][okk], expect, rtol=2e-5, atol=1e-7)
    assert np.all(weight[k][~okk] == 0)
    assert np.all(wi[k][~okk, 2] <= 1e-7)  # failed samples are those below the horizon
    np.testing.assert_allclose(np.linalg.norm(wi, axis=-1), 1.0, atol=1e-5)
    # the mixture estimator's mean weight is the albedo
    np.testing.assert_allclose(weight.mean(0), np.asarray(brdfs.albedo(m, p, wo32)), rtol=0.02, atol=2e-3)


def test_chi2_rejects_a_wrong_pdf():
    """The test can fail: samples of Phong s=20 against the pdf of s=23 are rejected."""
    m = brdfs.get("phong")
    wo = _wo(30, 0)
    wi, _, pdf, _ = _draw(m, m.params(rho_d=0.3, rho_s=0.7, s=20.0), wo, N_SAMPLES, seed=1)
    probs = _expected_cell_probs(m, m.params(rho_d=0.3, rho_s=0.7, s=23.0), wo)
    assert chi2_pvalue(_histogram(wi, pdf > 0), probs, N_SAMPLES) < 1e-6


# ---- sharpest lobes at the declared bounds ------------------------------------------------------
# A lobe 1e-3 rad wide falls into one cell of the hemisphere histogram above, so these cases bin
# the samples in a frame around the mirror direction r of wo instead: theta' (angle from r) in
# [0, WINDOW * width] in N_R rings of equal theta'^2 steps, times N_A azimuth sectors; everything
# outside the window (diffuse samples, the far tails) and the failed samples form one more cell.
WINDOW, N_R, N_A = 5.0, 8, 8
# (model, parameters at the sharp bound, view polar angle, view azimuth, lobe width in wi [rad])
SHARP_CASES = [
    ("phong", dict(rho_d=0.1, rho_s=0.9, s=1e6), 45, 0, math.sqrt(2 / 1e6)),
    ("blinn_phong", dict(rho_d=0.1, rho_s=0.9, s=1e6), 45, 0, 2 * math.sqrt(2 / 1e6)),
    ("cook_torrance", dict(rho_d=0.1, rho_s=0.9, m=0.001, eta=1000.0), 60, 0, 2e-3),
    ("ward", dict(rho_d=0.1, rho_s=0.9, alpha_x=0.001, alpha_y=0.002), 45, 30, 4e-3),
    ("ward_1992", dict(rho_d=0.1, rho_s=0.9, alpha_x=0.001, alpha_y=0.001), 80, 0, 2e-3),
    ("ward_duer", dict(rho_d=0.1, rho_s=0.9, alpha_x=0.002, alpha_y=0.001), 30, 60, 4e-3),
    ("ashikhmin_shirley", dict(rho_d=0.1, rho_s=0.9, n_u=1e6, n_v=2e5), 45, 30, 2 * math.sqrt(2 / 2e5)),
    # roughness 0 is GGX alpha = 0.001; clearcoat_gloss 1 is GTR1 alpha = 0.001
    ("disney", dict(base_color=0.5, metallic=1.0, roughness=0.0, clearcoat=1.0, clearcoat_gloss=1.0), 40, 0, 2e-3),
]
ALPHA_SHARP = 1 - (1 - ALPHA) ** (1 / len(SHARP_CASES))


def _mirror_frame(wo):
    r = wo * np.array([-1.0, -1.0, 1.0])
    t = np.cross([0.0, 1.0, 0.0], r) if abs(r[1]) < 0.9 else np.cross([1.0, 0.0, 0.0], r)
    t /= np.linalg.norm(t)
    return r, t, np.cross(r, t)


def _window_edges(width):
    return np.sqrt(np.linspace(0, (WINDOW * width) ** 2, N_R + 1)), np.linspace(0, 2 * math.pi, N_A + 1)


def _window_probs(model, p, wo, width, nq=8):
    """∫ pdf dω over each window cell, float64 Gauss-Legendre in (theta', phi') (nq x nq per cell)."""
    x, w = np.polynomial.legendre.leggauss(nq)
    te, pe = _window_edges(width)
    T = 0.5 * (te[1:, None] - te[:-1, None]) * x + 0.5 * (te[1:, None] + te[:-1, None])  # (N_R, nq)
    P = 0.5 * (pe[1:, None] - pe[:-1, None]) * x + 0.5 * (pe[1:, None] + pe[:-1, None])  # (N_A, nq)
    r, t, b = _mirror_frame(wo)
    TT, PP = T[:, None, :, None], P[None, :, None, :]
    wi = (np.cos(TT)[..., None] * r + (np.sin(TT) * np.cos(PP))[..., None] * t
          + (np.sin(TT) * np.sin(PP))[..., None] * b)  # (N_R, N_A, nq, nq, 3)
    with jax.enable_x64(True):
        p64 = {k: jnp.asarray(np.asarray(v), jnp.float64) for k, v in p.items()}
        pdf = np.asarray(model.pdf(p64, jnp.asarray(wo), jnp.asarray(wi)))
    jt = 0.5 * (te[1:] - te[:-1])[:, None, None, None] * np.sin(TT)  # d theta' and sin theta'
    jp = 0.5 * (pe[1] - pe[0])
    return np.einsum("abij,abij,i,j->ab", pdf, np.broadcast_to(jt, pdf.shape), w, w) * jp


def _window_histogram(wi, ok, wo, width):
    r, t, b = _mirror_frame(wo)
    w = wi[ok].astype(np.float64)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    th = 2 * np.arcsin(np.clip(np.linalg.norm(w - r, axis=-1) / 2, 0, 1))  # accurate near r
    ph = np.mod(np.arctan2(w @ b, w @ t), 2 * math.pi)
    te, pe = _window_edges(width)
    h, _, _ = np.histogram2d(th, ph, bins=[te, pe])
    return h


@pytest.mark.parametrize("name,kw,theta,phi,width", SHARP_CASES, ids=[c[0] for c in SHARP_CASES])
def test_chi2_sharp_lobes_at_the_bounds(name, kw, theta, phi, width):
    m = brdfs.get(name)
    p = m.params(**kw)
    wo = _wo(theta, phi)
    wi, weight, pdf, wo32 = _draw(m, p, wo, N_SAMPLES, seed=7 + theta)
    ok = pdf > 0
    probs = _window_probs(m, p, wo, width)
    assert probs.sum() > 0.5  # the window holds the lobe
    pval = chi2_pvalue(_window_histogram(wi, ok, wo, width), probs, N_SAMPLES)
    assert pval > ALPHA_SHARP, f"chi-square rejects sample() vs pdf() in the lobe frame: p = {pval:.3g}"
    assert np.all(np.isfinite(weight)) and np.all(np.isfinite(pdf)) and np.all(weight >= 0)
    k = slice(0, 20_000)
    f = np.asarray(m.eval(p, jnp.asarray(wi[k]), wo32))
    okk = ok[k]
    expect = f[okk] * (wi[k][okk, 2] / pdf[k][okk])[:, None]
    # At the roughness bound the lobe's D term turns one float32 ulp of cos θh into a relative change
    # of ~1e-4 (D ∝ 1/(cos²θh (α² − 1) + 1)², α ≈ 1e-3): sample() and eval() are separate programs
    # whose dot products XLA may contract into fused multiply-adds differently (and differently on
    # CPUs with other vector units: up to ~10 ulps of cos θh at pdf ~1e5 on an AVX-512 machine), so
    # all within 5e-3 and all but 0.1 % within 1e-3.
    pdf_eval = np.asarray(m.pdf(p, wo32, jnp.asarray(wi[k])))
    for got, want, atol in ((weight[k][okk], expect, 1e-7), (pdf[k], pdf_eval, 1e-30)):
        np.testing.assert_allclose(got, want, rtol=5e-3, atol=atol)
        assert np.mean(np.abs(got - want) <= 1e-3 * np.abs(want) + atol) >= 0.999
    np.testing.assert_allclose(weight.mean(0), np.asarray(brdfs.albedo(m, p, wo32)), rtol=0.02, atol=2e-3)


def test_window_chi2_rejects_a_wrong_sharp_pdf():
    """The lobe-frame test can fail: Beckmann samples of m = 0.001 against the pdf of m = 0.0011."""
    m = brdfs.get("cook_torrance")
    wo = _wo(60, 0)
    wi, _, pdf, _ = _draw(m, m.params(rho_d=0.1, rho_s=0.9, m=0.001), wo, N_SAMPLES, seed=2)
    probs = _window_probs(m, m.params(rho_d=0.1, rho_s=0.9, m=0.0011), wo, 2e-3)
    assert chi2_pvalue(_window_histogram(wi, pdf > 0, wo, 2e-3), probs, N_SAMPLES) < 1e-6


# ---- glass ------------------------------------------------------------------------------------

def _fresnel_textbook(n1, n2, theta_i):
    """Unpolarised Fresnel reflectance from the sine/tangent forms (Born & Wolf)."""
    s = n1 / n2 * math.sin(theta_i)
    if s >= 1:
        return 1.0
    tt = math.asin(s)
    if theta_i == 0:
        return ((n1 - n2) / (n1 + n2)) ** 2
    rs = math.sin(theta_i - tt) ** 2 / math.sin(theta_i + tt) ** 2
    rp = math.tan(theta_i - tt) ** 2 / math.tan(theta_i + tt) ** 2
    return 0.5 * (rs + rp)


def test_glass_fresnel_exact_matches_textbook_and_schlick_is_close():
    g = brdfs.get("glass")
    n = 1.5
    p = g.params(n_t=n)
    th = np.array([0, 10, 30, 45, 56.31, 70, 85]) * DEG
    r = np.asarray(g.dielectric.fresnel(p, jnp.asarray(np.cos(th), jnp.float32), jnp.asarray(True), exact=True))
    ref = np.array([_fresnel_textbook(1.0, n, t) for t in th])
    np.testing.assert_allclose(r, ref, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(g.dielectric.fresnel(p, jnp.cos(th), jnp.asarray(True), exact=True)), r, rtol=1e-6)
    # leaving the glass: textbook with n1 = n, n2 = 1, including total internal reflection
    th_in = np.array([0, 20, 40, 41.8, 42, 60]) * DEG
    r_in = np.asarray(g.dielectric.fresnel(p, jnp.asarray(np.cos(th_in), jnp.float32), jnp.asarray(False), exact=True))
    ref_in = np.array([_fresnel_textbook(n, 1.0, t) for t in th_in])
    np.testing.assert_allclose(r_in, ref_in, rtol=2e-3, atol=1e-5)
    assert r_in[-1] == 1.0 and r_in[-2] == 1.0  # beyond the critical angle asin(1/1.5) = 41.81 deg
    # Schlick: exact F0 at normal incidence, within 0.01 of the exact curve for glass, and
    # symmetric under reversal (same R entering at theta_i and leaving at theta_t).
    rs = np.asarray(g.dielectric.fresnel(p, jnp.asarray(np.cos(th), jnp.float32), jnp.asarray(True)))
    assert abs(rs[0] - 0.04) < 1e-6
    np.testing.assert_allclose(rs, ref, atol=0.04)  # Schlick's known error for glass is ~3.6 % near 80 deg
    cos_t = np.sqrt(1 - (np.sin(th) / n) ** 2)
    for exact in (False, True):
        a = g.dielectric.fresnel(p, jnp.asarray(np.cos(th), jnp.float32), jnp.asarray(True), exact=exact)
        b = g.dielectric.fresnel(p, jnp.asarray(cos_t, jnp.float32), jnp.asarray(False), exact=exact)
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_glass_refraction_obeys_snell_and_tir():
    g = brdfs.get("glass")
    n = 1.7
    p = g.params(n_t=n)
    rng = np.random.default_rng(5)
    ct = rng.uniform(0.01, 1, 200)
    ph = rng.uniform(0, 2 * math.pi, 200)
    st = np.sqrt(1 - ct**2)
    wo = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).astype(np.float32)
    for side, eta_o, eta_t in ((1, 1.0, n), (-1, n, 1.0)):
        w = wo * np.array([1, 1, side], np.float32)
        wt, ok = g.dielectric.refract(p, jnp.asarray(w))
        wt, ok = np.asarray(wt), np.asarray(ok)
        sin_o = np.linalg.norm(w[:, :2], axis=-1)
        tir = eta_o * sin_o > eta_t
        np.testing.assert_array_equal(ok, ~tir)
        np.testing.assert_allclose(np.linalg.norm(wt, axis=-1), 1, atol=1e-5)
        sin_t = np.linalg.norm(wt[:, :2], axis=-1)
        np.testing.assert_allclose(eta_o * sin_o[ok], eta_t * sin_t[ok], rtol=1e-4, atol=1e-6)
        assert np.all(np.sign(wt[ok, 2]) == -side)  # crosses the interface
        # in the plane of incidence, on the opposite side of the normal (wo and wt anti-parallel in xy)
        cross = wo[ok, 0] * wt[ok, 1] - wo[ok, 1] * wt[ok, 0]
        np.testing.assert_allclose(cross, 0, atol=1e-5)
        assert np.all(wo[ok, 0] * wt[ok, 0] + wo[ok, 1] * wt[ok, 1] <= 1e-6)
        # under TIR the returned direction is the mirror direction
        np.testing.assert_allclose(wt[tir], w[tir] * np.array([-1, -1, 1]), atol=1e-6)
    np.testing.assert_allclose(g.dielectric.reflect(jnp.asarray(wo)), wo * np.array([-1, -1, 1]))


@pytest.mark.parametrize("theta,inside", [(0, False), (60, False), (80, False), (30, True), (50, True)])
def test_glass_sample_chooses_reflection_with_probability_r(theta, inside):
    g = brdfs.get("glass")
    p = g.params(n_t=1.5)
    wo = _wo(theta, 20) * np.array([1, 1, -1 if inside else 1])
    n = 20_000
    u = jax.random.uniform(jax.random.PRNGKey(theta), (n, 2), jnp.float32)
    wi, weight, prob = (np.asarray(a) for a in jax.jit(g.sample)(p, jnp.asarray(wo, jnp.float32), u))
    r = _fresnel_textbook(1.5, 1.0, theta * DEG) if inside else None
    r_schlick = float(g.dielectric.fresnel(p, jnp.float32(abs(wo[2])), jnp.asarray(not inside)))
    refl = np.sign(wi[:, 2]) == np.sign(wo[2])
    k = int(refl.sum())
    assert stats.binomtest(k, n, r_schlick).pvalue > 1e-3
    np.testing.assert_array_equal(weight, 1.0)
    np.testing.assert_allclose(prob[refl], r_schlick, rtol=1e-6)
    np.testing.assert_allclose(prob[~refl], 1 - r_schlick, rtol=1e-5)
    if r is not None and r == 1.0:  # total internal reflection: always reflected
        assert k == n
    assert np.all(np.asarray(g.pdf(p, jnp.asarray(wo), jnp.asarray(wi))) == 0)
