"""`jaxrt.sweep` and `jaxrt sweep`: one compiled frame for every model and value, labelled strips.

Expectations are physical or come from the parameter declarations, never from stored renders:
Phong's diffuse term is linear in ρd (so the three frames of a ρd sweep are affine in ρd), a
black sphere with δ = 1 becomes a mirror, and log-scale grids are geometric between the declared bounds.
"""

import numpy as np
import pytest
from PIL import Image

import brdfs
from jaxrt import sweep
import jaxrt as render
from jaxrt.cli import main
from jaxrt.errors import InputError

W, H = 32, 24


@pytest.fixture(scope="module")
def rho_sweep():
    imgs = sweep.sweep("phong", "rho_d", [0.0, 0.5, 1.0], width=W, height=H)
    return imgs, render.frame._cache_size()


def test_rho_d_sweep_is_affine_and_brightening(rho_sweep):
    (a, b, c), _ = rho_sweep
    assert a.shape == (H, W, 3) and all(np.isfinite(x).all() for x in (a, b, c))
    assert np.all(c >= a - 1e-6) and float((c - a).max()) > 0.05  # more diffuse albedo: never darker
    # f = ρd/π + specular: radiance is affine in ρd, so the middle frame is the mean of the others
    np.testing.assert_allclose(b, 0.5 * (a + c), atol=2e-5)


def test_other_models_delta_and_glass_reuse_the_compiled_frame(rho_sweep):
    _, compiled = rho_sweep
    black = {"rho_d": 0.0, "rho_s": 0.0}
    d0, d1 = sweep.sweep("phong", "delta", [0.0, 1.0], width=W, height=H, base_params=black)
    ward = sweep.sweep("ward", "alpha_x", [0.05, 0.5], width=W, height=H)
    glass = sweep.sweep("glass", "n_t", [1.3, 2.0], width=W, height=H)
    assert render.frame._cache_size() == compiled  # no recompilation for new models, δ or n_t
    # a black sphere reflects nothing without δ and becomes a mirror (of floor and sky) with δ = 1:
    changed = np.abs(d1 - d0).max(-1) > 1e-4
    assert changed.sum() >= 10
    assert np.all(d0[changed] == 0.0) and np.all(d1[changed] > 0.0)
    assert not np.allclose(ward[0], ward[1]) and not np.allclose(glass[0], glass[1])


def test_default_values_follow_the_declared_scale():
    s = brdfs.get("phong").param("s")
    np.testing.assert_allclose(sweep.default_values("phong", "s", 4), np.geomspace(*s.typical_range, 4), rtol=1e-9)
    assert s.typical_range == (1.0, 1000.0) and s.hi == 1e6  # the typical span, not the whole range
    np.testing.assert_allclose(sweep.default_values("phong", "rho_s", 3), [0.0, 0.5, 1.0])
    np.testing.assert_allclose(sweep.default_values("phong", "delta", 3), [0.0, 0.5, 1.0])
    v = sweep.default_values("ashikhmin_shirley", "n_u", 5)
    assert v[0] == 1.0 and v[-1] == 10000.0  # clipped into the declared range despite rounding


@pytest.mark.parametrize("model,param,values,match", [
    ("nope", "s", [1.0], "unknown BRDF model"),
    ("phong", "eta", [1.0], "allowed: rho_d, rho_s, s, delta"),
    ("phong", "s", [0.5], r"outside the allowed range \[1, 1e\+06\]"),
    ("glass", "delta", [0.5], "allowed: n_t"),
    ("cook_torrance", "m", [float("nan")], "outside the allowed range"),
])
def test_bad_sweeps_are_one_line_input_errors(model, param, values, match):
    with pytest.raises(InputError, match=match):
        sweep.sweep(model, param, values, width=W, height=H)


def test_strip_png(tmp_path, rho_sweep):
    imgs, _ = rho_sweep
    out = tmp_path / "strip.png"
    sweep.strip_png(out, imgs, sweep.labels("phong", "rho_d", [0, 0.5, 1]), sweep.title("phong", "rho_d"))
    with Image.open(out) as im:
        assert im.format == "PNG" and im.width > 2 * im.height  # three frames side by side
    with pytest.raises(InputError, match="one label per image"):
        sweep.strip_png(tmp_path / "bad.png", imgs, ["only one"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["strip.png"]  # nothing half-written


def test_cli_sweep_writes_a_strip(tmp_path, capsys, rho_sweep):
    out = tmp_path / "s.png"
    rc = main(["sweep", "phong", "s", "--from", "2", "--to", "200", "--steps", "3",
               "--width", str(W), "--height", str(H), "-o", str(out)])
    assert rc == 0 and out.is_file()
    assert "phong.s: 3 frames" in capsys.readouterr().out


@pytest.mark.parametrize("argv,match", [
    (["sweep", "phong", "zz"], "unknown parameter 'zz'"),
    (["sweep", "nope", "s"], "unknown BRDF model"),
    (["sweep", "phong", "s", "--from", "0.5"], r"--from 0.5: phong.s must lie in \[1, 1e\+06\]"),
    (["sweep", "cook_torrance", "eta", "--to", "2000"], r"must lie in \[1, 1000\]"),
    (["sweep", "phong", "s", "--steps", "0"], "--steps"),
    (["sweep", "phong", "s", "-o", "x.jpg"], "must end in .png"),
])
def test_cli_sweep_bad_input(argv, match, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("jaxrt sweep: error:")
    import re

    assert re.search(match, err), err
    assert list(tmp_path.iterdir()) == []
