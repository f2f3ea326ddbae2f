"""Measured materials in scene files (`model = "measured"`, `data = NAME | FILE`): they parse, render
with both integrators to the value computed directly from `brdfs.measured`, and bad references give
one line (exit code 2 from the CLI)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import brdfs
import jaxrt as R
from brdfs import measured, merl
from jaxrt import camera, cli
from jaxrt import scene as S
from jaxrt.errors import InputError

MATERIAL = "merl/gold-metallic-paint"
LIGHT = np.array([0.6, 1.5, 0.4])
INTENSITY = np.array([3.0, 2.5, 2.0])


def plane_doc(material: dict, **render) -> dict:
    """A floor (y = 0, normal +y) in `material`, seen obliquely, under one point light; Whitted,
    one sample per pixel at the pixel centres, direct light only."""
    return {
        "camera": {"position": [0.0, 1.2, 2.0], "look_at": [0.0, 0.0, 0.0], "vfov": 40.0, "width": 12, "height": 10},
        "lights": [{"position": LIGHT.tolist(), "intensity": INTENSITY.tolist()}],
        "materials": {"m": material},
        "objects": [{"name": "floor", "primitive": "plane", "size": [20.0, 20.0], "material": "m"}],
        "render": {"max_depth": 1, "spp": 1, **render},
    }


def direct_floor(cam, model, p) -> np.ndarray:
    """f(wi, wo) cosθi I / r² at every pixel's floor hit, computed here: the camera rays through the
    pixel centres met with y = 0 in float64, the BRDF evaluated in the frame (x, n × x, n) of the
    floor's normal n = +y (any frame about n: the measured models are isotropic)."""
    o, d = (np.asarray(x, np.float64) for x in camera.generate_rays(cam, 1, 0, False))
    t = -o[:, 1] / d[:, 1]
    x = o + t[:, None] * d
    to_l = LIGHT - x
    r2 = np.sum(to_l * to_l, -1)
    wi_w = to_l / np.sqrt(r2)[:, None]
    wo_w = -d / np.linalg.norm(d, axis=-1, keepdims=True)
    frame = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # rows t, b = n × t, n
    wi, wo = wi_w @ frame.T, wo_w @ frame.T
    f = np.asarray(model.eval(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)), np.float64)
    rad = f * (wi[:, 2] * np.where(t > 0, 1.0, 0.0))[:, None] * INTENSITY / r2[:, None]
    return rad.reshape(cam.height, cam.width, 3)


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_neural_material_renders_the_direct_value_with_both_integrators(brdf_data):
    sc = S.load(plane_doc({"model": "measured", "data": MATERIAL}))
    assert sc.materials.models == ("nbrdf",)
    img = np.asarray(R.frame(sc))
    assert np.all(np.isfinite(img)) and img.max() > 0
    model, p = measured.load(MATERIAL)
    ref = direct_floor(sc.camera, model, p)
    np.testing.assert_allclose(img, ref, rtol=2e-4, atol=1e-6 * ref.max())
    # the path tracer's estimate with point lights only and max_depth 1 is the Whitted image
    sc_p = S.load(plane_doc({"model": "measured", "data": MATERIAL}, integrator="path"))
    np.testing.assert_allclose(np.asarray(R.frame(sc_p)), img, rtol=2e-4, atol=1e-6 * ref.max())


@pytest.mark.slow  # 11 s on 2 cores
def test_two_measured_materials_each_shade_their_own_object(brdf_data):
    # two rows of one measured model: each hit must use its own row (at_hits), not row 0
    doc = plane_doc({"model": "measured", "data": MATERIAL})
    doc["materials"]["n"] = {"model": "measured", "data": "merl/blue-acrylic"}
    doc["objects"] = [
        {"name": "left", "primitive": "plane", "size": [20.0, 20.0], "translate": [-10.0, 0.0, 0.0], "material": "m"},
        {"name": "right", "primitive": "plane", "size": [20.0, 20.0], "translate": [10.0, 0.0, 0.0], "material": "n"},
    ]
    sc = S.load(doc)
    img = np.asarray(R.frame(sc))
    ref_m = direct_floor(sc.camera, *measured.load(MATERIAL))
    ref_n = direct_floor(sc.camera, *measured.load("merl/blue-acrylic"))
    o, d = (np.asarray(x, np.float64) for x in camera.generate_rays(sc.camera, 1, 0, False))
    x = (o[:, 0] - o[:, 1] / d[:, 1] * d[:, 0]).reshape(sc.camera.height, sc.camera.width)
    ref = np.where((x < 0)[..., None], ref_m, ref_n)
    away = np.abs(x) > 0.05  # pixels off the seam between the two planes
    np.testing.assert_allclose(img[away], ref[away], rtol=2e-4, atol=1e-6 * ref.max())
    assert not np.allclose(ref_m[away], ref_n[away], rtol=0.1)


@pytest.mark.slow
def test_path_tracer_with_bounces_is_finite(brdf_data):
    doc = plane_doc({"model": "measured", "data": MATERIAL}, integrator="path", spp=4, max_depth=3)
    doc["objects"].append({"name": "ball", "primitive": "sphere", "radius": 0.3, "subdivisions": 2,
                           "translate": [0.0, 0.3, 0.0], "material": "m"})
    img = np.asarray(R.frame(S.load(doc)))
    assert np.all(np.isfinite(img)) and img.max() > 0


@pytest.fixture(scope="module")
def lambert_binary(tmp_path_factory):
    """A MERL .binary file tabulating a Lambert BRDF (a constant table: trilinear interpolation of it
    is exact), and the Lambert model's parameters."""
    model = brdfs.get("lambert")
    p = model.params(rho_d=[0.6, 0.3, 0.15])
    path = tmp_path_factory.mktemp("merl") / "lambert.binary"
    merl.write(path, merl.tabulate(model, p))
    return path, model, p


def test_merl_file_relative_to_the_scene_renders_like_its_analytic_source(lambert_binary, tmp_path):
    path, model, p = lambert_binary
    (tmp_path / "brdfs").mkdir()
    (tmp_path / "brdfs" / path.name).symlink_to(path)
    spec = S.parse(plane_doc({"model": "measured", "data": "brdfs/lambert.binary"}), base_dir=tmp_path)
    assert spec.materials["m"].model == "merl" and spec.materials["m"].data == str(tmp_path / "brdfs" / path.name)
    img = np.asarray(R.frame(S.build(spec)))
    ref = np.asarray(R.frame(S.load(plane_doc({"model": "lambert", "rho_d": [0.6, 0.3, 0.15]}))))
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-7)
    assert ref.max() > 0


def bad(doc, *needles, base_dir=None):
    with pytest.raises(InputError) as e:
        S.parse(doc, base_dir=base_dir)
    msg = str(e.value)
    assert "\n" not in msg, msg
    for n in needles:
        assert n in msg, msg
    return msg


def test_bad_measured_references_give_one_line(brdf_data, tmp_path):
    def mat(**kw):
        return plane_doc({"model": "measured", **kw})

    bad(mat(data="merl/gold-metalic-paint"), "[materials.m] data", "unknown measured material",
        "merl/gold-metallic-paint")  # a close match is suggested
    bad(mat(data="nope/gold"), "[materials.m] data", "unknown measured-material collection")
    bad(mat(data="scans/missing.h5"), "[materials.m] data", "no such file", str(tmp_path / "scans"),
        base_dir=tmp_path)
    bad(mat(data="material.json"), "[materials.m] data", ".h5", ".binary")
    bad(mat(data="picture.png"), "[materials.m] data", ".h5", ".binary")
    bad(mat(), "[materials.m] data", "required")
    bad(mat(data=3), "[materials.m] data", "expected a string")
    bad(mat(data=MATERIAL, rho_d=0.5), "[materials.m] rho_d", "unknown key", "data, delta, emission")
    bad(mat(data=MATERIAL, delta=2.0), "[materials.m] delta", "outside the allowed range")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all")
    bad(mat(data="junk.h5"), "[materials.m] data", "junk.h5", "not a readable HDF5", base_dir=tmp_path)
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as fh:
        fh["dense_1/dense_1/kernel:0"] = np.zeros((6, 8), np.float32)
    bad(mat(data="other.h5"), "[materials.m] data", "6-21-21-3", base_dir=tmp_path)
    (tmp_path / "short.binary").write_bytes(np.asarray([90, 90, 180], "<i4").tobytes() + b"\0" * 64)
    bad(mat(data="short.binary"), "[materials.m] data", "not a MERL .binary BRDF", base_dir=tmp_path)
    (tmp_path / "dir.h5").mkdir()
    bad(mat(data="dir.h5"), "[materials.m] data", "is a directory", base_dir=tmp_path)
    bad(plane_doc({"model": "measurd", "data": MATERIAL}), "[materials.m] model", "measured", "lambert")


def test_confined_scene_refuses_a_measured_file_outside(brdf_data, tmp_path, lambert_binary):
    path, _, _ = lambert_binary
    with pytest.raises(InputError, match="outside the scene's folder"):
        S.parse(plane_doc({"model": "measured", "data": str(path)}), base_dir=tmp_path, confine=True)
    # material names are registry lookups, always allowed
    S.parse(plane_doc({"model": "measured", "data": MATERIAL}), base_dir=tmp_path, confine=True)


def test_cli_exit_code_2_for_a_bad_measured_material(brdf_data, tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text("""
[camera]
position = [0.0, 1.2, 2.0]
look_at = [0.0, 0.0, 0.0]
width = 8
height = 6
[[lights]]
position = [0.6, 1.5, 0.4]
intensity = 3.0
[materials.m]
model = "measured"
data = "merl/no-such-paint"
[[objects]]
primitive = "plane"
material = "m"
""")
    rc = cli.main(["render", str(tmp_path / "s.toml"), "-o", str(tmp_path / "o.exr"), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "s.toml: [materials.m] data: unknown measured material 'merl/no-such-paint'" in err
    assert not (tmp_path / "o.exr").exists()


FIT_SCENE = """
[camera]
position = [0.0, 0.9, 2.4]
look_at = [0.0, 0.35, 0.0]
vfov = 30.0
width = 20
height = 20
[render]
max_depth = 1
[[lights]]
position = [1.5, 2.5, 2.0]
intensity = 8.0
[materials.gold]
model = "measured"
data = "merl/gold-metallic-paint"
[materials.floor]
model = "lambert"
rho_d = 0.5
[[objects]]
name = "ball"
primitive = "sphere"
radius = 0.35
subdivisions = 3
translate = [0.0, 0.35, 0.0]
material = "gold"
[[objects]]
primitive = "plane"
size = [10.0, 10.0]
material = "floor"
"""


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_jaxrt_fit_of_an_analytic_model_to_a_measured_render(brdf_data, tmp_path, capsys):
    # a measured material is a target like any other: render it, then fit Ward to the render
    import json

    scene, target, out = tmp_path / "gold.toml", tmp_path / "gold.exr", tmp_path / "fit.json"
    scene.write_text(FIT_SCENE)
    assert cli.main(["render", str(scene), "-o", str(target), "-q"]) == 0, capsys.readouterr().err
    rc = cli.main(["fit", str(target), "--scene", str(scene), "--model", "ward", "--starts", "2",
                   "--max-steps", "40", "--out", str(out), "-q"])
    assert rc == 0, capsys.readouterr().err
    fit = json.loads(out.read_text())
    assert fit["model"] == "ward" and np.all(np.isfinite(fit["params"]["rho_s"]))
    # one specular lobe reproduces the gold sphere's pixels to within a fifth of their RMS, and its
    # specular colour is gold's: more red than green than blue
    assert fit["relative_rmse"] < 0.2, fit["relative_rmse"]
    r, g, b = fit["params"]["rho_s"]
    assert r > g > b, fit["params"]


@pytest.mark.slow
def test_viewer_offers_the_objects_measured_material(brdf_data, tmp_path):
    from jaxrt.viewer import Viewer

    scene = tmp_path / "gold.toml"
    scene.write_text(FIT_SCENE)
    v = Viewer(scene, object="ball", width=12, height=12)
    assert v.model == "nbrdf" and v.models == brdfs.names() + ("nbrdf",)
    assert [p.name for p in v.spec] == ["delta"] and set(v.values) == {"delta"}
    own = v.image.copy()
    v.set_model("phong")
    assert not np.allclose(v.image, own)
    v.set_model("nbrdf")
    np.testing.assert_array_equal(v.image, own)
    with pytest.raises(InputError, match="can wear"):
        v.set_model("merl")
