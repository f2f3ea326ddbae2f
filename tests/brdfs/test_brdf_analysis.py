"""The albedo estimator against independent float64 brute-force quadrature; lobe slices,
reciprocity error, lobe plots and the `jaxrt brdf-report` command."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfs
from jaxrt.cli import main as cli_main

DEG = math.pi / 180


def _p64(p):
    return {k: jnp.asarray(np.asarray(v), jnp.float64) for k, v in p.items()}


def _gl(a, b, n):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (b + a), 0.5 * (b - a) * w


def _wo(theta):
    return np.array([math.sin(theta), 0.0, math.cos(theta)])


def brute_albedo(model, p, theta_o, nt=96, nph=256):
    """float64 tensor Gauss-Legendre (cos theta_i, split at 0.5 and 0.9) x midpoint (phi) quadrature."""
    pieces = [_gl(a, b, nt) for a, b in [(0, 0.5), (0.5, 0.9), (0.9, 1.0)]]
    c = np.concatenate([q[0] for q in pieces])
    wc = np.concatenate([q[1] for q in pieces])
    ph = (np.arange(nph) + 0.5) / nph * 2 * math.pi
    C, P = np.meshgrid(c, ph, indexing="ij")
    S = np.sqrt(1 - C**2)
    wi = np.stack([S * np.cos(P), S * np.sin(P), C], -1)
    with jax.enable_x64(True):
        f = np.asarray(model.eval(_p64(p), jnp.asarray(wi), jnp.asarray(_wo(theta_o))))
    return np.einsum("ijc,ij,i->c", f, C, wc) * (2 * math.pi / nph)


def halfvector_albedo(model, p, theta_o, width, nt=100, nph=256):
    """float64 quadrature in half-vector space, nodes concentrated where the lobe is:
    ∫ f cos_i dω_i = ∫ f(wi(h)) cos_i 4 (wo·h) dω_h, theta_h split at `width` multiples."""
    edges = [0.0, width, 3 * width, 8 * width, math.pi / 2]
    edges = sorted({min(e, math.pi / 2) for e in edges})
    pieces = [_gl(a, b, nt) for a, b in zip(edges[:-1], edges[1:])]
    th = np.concatenate([q[0] for q in pieces])
    wt = np.concatenate([q[1] for q in pieces])
    ph = (np.arange(nph) + 0.5) / nph * 2 * math.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    h = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    wo = _wo(theta_o)
    oh = h @ wo
    wi = 2 * oh[..., None] * h - wo
    with jax.enable_x64(True):
        f = np.asarray(model.eval(_p64(p), jnp.asarray(wi), jnp.asarray(wo)))
    integrand = f * (np.maximum(wi[..., 2], 0) * 4 * np.maximum(oh, 0) * np.sin(T))[..., None]
    return np.einsum("ijc,i->c", integrand, wt) * (2 * math.pi / nph)


def mirror_albedo(model, p, theta_o, width, nt=100, nph=256):
    """float64 quadrature in a frame around the mirror direction r of wo (for Phong)."""
    edges = sorted({min(e, math.pi) for e in [0.0, width, 3 * width, 8 * width, math.pi]})
    pieces = [_gl(a, b, nt) for a, b in zip(edges[:-1], edges[1:])]
    th = np.concatenate([q[0] for q in pieces])
    wt = np.concatenate([q[1] for q in pieces])
    ph = (np.arange(nph) + 0.5) / nph * 2 * math.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    r = _wo(-theta_o)
    t = np.array([r[2], 0.0, -r[0]])
    b = np.array([0.0, 1.0, 0.0])
    wi = (np.sin(T) * np.cos(P))[..., None] * t + (np.sin(T) * np.sin(P))[..., None] * b + np.cos(T)[..., None] * r
    with jax.enable_x64(True):
        f = np.asarray(model.eval(_p64(p), jnp.asarray(wi), jnp.asarray(_wo(theta_o))))
    integrand = f * (np.maximum(wi[..., 2], 0) * np.sin(T))[..., None]
    return np.einsum("ijc,i->c", integrand, wt) * (2 * math.pi / nph)


SMOOTH = [
    ("lambert", dict(rho_d=[0.3, 0.6, 0.9])),
    ("phong", dict(rho_d=0.3, rho_s=0.6, s=20)),
    ("blinn_phong", dict(rho_d=0.3, rho_s=0.6, s=30)),
    ("cook_torrance", dict(rho_d=0.3, rho_s=0.7, m=0.3, eta=1.8)),
    ("ward", dict(rho_d=0.2, rho_s=0.7, alpha_x=0.3, alpha_y=0.15)),
    ("ashikhmin_shirley", dict(rho_d=0.6, rho_s=0.3, n_u=50, n_v=10)),
]
THETAS = [0.0, 40 * DEG, 75 * DEG]


@pytest.mark.parametrize("name,kw", SMOOTH, ids=[s[0] for s in SMOOTH])
def test_albedo_smooth_lobes_within_1e4_of_quadrature(name, kw):
    m = brdfs.get(name)
    p = m.params(**kw)
    wo = np.stack([_wo(t) for t in THETAS]).astype(np.float32)
    got = np.asarray(brdfs.albedo(m, p, wo))
    ref = np.stack([brute_albedo(m, p, t) for t in THETAS])
    np.testing.assert_allclose(got, ref, atol=1e-4, rtol=0)


SHARP = [
    ("phong", dict(rho_d=0.0, rho_s=1.0, s=1000), "mirror", 1 / math.sqrt(1000)),
    ("blinn_phong", dict(rho_d=0.0, rho_s=1.0, s=1000), "half", 1 / math.sqrt(1000)),
    ("cook_torrance", dict(rho_d=0.0, rho_s=1.0, m=0.01, eta=1.5), "half", 0.01),
    ("ward", dict(rho_d=0.0, rho_s=1.0, alpha_x=0.01, alpha_y=0.01), "half", 0.01),
    ("ashikhmin_shirley", dict(rho_d=0.0, rho_s=1.0, n_u=10000, n_v=10000), "half", 0.01),
]
SHARP_TOL = 1e-4  # measured ~2e-5; see brdfs/analysis.py


@pytest.mark.parametrize("name,kw,frame,width", SHARP, ids=[s[0] for s in SHARP])
def test_albedo_sharp_lobes_documented_accuracy(name, kw, frame, width):
    m = brdfs.get(name)
    p = m.params(**kw)
    thetas = [0.0, 45 * DEG]
    wo = np.stack([_wo(t) for t in thetas]).astype(np.float32)
    got = np.asarray(brdfs.albedo(m, p, wo))
    ref_fn = mirror_albedo if frame == "mirror" else halfvector_albedo
    ref = np.stack([ref_fn(m, p, t, width) for t in thetas])
    np.testing.assert_allclose(got, ref, atol=SHARP_TOL, rtol=0)


def test_glass_albedo_is_fresnel_reflectance():
    g = brdfs.get("glass")
    a = brdfs.albedo(g, g.params(n_t=1.5), jnp.asarray(_wo(0.0), jnp.float32))
    np.testing.assert_allclose(a, [0.04] * 3, rtol=1e-5)


def test_lobe_slices_peak_at_mirror_and_symmetric():
    m = brdfs.get("phong")
    p = m.params(rho_d=0.0, rho_s=1.0, s=200)
    t, f = brdfs.lobe_slice(m, p, 30 * DEG, n=181, plane="incidence")
    assert t.shape == (181,) and f.shape == (181, 3)
    assert abs(t[np.argmax(f[:, 0])] - 30 * DEG) < 1.1 * DEG
    t, f = brdfs.lobe_slice(m, p, 30 * DEG, n=181, plane="perpendicular")
    assert abs(t[np.argmax(f[:, 0])]) < 1e-9
    np.testing.assert_allclose(f[:, 0], f[::-1, 0], rtol=1e-5, atol=1e-6)
    # Ward with alpha_x > alpha_y: at normal incidence the lobe is wider in the incidence (xz)
    # plane than in the perpendicular (yz) plane.
    w = brdfs.get("ward")
    pw = w.params(rho_d=0.0, alpha_x=0.4, alpha_y=0.1)
    _, fi = brdfs.lobe_slice(w, pw, 0.0, n=181, plane="incidence")
    _, fp = brdfs.lobe_slice(w, pw, 0.0, n=181, plane="perpendicular")
    assert (fi[:, 0] > 0.5 * fi[:, 0].max()).sum() > 2 * (fp[:, 0] > 0.5 * fp[:, 0].max()).sum()
    with pytest.raises(ValueError, match="plane"):
        brdfs.lobe_slice(m, p, 0.0, plane="sideways")


def test_reciprocity_error_detects_the_2015_report_diffuse_term():
    """The report's A-S diffuse term (n·wi in both factors) is not reciprocal; the paper's is."""
    import dataclasses

    a_s = brdfs.get("ashikhmin_shirley")
    p = a_s.params(rho_d=0.8, rho_s=0.1)

    def report_eval(p, wi, wo):
        ci = jnp.maximum(wi[..., 2], 0.0)
        return (28 / (23 * math.pi) * p["rho_d"] * (1 - p["rho_s"])
                * ((1 - (1 - ci / 2) ** 5) ** 2 * (wo[..., 2] > 0))[..., None])

    bad = dataclasses.replace(a_s, name="as_report", eval=report_eval)
    assert brdfs.reciprocity_error(bad, p) > 0.1
    assert brdfs.reciprocity_error(a_s, p) < 1e-4


def test_plot_lobe_writes_png_atomically(tmp_path):
    m = brdfs.get("cook_torrance")
    out = tmp_path / "lobe.png"
    brdfs.plot_lobe(m, m.params(), [0.0, 30 * DEG, 60 * DEG], out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(FileNotFoundError):
        brdfs.plot_lobe(m, m.params(), [0.0], tmp_path / "missing" / "lobe.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lobe.png"]


def test_brdf_report_cli(tmp_path, capsys):
    out = tmp_path / "report.png"
    rc = cli_main(["brdf-report", "-o", str(out), "--samples", "32"])
    assert rc == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    for name in brdfs.names():
        assert name in text
    # Lambert's default rho_d = 0.8 must show as 0.8000 in every column of its row.
    row = next(line for line in text.splitlines() if line.startswith("lambert"))
    assert row.split()[1:].count("0.8000") >= 5
    rc = cli_main(["brdf-report", "-o", str(tmp_path / "nodir" / "x.png")])
    assert rc == 2
