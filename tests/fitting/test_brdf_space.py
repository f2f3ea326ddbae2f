"""BRDF-space fitting (fitting.brdf_space), the study (fitting.study) and their commands.

References are independent of the code under test: the sampling's weights against closed-form
integrals, every metric between two Lambertian materials against a 1-D Gauss–Legendre quadrature of
its definition over the 80° cap, the metrics against float64 numpy written out here, closed loops against known parameters,
and the batched solve against the one-target-set path (fitting.solve.fit_images). Every fit here uses
one small grid, 4 starts and the same solver settings, so the compiled solves are shared across tests.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

import brdfs
from fitting import brdf_space as bs
from fitting import study
from fitting.solve import fit_images

RES = (16, 12, 12)
STARTS = 4
TWO = ["merl/alum-bronze", "merl/white-paint"]


@pytest.fixture(scope="module")
def samp():
    return bs.sampling(*RES)


def test_sampling_weights_integrate_the_hemispheres():
    """Σ w ≈ ∫∫ dωi dωo and Σ w cos θi cos θo ≈ ∫∫ cos cos dωi dωo, in closed form, with and without the cutoff."""
    s = bs.sampling(32, 24, 24, cutoff_deg=90.0)
    assert s.weight.sum() == pytest.approx((2 * math.pi) ** 2, rel=4e-3)
    assert np.sum(s.weight * s.wi[:, 2] * s.wo[:, 2]) == pytest.approx(math.pi**2, rel=4e-3)
    c = bs.sampling(32, 24, 24)  # θ ≤ 80°: each hemisphere's cap has solid angle 2π (1 − cos 80°)
    cap = 2 * math.pi * (1 - math.cos(math.radians(80)))
    assert c.weight.sum() == pytest.approx(cap**2, rel=4e-3)
    cos80 = math.cos(math.radians(80))
    assert np.all(c.wi[:, 2] > cos80) and np.all(c.wo[:, 2] > cos80)
    np.testing.assert_allclose(np.linalg.norm(c.wi, axis=-1), 1.0, atol=1e-12)
    # every pair is a reflection about its half vector at θh from the normal (MERL's square-root scale)
    h = c.wi + c.wo
    assert np.min(np.arccos(np.clip(h[:, 2] / np.linalg.norm(h, axis=-1), -1, 1))) < math.radians(0.05)


@pytest.mark.parametrize("res, rel", [(bs.FIT_RESOLUTION, 3e-3), (bs.EVAL_RESOLUTION, 5e-4)])
def test_metrics_between_lambertians_match_quadrature_over_the_cap(res, rel):
    """E between two Lambertians f = ρ/π reduces to a 1-D integral over μ = cos θi on the cap
    μ ≥ cos 80° (the ωo integral and the φ integrals cancel against Σ w):

        E² = Σ_ch ∫_c^1 (g(ρa μ/π) − g(ρb μ/π))² dμ / (3 (1 − c)),

    which Gauss–Legendre quadrature computes to float64 precision; for "ngan" it is also the closed
    form |Δρ|_rms/π · √((1 − c³) / (3 (1 − c))). This checks the weights, the cosine factor, the
    cutoff and the channel average of the grid the fits and the study's errors use."""
    ra, rb = np.array([0.8, 0.5, 0.2]), np.array([0.3, 0.45, 0.05])
    s = bs.sampling(*res)
    e = bs.errors(np.broadcast_to(ra / math.pi, (s.size, 3)), np.broadcast_to(rb / math.pi, (s.size, 3)), s)
    c = math.cos(math.radians(bs.CUTOFF_DEG))
    x, wq = np.polynomial.legendre.leggauss(64)
    mu, w = c + (1 - c) * (x + 1) / 2, wq * (1 - c) / 2
    g = {"ngan": lambda v: v, "cuberoot": lambda v: np.cbrt(v + bs.CBRT_EPS), "log": np.log1p}
    for m in bs.METRICS:
        d = g[m](ra[None] * mu[:, None] / math.pi) - g[m](rb[None] * mu[:, None] / math.pi)
        ref = math.sqrt(np.sum(w[:, None] * d**2) / (3 * (1 - c)))
        assert e[m] == pytest.approx(ref, rel=rel), m
    closed = math.sqrt(np.mean((ra - rb) ** 2)) / math.pi * math.sqrt((1 - c**3) / (3 * (1 - c)))
    assert e["ngan"] == pytest.approx(closed, rel=rel)


def _blinn_phong_np(rho_d, rho_s, s, wi, wo):
    """Normalised Blinn–Phong in float64 numpy (the formula of brdfs/blinn_phong.py, written out)."""
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    lobe = (s + 8) / (8 * math.pi) * np.clip(h[:, 2], 0, None) ** s
    return np.asarray(rho_d)[None] / math.pi + np.asarray(rho_s)[None] * lobe[:, None]


@pytest.mark.parametrize("metric", bs.METRICS)
def test_metric_definitions_match_float64_numpy(samp, metric):
    """The solver's weighted residuals (JAX, float32) and `errors` give the documented E."""
    model = brdfs.get("blinn_phong")
    a = dict(rho_d=[0.3, 0.2, 0.1], rho_s=[0.2, 0.25, 0.3], s=40.0)
    b = dict(rho_d=[0.25, 0.22, 0.05], rho_s=[0.3, 0.2, 0.1], s=90.0)
    fa = _blinn_phong_np(a["rho_d"], a["rho_s"], a["s"], samp.wi, samp.wo)
    fb = _blinn_phong_np(b["rho_d"], b["rho_s"], b["s"], samp.wi, samp.wo)
    c = samp.wi[:, 2:3]
    g = {"ngan": lambda x: x, "cuberoot": lambda x: np.cbrt(x + 1e-6), "log": np.log1p}[metric]
    ref = math.sqrt(np.sum(samp.weight[:, None] * (g(fa * c) - g(fb * c)) ** 2) / (3 * samp.weight.sum()))
    assert bs.errors(fa, fb, samp)[metric] == pytest.approx(ref, rel=1e-12)
    shade = bs.shader(model, metric)
    d = bs.device_data(samp)
    ya = np.asarray(shade(model.params(**a), d), np.float64)
    yb = np.asarray(shade(model.params(**b), d), np.float64)
    w = samp.weight / samp.weight.mean()  # the solver's mask
    e_solver = math.sqrt(np.sum(w[:, None] * (ya - yb) ** 2) / (3 * w.sum()))
    assert e_solver == pytest.approx(ref, rel=2e-4)


CLOSED_LOOP = {
    "blinn_phong": [dict(rho_d=[0.3, 0.2, 0.1], rho_s=[0.2, 0.25, 0.3], s=60.0),
                    dict(rho_d=[0.05, 0.1, 0.4], rho_s=[0.5, 0.4, 0.3], s=8.0)],
    "cook_torrance": [dict(rho_d=[0.1, 0.15, 0.2], rho_s=[0.6, 0.5, 0.4], m=0.15, eta=2.0),
                      dict(rho_d=[0.4, 0.3, 0.2], rho_s=[0.3, 0.3, 0.3], m=0.4, eta=1.4)],
    "ward": [dict(rho_d=[0.2, 0.3, 0.1], rho_s=[0.1, 0.2, 0.15], alpha_x=0.08, alpha_y=0.08),
             dict(rho_d=[0.5, 0.1, 0.1], rho_s=[0.3, 0.3, 0.2], alpha_x=0.3, alpha_y=0.3)],
}


# the metric each closed loop fits with (Blinn–Phong's also serves the bound test: one compilation)
CLOSED_LOOP_METRIC = {"blinn_phong": "cuberoot", "cook_torrance": "ngan", "ward": "ngan"}


@pytest.mark.parametrize("name", CLOSED_LOOP)
def test_closed_loop_recovers_known_parameters(samp, name):
    model = brdfs.get(name)
    truths = CLOSED_LOOP[name]
    f = bs.evaluate(model, [model.params(**t) for t in truths], samp)
    fits = bs.fit_samples(f, model, samp=samp, starts=STARTS, metric=CLOSED_LOOP_METRIC[name])
    for t, fit in zip(truths, fits):
        for k, v in t.items():
            np.testing.assert_allclose(fit.params[k], v, rtol=2e-3, atol=1e-4, err_msg=f"{name}.{k}")
        assert fit.error < 1e-5 * max(1.0, float(np.max(f))) and fit.metric == CLOSED_LOOP_METRIC[name]
        assert fit.at_bound == {}
    if name == "ward":  # isotropic materials fit one roughness: alpha_y follows alpha_x
        assert fits[0].tied == {"alpha_y": "alpha_x"} and fits[0].stderr["alpha_y"] == fits[0].stderr["alpha_x"]


# Ashikhmin–Shirley with its specular scale k_s: a sharp, weak lobe like the MERL plastics' (k_s ~ 0.1,
# n ~ 1e4: the case the paper's model, k_s = 1, cannot fit) and a broad, strong one
AS_TRUTHS = [dict(rho_d=[0.3, 0.2, 0.1], rho_s=[0.05, 0.06, 0.08], k_s=[0.2, 0.15, 0.1], n_u=3000.0, n_v=3000.0),
             dict(rho_d=[0.1, 0.3, 0.5], rho_s=[0.6, 0.5, 0.4], k_s=[0.8, 0.7, 0.9], n_u=40.0, n_v=40.0)]


@pytest.mark.slow  # ~15 s on a 2-core CPU: compiles the one-start solve
def test_ashikhmin_shirley_recovers_known_parameters_from_the_default_start(samp):
    """Targets made by the model itself with known parameters (n_v = n_u, as the isotropic tie) fit back
    from the one default start (k_s = 1, n = 100, rho_s = 0.05), with the solver settings of the study."""
    model = brdfs.get("ashikhmin_shirley")
    f = bs.evaluate(model, [model.params(**t) for t in AS_TRUTHS], samp)
    fits = bs.fit_samples(f, model, samp=samp, starts=1)
    for t, fit in zip(AS_TRUTHS, fits):
        for k, v in t.items():
            np.testing.assert_allclose(fit.params[k], v, rtol=2e-3, atol=1e-4, err_msg=f"ashikhmin_shirley.{k}")
        assert fit.converged and fit.at_bound == {} and fit.error < 1e-5 * float(np.max(f))


@pytest.mark.slow  # ~15 s on a 2-core CPU: one more compiled solve (4 starts) and a neural material
def test_ashikhmin_shirley_fit_of_a_measured_plastic_beats_its_lambertian_term(brdf_data, samp):
    """On blue-acrylic (a sharp, weak highlight) the fitted lobe must explain most of what a Lambertian
    term leaves: E at most half the best Lambertian fit's (closed-form weighted least squares in float64,
    independent of the solver). The paper's model (k_s = 1) ends at rho_s = 0 there, within 2 % of it."""
    model = brdfs.get("ashikhmin_shirley")
    f = bs.measured_samples(["merl/blue-acrylic"], samp)
    fit = bs.fit_samples(f, model, samp=samp, starts=STARTS)[0]
    c, w = samp.wi[:, 2:3], samp.weight[:, None]
    y = f[0].astype(np.float64) * c
    rho_d = np.clip(np.sum(w * y * c / math.pi, 0) / np.sum(w * (c / math.pi) ** 2, 0), 0.0, 1.0)
    e_lambert = math.sqrt(np.sum(w * (rho_d * c / math.pi - y) ** 2) / (3 * w.sum()))
    assert fit.error < 0.5 * e_lambert, (fit.error, e_lambert, fit.params)
    assert not any(k.startswith("rho_s") for k in fit.at_bound)


def test_fit_reports_parameters_that_end_at_a_bound(samp):
    """Data made at a bound of the declared range (read from the model's Params) fit back to that bound."""
    model = brdfs.get("blinn_phong")
    hi = model.param("s").hi
    truth = model.params(rho_d=[0.0, 0.2, 0.3], rho_s=0.5, s=hi)
    f = bs.evaluate(model, [truth, truth], samp)
    fit = bs.fit_samples(f, model, samp=samp, starts=STARTS, metric=CLOSED_LOOP_METRIC["blinn_phong"])[0]
    assert fit.at_bound.get("s") == "upper" and fit.at_bound.get("rho_d[r]") == "lower", fit.at_bound
    assert "rho_d[g]" not in fit.at_bound and "rho_s[b]" not in fit.at_bound


@pytest.fixture(scope="module")
def two_materials(brdf_data, samp):
    return bs.measured_samples(TWO, samp)


@pytest.mark.slow  # ~20 s on a 2-core CPU: compiles fit_images' solver beside the batched one
def test_batched_solve_equals_the_per_material_solve(two_materials, samp):
    model = brdfs.get("cook_torrance")
    batched = bs.fit_samples(two_materials, model, names=TWO, samp=samp, starts=STARTS)
    shade = bs.shader(model, "ngan")
    d = bs.device_data(samp)
    mask = samp.weight / samp.weight.mean()
    for i, fit in enumerate(batched):
        target = np.asarray(two_materials[i] * d["cos"])
        one = fit_images(shade, d, target, model, mask=mask, starts=STARTS, max_steps=100, solver=bs.SOLVER,
                         rtol=1e-5, atol=1e-8, progress=False)
        for k in model.param_names:
            np.testing.assert_allclose(fit.params[k], one.params[k], rtol=1e-3, atol=1e-5, err_msg=f"{TWO[i]} {k}")
            np.testing.assert_allclose(fit.stderr[k], one.stderr[k], rtol=2e-2, atol=1e-7)
        assert fit.at_bound == one.at_bound
    # and a batch of one gives each material's fit again
    single = bs.fit_samples(two_materials[1:], model, names=TWO[1:], samp=samp, starts=STARTS)[0]
    for k in model.param_names:
        np.testing.assert_allclose(single.params[k], batched[1].params[k], rtol=1e-4, atol=1e-6)


def _cli(*argv):
    from jaxrt.cli import main

    return main(list(argv))


SMALL = ["--sampling", ",".join(map(str, RES)), "--eval-sampling", ",".join(map(str, RES)),
         "--starts", str(STARTS), "-q"]


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_fit_brdf_cli_writes_both_outputs_or_none(brdf_data, tmp_path, monkeypatch, capsys):
    out, plot = tmp_path / "fit.json", tmp_path / "fit.png"
    assert _cli("fit-brdf", TWO[0], "--model", "cook_torrance", "--out", str(out), "--plot", str(plot), *SMALL) == 0
    r = json.loads(out.read_text())
    assert r["material"] == TWO[0] and r["model"] == "cook_torrance" and r["unit"] == "1/sr"
    assert set(r["errors"]) == set(bs.METRICS) and r["error"] == r["errors"]["ngan"]
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "E = " in capsys.readouterr().out
    # a failure while writing the picture leaves neither file
    from fitting import report

    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(report, "brdf_fit_png", broken)
    out2, plot2 = tmp_path / "b.json", tmp_path / "b.png"
    with pytest.raises(OSError):
        _cli("fit-brdf", TWO[0], "--model", "cook_torrance", "--out", str(out2), "--plot", str(plot2), *SMALL)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.json", "fit.png"]


@pytest.mark.parametrize("argv, message", [
    (["fit-brdf", "merl/no-such-material", "--model", "ward"], "no-such-material"),
    (["fit-brdf", "merl/alum-bronze", "--model", "phongg"], "phongg"),
    (["fit-brdf", "merl/alum-bronze", "--model", "disney"], "disney"),
    (["fit-brdf", "merl/alum-bronze", "--model", "ward", "--out", "{tmp}/missing/fit.json"], "does not exist"),
    (["fit-brdf", "merl/alum-bronze", "--model", "ward", "--plot", "{tmp}/fit.jpg"], ".png"),
    (["fit-brdf", "merl/alum-bronze", "--model", "ward", "--sampling", "8,8"], "NH,ND,NP"),
    (["study", "--materials", "merl/alum-bronze,merl/nope", "-o", "{tmp}/s"], "nope"),
    (["study", "--materials", "merl", "--models", "ward,glass", "-o", "{tmp}/s"], "glass"),
    (["study", "--materials", "merl", "-o", "{tmp}/missing/s"], "does not exist"),
    (["study", "--materials", "merl", "-o", "{tmp}/file.txt"], "not a folder"),
    (["study", "--materials", "merl/alum-bronze,{tmp}/file.txt", "-o", "{tmp}/s"], ".binary"),
    (["study", "--materials", "merl/alum-bronze", "--space", "image", "--metric", "log", "-o", "{tmp}/s"],
     "brdf only"),
    (["study", "--materials", "merl/alum-bronze", "--space", "image", "--size", "4,4", "-o", "{tmp}/s"], "between 8"),
    (["study", "--materials", "merl/alum-bronze", "--space", "image", "--size", "64", "-o", "{tmp}/s"], "W,H"),
    (["study", "--materials", "merl/alum-bronze", "--scene", "sphere", "-o", "{tmp}/s"], "image only"),
])
def test_bad_input_is_one_line_and_writes_nothing(brdf_data, tmp_path, capsys, argv, message):
    (tmp_path / "file.txt").write_text("x")
    before = sorted(p.name for p in tmp_path.iterdir())
    assert _cli(*[a.replace("{tmp}", str(tmp_path)) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_tiny_study_writes_consistent_tables(brdf_data, tmp_path, capsys):
    out = tmp_path / "study"
    # --batch 2: both materials in one solve, the compiled programs of the closed-loop tests
    assert _cli("study", "--materials", ",".join(TWO), "--models", "cook_torrance,ward", "-o", str(out),
                "--batch", "2", *SMALL) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(study.OUTPUTS)
    with open(out / "study.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    js = json.loads((out / "study.json").read_text())
    assert [(r["material"], r["model"]) for r in rows] == [(f["material"], f["model"]) for f in js["fits"]]
    assert len(rows) == 4 and js["models"] == ["cook_torrance", "ward"] and js["materials"] == TWO
    for r, f in zip(rows, js["fits"]):
        assert float(r["error"]) == pytest.approx(f["error"], rel=1e-12)
        assert float(r["error_log"]) == pytest.approx(f["errors"]["log"], rel=1e-12)
        for k, v in f["params"].items():
            vals = v if isinstance(v, list) else [v]
            cols = [f"{k}[{c}]" for c in "rgb"] if isinstance(v, list) else [k]
            np.testing.assert_allclose([float(r[c]) for c in cols], vals, rtol=1e-12)
        assert float(r["stderr:rho_d[g]"]) == pytest.approx(f["stderr"]["rho_d"][1], rel=1e-12)
    s = js["summary"]
    assert sum(v["best"] for v in s.values()) == 2
    for m in js["models"]:
        errs = [f["error"] for f in js["fits"] if f["model"] == m]
        assert s[m]["median"] == pytest.approx(float(np.median(errs)))
        assert s[m]["q1"] <= s[m]["median"] <= s[m]["q3"]
    md = (out / "summary.md").read_text()
    assert "cook_torrance" in md and "ward" in md and "1/sr" in md
    for png in ("errors.png", "spheres.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    assert "wrote" in capsys.readouterr().out


def test_study_models_are_the_one_lobe_models():
    names = study.study_models()
    assert {"phong", "blinn_phong", "cook_torrance", "ward", "ashikhmin_shirley"} <= set(names)
    assert not {"lambert", "disney", "glass"} & set(names)


def test_sphere_image_is_the_closed_form_for_lambert():
    """A Lambertian sphere under a distant light: L = ρ/π · max(n·l, 0) per pixel."""
    model = brdfs.get("lambert")
    img = bs.sphere_image(model, model.params(rho_d=0.6), size=33)
    _, wo, idx, cos_i = bs.sphere_directions(33)
    np.testing.assert_allclose(img.reshape(-1, 3)[idx, 1], 0.6 / math.pi * np.maximum(cos_i, 0), rtol=1e-5, atol=1e-7)
    assert np.all(img.reshape(-1, 3)[np.setdiff1d(np.arange(33 * 33), idx)] == 0)
    np.testing.assert_allclose(wo[:, 2], np.sqrt(1 - (np.linalg.norm(wo[:, :2], axis=-1)) ** 2), atol=1e-12)
