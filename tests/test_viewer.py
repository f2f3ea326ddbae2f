"""The slider viewer, driven headless (Agg): sliders change the image as physics says and never recompile.

Expectations are independent of the renderer's numbers: more diffuse albedo never darkens a pixel,
a specular highlight follows the light, a log slider's position is log10 of the value declared in
the model's `Param`, and `jaxrt.frame`'s compile cache does not grow after the first frame.
A path-traced scene refines progressively: k refine() passes equal `jaxrt.integrators.path.accumulate` called k
times, the mean over the sphere matches the closed-form furnace radiance, and any change restarts.
"""

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest

import brdfs
from jaxrt.integrators import path
from jaxrt.cli import main
from jaxrt.errors import InputError
from jaxrt.viewer import Viewer, from_slider, orbit_angles, orbit_position, slider_spec

W, H = 32, 24


@pytest.fixture(scope="module")
def viewer():
    v = Viewer("spheres", object="phong", width=W, height=H, frame=True)
    v.figure()
    v.compiled = v.compiles  # the first frame compiled; nothing after it may
    return v


def _set_rgb(v, name, value):
    for c in "rgb":
        v.sliders[f"{name}.{c}"].set_val(value)


def test_rho_d_slider_brightens_and_does_not_recompile(viewer):
    _set_rgb(viewer, "rho_d", 0.0)
    dark = viewer.image.copy()
    _set_rgb(viewer, "rho_d", 1.0)
    bright = viewer.image.copy()
    assert viewer.values["rho_d"] == pytest.approx(1.0)
    assert np.all(bright >= dark - 1e-6) and float((bright - dark).max()) > 0.05
    assert np.isfinite(viewer.frame_time) and "ms" in viewer._title.get_text()
    assert viewer.compiles == viewer.compiled


def test_one_slider_per_channel_keeps_the_colour(viewer):
    """Moving rho_d's green slider changes green only (it used to set all three to one grey value)."""
    _set_rgb(viewer, "rho_d", 0.2)
    viewer.sliders["rho_d.r"].set_val(0.9)
    before = viewer.image.copy()
    viewer.sliders["rho_d.g"].set_val(0.6)
    assert viewer.channels["rho_d"] == pytest.approx([0.9, 0.6, 0.2])
    d = viewer.image - before
    assert float(d[..., 1].max()) > 0.02 and np.abs(d[..., [0, 2]]).max() < 1e-6
    assert viewer.sliders["rho_d.g"].valtext.get_text() == "0.6"
    with pytest.raises(InputError, match="channel"):
        viewer.set_param("s", 10.0, channel=1)
    assert viewer.compiles == viewer.compiled


def test_image_is_framed_on_a_grey_page(viewer):
    ax = viewer._ax
    assert ax.axison and all(sp.get_visible() for sp in ax.spines.values())
    assert viewer.figure().get_facecolor()[:3] != (1.0, 1.0, 1.0)


def test_log_slider_shows_the_value(viewer):
    p = brdfs.get("phong").param("s")
    lo, hi, _ = slider_spec(p)
    assert (lo, hi) == (np.log10(p.lo), np.log10(p.hi))
    viewer.sliders["s"].set_val(2.0)
    assert viewer.values["s"] == pytest.approx(100.0, rel=1e-5)
    assert viewer.sliders["s"].valtext.get_text() == "100"
    assert from_slider(p, 99.0) == p.hi  # clipped into the declared range


def test_highlight_follows_the_light(viewer):
    viewer.set_param("rho_d", 1.0)
    lit = viewer.image.copy()
    viewer.set_param("rho_d", 0.0)
    sphere = np.abs(lit - viewer.image).max(-1) > 1e-4  # the object's lit pixels
    assert sphere.sum() > 30
    viewer.set_param("s", 30.0)
    cols = []
    for x in (-6.0, -2.0, 6.0):
        viewer.sliders["light_x"].set_val(x)
        lum = np.where(sphere, viewer.image.mean(-1), -1.0)
        cols.append(np.unravel_index(lum.argmax(), lum.shape)[1])
    assert cols[0] <= cols[1] <= cols[2] and cols[2] > cols[0]  # moves right with the light
    at60 = viewer.image.copy()  # the scene's 60 W/sr
    viewer.sliders["intensity"].set_val(0.0)
    unlit = viewer.image.copy()  # background and its reflections only
    viewer.sliders["intensity"].set_val(120.0)
    assert float(np.abs(at60 - unlit).max()) > 0.1
    np.testing.assert_allclose(viewer.image, 2 * at60 - unlit, rtol=1e-4, atol=1e-5)  # light adds linearly
    assert viewer.compiles == viewer.compiled


def test_model_switch_and_orbit_reuse_the_compiled_frame(viewer):
    viewer.set_model("phong")
    viewer.set_param("s", 30.0)  # set here, not by an earlier test: xdist may run tests apart
    before = viewer.image.copy()
    viewer.sliders["model"].set_active(brdfs.names().index("ward"))
    assert viewer.model == "ward"
    assert {"alpha_x", "alpha_y", "delta"} <= set(viewer.sliders) and "s" not in viewer.sliders
    assert not np.allclose(before, viewer.image)
    viewer.set_model("glass")
    assert "n_t" in viewer.sliders and "delta" not in viewer.sliders
    viewer.sliders["n_t"].set_val(2.0)
    assert viewer.values["n_t"] == pytest.approx(2.0)
    viewer.set_model("phong")
    assert viewer.values["s"] == pytest.approx(30.0)  # each model keeps its own values
    old = viewer.image.copy()
    viewer.sliders["azimuth"].set_val(viewer.azimuth + 25.0)
    assert not np.allclose(old, viewer.image)
    assert viewer.compiles == viewer.compiled


def test_orbit_geometry():
    look = np.array([1.0, 2.0, 3.0])
    p = orbit_position(look, 5.0, 90.0, 0.0)
    np.testing.assert_allclose(p, [6.0, 2.0, 3.0], atol=1e-5)  # azimuth 90° is +x
    np.testing.assert_allclose(orbit_angles(orbit_position(look, 2.0, -30.0, 40.0), look), (2.0, -30.0, 40.0),
                               atol=1e-4)


def test_bad_viewer_input(viewer):
    with pytest.raises(InputError, match=r"outside the allowed range \[1, 1e\+06\]"):
        viewer.set_param("s", 5e6)
    with pytest.raises(InputError, match="unknown parameter"):
        viewer.set_param("eta", 1.0)
    with pytest.raises(InputError, match="elevation"):
        viewer.orbit(0.0, 95.0)
    with pytest.raises(InputError, match="no object named 'teapot'"):
        Viewer("spheres", object="teapot", width=W, height=H)


def test_cli_view_headless(capsys):
    assert main(["view", "spheres", "--object", "phong", "--width", str(W), "--height", str(H), "--frame"]) == 0
    assert "no interactive matplotlib backend" in capsys.readouterr().out
    assert main(["view", "spheres", "--object", "nope"]) == 2
    assert "no object named 'nope'" in capsys.readouterr().err


# ---- progressive path tracing ------------------------------------------------------------------
PW, SPP = 16, 2


@pytest.fixture(scope="module")
def furnace():
    # a white-furnace sphere lit only by a uniform environment of radiance 1 (scenes/furnace.toml)
    v = Viewer("furnace", width=PW, height=PW, spp=SPP)
    v.figure()
    v.compiled = v.compiles  # the first pass compiled; no later pass or value change may
    return v


def _direct(scene, k):
    """k passes through jaxrt.integrators.path itself, outside the viewer."""
    acc = None
    for _ in range(k):
        acc = path.accumulate(scene, acc)
    return np.asarray(acc.image), int(acc.count)


def test_refine_accumulates_the_path_tracer_passes(furnace):
    v = furnace
    v.set_param("rho_d", 1.0)  # a change: starts again from pass 0
    assert v.progressive and v.samples == SPP and int(v.accumulation.passes) == 1
    first = v.image.copy()
    counts = [v.samples]
    for _ in range(4):
        v.refine()
        counts.append(v.samples)
    assert counts == [SPP * k for k in range(1, 6)]
    assert f"{5 * SPP} spp" in v._title.get_text()
    img, count = _direct(v.scene, 5)
    assert count == 5 * SPP
    np.testing.assert_array_equal(v.image, img)
    assert not np.array_equal(first, v.image)  # later passes use new random streams
    v._tick()  # what the window's idle timer calls
    assert v.samples == 6 * SPP
    assert v.compiles == v.compiled


def test_progressive_furnace_closed_form_and_reset(furnace):
    # A convex Lambert sphere under a uniform environment L_e = 1 reflects L = rho_d * L_e (every
    # reflected ray escapes); pixels that miss the sphere see L_e exactly.
    v = furnace
    _set_rgb(v, "rho_d", 0.5)
    assert v.samples == SPP and int(v.accumulation.passes) == 1  # the slider restarted the accumulation
    np.testing.assert_array_equal(v.image, _direct(v.scene, 1)[0])
    for _ in range(7):
        v.refine()
    y, x = np.mgrid[:PW, :PW] + 0.5
    r = np.hypot(x - PW / 2, y - PW / 2)
    # the sphere's image radius is tan(asin(1/4)) / tan(vfov/2) * PW/2 = 6.55 pixels
    inside, outside = r < 5.0, r > 8.0
    assert np.isfinite(v.image).all()
    assert abs(float(v.image[inside].mean()) - 0.5) < 0.02
    np.testing.assert_allclose(v.image[outside], 1.0, rtol=1e-6)
    n = v.samples
    v.refine()
    v.orbit(v.azimuth + 20.0, v.elevation)  # camera, model and value changes restart too
    assert v.samples == SPP
    v.refine()
    v.set_model("phong")
    assert v.samples == SPP and v.model == "phong" and n == 8 * SPP
    v.set_model("lambert")
    assert v.compiles == v.compiled


def test_notebook_controls_without_point_lights(furnace):
    from jaxrt.viewer import notebook_controls

    _, sliders = notebook_controls(furnace)
    assert "light_x" not in sliders and "intensity" not in sliders
    assert {"rho_d.r", "rho_d.g", "rho_d.b"} <= set(sliders) and "rho_d" not in sliders
    furnace.refine()
    sliders["elevation"].value = 10.0  # a widget change restarts the accumulation
    assert furnace.samples == SPP and furnace.elevation == pytest.approx(10.0)
    assert furnace.compiles == furnace.compiled


def test_whitted_viewer_does_not_refine(viewer):
    before = viewer.image.copy()
    assert not viewer.progressive and viewer.accumulation is None
    assert viewer.refine() is viewer.image and np.array_equal(before, viewer.image)
    assert "spp" not in viewer.status()


def test_cli_view_integrator_option(capsys):
    assert main(["view", "furnace", "--integrator", "bidir"]) == 2
    assert "integrator: 'bidir' is not allowed; allowed: whitted, path" in capsys.readouterr().err


# ---- several devices ----------------------------------------------------------------------------


def test_cli_view_bad_devices_is_a_one_line_error(capsys):
    assert main(["view", "spheres", "--devices", "0"]) == 2
    err = capsys.readouterr().err
    assert "--devices 0" in err and "'all' or a number" in err and len(err.strip().splitlines()) == 1
    assert main(["view", "spheres", "--devices", "99"]) == 2  # more than this host has: checked before rendering
    assert "--devices 99" in capsys.readouterr().err


_DEVICES = r"""
import json, sys
import matplotlib
matplotlib.use("Agg")
import numpy as np
import jax
import jaxrt
from jaxrt import integrators
from jaxrt.integrators import path
from jaxrt.viewer import Viewer

out = {"devices": len(jax.devices())}
if sys.argv[1] == "whitted":
    # the viewer's frame on 4 devices, after a slider change, against jaxrt.render on 4 devices and
    # against one device's frame
    v = Viewer("spheres", object="phong", width=24, height=18, devices=4)
    v.set_param("s", 150.0)
    split = np.asarray(jaxrt.render(v.scene, devices=4))
    one = np.asarray(integrators.frame(v.scene))
    d = np.abs(v.image - one)
    out.update(tiles=v._plan.tiles, same_as_render=bool(np.array_equal(v.image, split)), max=float(d.max()),
               beyond=float(np.mean(d.max(-1) / np.maximum(one.max(-1), 1e-2) > 1e-4)), peak=float(one.max()))
else:
    # progressive path tracing: three idle passes against three one-device passes
    f = Viewer("furnace", width=16, height=16, spp=2, devices=4)
    f.refine(); f.refine()
    acc = None
    for _ in range(3):
        acc = path.accumulate(f.scene, acc)
    ref = np.asarray(acc.image, np.float64)
    d = np.abs(np.asarray(f.image, np.float64) - ref)
    out.update(tiles=f._plan.tiles, measured=f._plan.costs is not None, count=int(f.accumulation.count),
               max=float(d.max()), mean_ref=float(ref.mean()))
    f.orbit(20.0, 10.0)  # a change starts again from pass 0, timing the tiles again
    out["reset"] = int(f.accumulation.count)
print(json.dumps(out))
"""


def _on_4_devices(part: str) -> dict:
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    e = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])))
    r = subprocess.run([sys.executable, "-c", _DEVICES, part], cwd=root, env=e, capture_output=True, text=True,
                       timeout=900, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["devices"] == 4
    return out


@pytest.mark.slow  # the sharded Whitted program on 4 virtual devices and the one-device frame
def test_viewer_whitted_frame_on_4_devices_is_jaxrt_renders():
    """`Viewer(devices=4)` on four virtual CPU devices (a subprocess): the frame after a slider change
    is `jaxrt.render(devices=4)`'s bit for bit and one device's within the rounding of another XLA
    module (`tests/test_tiles.py`'s bound)."""
    w = _on_4_devices("whitted")
    assert w["tiles"] >= 8 and w["same_as_render"], w
    assert w["beyond"] <= 0.01 and w["max"] <= 1e-3 * w["peak"] and w["peak"] > 0.1, w


@pytest.mark.slow  # the timed tile program compiles once per virtual device, then the cost-scheduled pass
def test_viewer_progressive_passes_on_4_devices_equal_one_devices():
    """Idle passes of `Viewer(devices=4)`: the first timed, the later ones scheduled by cost; three
    equal three `path.accumulate` passes within float32 rounding, and a change starts again."""
    p = _on_4_devices("path")
    assert p["tiles"] >= 4 and p["measured"] and p["count"] == 6
    assert p["max"] <= 1e-5 * max(p["mean_ref"], 1.0) and p["mean_ref"] > 0.1, p
    assert p["reset"] == 2


# ---- progressive photon mapping ----------------------------------------------------------------
def check_sppm_refine_runs_several_passes_a_call(tmp_path):
    """An SPPM viewer's first refine after a change runs one pass, later ones `passes_per_call`
    passes in one call (here forced to 3): the image equals that many single passes through
    `jaxrt.integrators.sppm` itself, bit for bit, and no refine compiles anything."""
    from jaxrt.integrators import sppm

    sppm.passes_per_call = lambda seconds, remaining, target=sppm.CALL_SECONDS: 3  # its own process
    scene = tmp_path / "lamp.toml"  # a Lambert floor and ball under a point light: a small program
    scene.write_text("""
[camera]
position = [0.0, 1.5, 3.0]
look_at = [0.0, 0.4, 0.0]
width = 8
height = 6
[render]
integrator = "sppm"
max_depth = 3
photons = 256
[[lights]]
position = [1.0, 3.0, 1.0]
intensity = 5.0
[materials.white]
model = "lambert"
rho_d = 0.7
[[objects]]
primitive = "plane"
size = [4.0, 4.0]
material = "white"
[[objects]]
primitive = "sphere"
radius = 0.4
subdivisions = 2
translate = [0.0, 0.4, 0.0]
material = "white"
""")
    v = Viewer(scene)
    compiled = v.compiles
    assert v.samples == 1  # the first pass, from render()
    v.refine()
    v.refine()
    assert v.samples == 7
    st = sppm.start(v.scene)
    for _ in range(7):
        st = sppm.step(v.scene, st)
    np.testing.assert_array_equal(v.image, np.asarray(st.image))
    assert v.compiles == compiled


@pytest.mark.slow  # an SPPM pass compiles: ~70 CPU seconds on the 2-core CPU without a warm cache
def test_sppm_refine_runs_several_passes_a_call(tmp_path):
    """`check_sppm_refine_runs_several_passes_a_call` in a process of its own: XLA:CPU once crashed
    (a segmentation fault inside the compiler) compiling this program in a test worker that had
    compiled many others before; in a fresh process it compiles as a render's does."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys; from pathlib import Path; sys.path.insert(0, sys.argv[1]); import test_viewer as T; "
            "T.check_sppm_refine_runs_several_passes_a_call(Path(sys.argv[2]))")
    r = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent), str(tmp_path)], capture_output=True,
                       text=True, timeout=900, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
