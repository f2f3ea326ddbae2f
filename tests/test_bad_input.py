"""Inputs that must give one-line errors (exit code 2) before any work, never a traceback, an
overflow or a silently black image: float32 limits, output paths, lights that give nothing, CLI
option ranges, mesh and scene-file errors, duplicate names, fit targets, and `--confine`.
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import numpy as np
import pytest

from jaxrt import cli
from jaxrt import scene as S
from jaxrt.errors import InputError


def tiny(**changes) -> dict:
    """A small valid scene (8x6, two primitives, one point light) with `changes` merged per table."""
    d = {
        "camera": {"position": [0.0, 1.0, 4.0], "look_at": [0.0, 0.5, 0.0], "width": 8, "height": 6},
        "lights": [{"position": [2.0, 4.0, 3.0], "intensity": 20.0}],
        "materials": {"red": {"model": "lambert", "rho_d": [0.7, 0.2, 0.2]}},
        "objects": [
            {"name": "ball", "primitive": "sphere", "radius": 0.5, "subdivisions": 1,
             "translate": [0.0, 0.5, 0.0], "material": "red"},
            {"name": "floor", "primitive": "plane", "size": [4.0, 4.0], "material": "red"},
        ],
    }
    for table, value in changes.items():
        if isinstance(value, dict) and isinstance(d.get(table), dict):
            d[table].update(value)
        else:
            d[table] = value
    return d


def bad(doc, *needles, **kw) -> str:
    with pytest.raises(InputError) as e:
        S.parse(doc, **kw)
    msg = str(e.value)
    assert "\n" not in msg, msg
    for n in needles:
        assert n in msg, msg
    return msg


def run_cli(argv, capsys) -> tuple[int, str]:
    """Run `jaxrt ARGV` in-process; (exit code, stderr). argparse's own exits count as exit codes."""
    try:
        rc = cli.main([str(a) for a in argv])
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    return rc, err


def one_line_error(rc, err, *needles):
    assert rc == 2, (rc, err)
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]


# ---------------------------------------------------------------------------------------------
# 2. float32 limits: every scene number must be representable and keep the renderer finite


def _set(doc, path, value):
    cur = doc
    for k in path[:-1]:
        cur = cur[k]
    cur[path[-1]] = value
    return doc


@pytest.mark.parametrize("path,value,needle", [
    (("lights", 0, "intensity"), 1e39, "[[lights] #1] intensity"),
    (("lights", 0, "intensity"), [1.0, 3.5e38, 1.0], "[[lights] #1] intensity"),
    (("lights", 0, "position"), [1e39, 0.0, 0.0], "[[lights] #1] position"),
    (("camera", "position"), [0.0, 1e39, 4.0], "[camera] position"),
    (("camera", "look_at"), [0.0, 0.0, -1e39], "[camera] look_at"),
    (("camera", "aperture"), 1e39, "[camera] aperture"),
    (("camera", "focus_distance"), 1e39, "[camera] focus_distance"),
    (("objects", 0, "translate"), [1e39, 0.0, 0.0], "[[objects] #1] translate"),
    (("objects", 0, "radius"), 1e39, "[[objects] #1] radius"),
    (("objects", 0, "scale"), 1e39, "[[objects] #1] scale"),
    (("objects", 1, "size"), [1e39, 1.0], "[[objects] #2] size"),
    (("materials", "red", "emission"), 1e39, "[materials.red] emission"),
])
def test_values_beyond_float32_are_refused_by_the_parser(path, value, needle):
    msg = bad(_set(tiny(), path, value), needle)
    assert "1e+18" in msg  # the representable bound is stated


def test_background_and_environment_beyond_float32_are_refused():
    bad(tiny(render={"background": 1e39}), "[render] background")
    bad(tiny(environment={"radiance": 1e39}), "[environment] radiance")
    bad(tiny(environment={"radiance": 1.0, "scale": 1e39}), "[environment] scale")


def test_lens_that_loses_the_scene_is_refused():
    # each value is representable; together the rays start 5e17 off the axis of a 4-unit focus
    bad(tiny(camera={"aperture": 1e18, "focus_distance": 4.0}), "[camera] aperture", "focus_distance")
    bad(tiny(camera={"focus_distance": 1e-30}), "[camera] focus_distance", "1e-12")
    sc = S.load(tiny(camera={"aperture": 0.5, "focus_distance": 4.0}))
    with pytest.raises(InputError, match="focus_distance"):
        sc.with_camera(aperture=1e6)
    with pytest.raises(InputError, match="focus_distance"):
        sc.with_camera(focus_distance=1e-30)


def test_pinhole_image_does_not_depend_on_the_focus_distance():
    from jaxrt import integrators

    ref = np.asarray(integrators.frame(S.load(tiny())))
    small = np.asarray(integrators.frame(S.load(tiny(camera={"focus_distance": 1e-9}))))
    assert ref.max() > 0
    np.testing.assert_allclose(small, ref, rtol=1e-4, atol=1e-6)


def test_camera_that_collapses_in_float32_is_refused():
    # distinct in float64, the same point in float32: the view direction would be 0/0
    bad(tiny(camera={"position": [1e9, 0.0, 0.0], "look_at": [1e9 + 1.0, 0.0, 0.0]}), "[camera] look_at")


def test_geometry_that_overflows_after_its_transform_is_refused():
    # radius and scale are each representable, their product squared is not
    doc = tiny()
    doc["objects"][0].update(radius=1e17, scale=1e17)
    with pytest.raises(InputError) as e:
        S.build(S.parse(doc))
    assert "'ball'" in str(e.value) and "1e+18" in str(e.value)


def test_texture_uv_transform_beyond_float32_is_refused():
    doc = tiny()
    doc["materials"]["red"]["rho_d"] = {"checker": [0.1, 0.9], "scale": 1e39}
    bad(doc, "materials.red.rho_d", "scale")


def test_value_updates_check_float32_limits():
    sc = S.load(tiny())
    for call in (lambda: sc.with_light(0, position=[1e39, 0.0, 0.0]),
                 lambda: sc.with_light(0, intensity=1e39),
                 lambda: sc.with_camera(position=[0.0, 1e39, 0.0]),
                 lambda: sc.with_camera(aperture=1e39),
                 lambda: sc.with_camera(vfov=400.0),
                 lambda: sc.with_camera(look_at=[0.0, 1.0, 4.0])):  # = position
        with pytest.raises(InputError):
            call()


def test_param_check_refuses_values_that_overflow_float32():
    from brdfs.base import Param

    p = Param("k", 1.0, 0.0, math.inf)
    assert p.check(3e38) == np.float32(3e38)
    with pytest.raises(InputError, match="float32"):
        p.check(1e39)


def test_environment_map_whose_scale_overflows_float32_is_refused():
    from jaxrt import envmap

    with pytest.raises(InputError, match="environment map"):
        envmap.from_array(np.full((2, 4, 3), 1e30), scale=1e10)


# ---------------------------------------------------------------------------------------------
# 3. outputs are checked before any work, and a command writes all of them or none


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


@pytest.mark.parametrize("target", ["/sys/out.exr", "/proc/out.exr"])
def test_render_to_an_unwritable_folder_fails_before_work(target, capsys):
    rc, err = run_cli(["render", "spheres", "-o", target, "-q"], capsys)
    one_line_error(rc, err, "-o", target)
    assert ".out.exr." not in err  # names the output, not a temporary file


def test_render_writes_no_output_when_another_is_bad(tmp_path, capsys):
    (tmp_path / "adir.png").mkdir()
    rc, err = run_cli(["render", "spheres", "-o", tmp_path / "ok.exr", "--png", tmp_path / "adir.png",
                       "--width", 8, "--height", 6, "-q"], capsys)
    one_line_error(rc, err, "--png", "directory")
    assert _listing(tmp_path) == ["adir.png"]


def test_render_writes_every_output_and_no_temporary_file(tmp_path, capsys):
    from jaxrt import image

    scene = tmp_path / "s.toml"
    scene.write_text('[camera]\nposition = [0.0, 1.0, 4.0]\nlook_at = [0.0, 0.5, 0.0]\nwidth = 8\nheight = 6\n'
                     '[[lights]]\nposition = [2.0, 4.0, 3.0]\nintensity = 20.0\n[materials.m]\nmodel = "lambert"\n'
                     '[[objects]]\nprimitive = "sphere"\nsubdivisions = 1\nmaterial = "m"\n')
    (tmp_path / "a.png").write_text("old")
    rc, err = run_cli(["render", scene, "-o", tmp_path / "a.exr", "--png", tmp_path / "a.png", "-q"], capsys)
    assert rc == 0, err
    assert _listing(tmp_path) == ["a.exr", "a.png", "s.toml"]
    assert image.read_exr(tmp_path / "a.exr").shape == (6, 8, 3)
    assert (tmp_path / "a.png").read_bytes()[:4] == b"\x89PNG"
    assert oct((tmp_path / "a.exr").stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_render_says_when_the_image_is_black(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text('[camera]\nposition = [0.0, 1.0, 4.0]\nlook_at = [0.0, 0.5, 0.0]\nwidth = 8\nheight = 6\n'
                     '[[lights]]\nposition = [0.0, -3.0, 0.0]\nintensity = 20.0\n'  # under the floor
                     '[materials.m]\nmodel = "lambert"\n[[objects]]\nprimitive = "plane"\nsize = [50.0, 50.0]\n'
                     'material = "m"\n')
    rc, err = run_cli(["render", scene, "-o", tmp_path / "a.exr", "-q"], capsys)
    assert rc == 0 and "black everywhere" in err, err


def test_fit_checks_plot_and_out_before_work(tmp_path, capsys):
    (tmp_path / "p.png").mkdir()
    rc, err = run_cli(["fit", "--demo", "--out", tmp_path / "f.json", "--plot", tmp_path / "p.png", "-q"], capsys)
    one_line_error(rc, err, "--plot", "directory")
    assert _listing(tmp_path) == ["p.png"]


def test_fit_demo_checks_its_default_plot_path(tmp_path, capsys, monkeypatch):
    (tmp_path / "fit_demo.png").mkdir()
    monkeypatch.chdir(tmp_path)
    rc, err = run_cli(["fit", "--demo", "-q"], capsys)
    one_line_error(rc, err, "fit_demo.png", "directory")


@pytest.mark.parametrize("argv", [
    ["brdf-report", "-o", "{d}/x.png"],
    ["fit-matrix", "--models", "lambert,phong", "-o", "{d}/x.png", "-q"],
    ["sweep", "phong", "s", "--steps", "2", "-o", "{d}/x.png", "-q"],
])
def test_other_commands_refuse_a_directory_as_output(argv, tmp_path, capsys):
    (tmp_path / "x.png").mkdir()
    rc, err = run_cli([a.format(d=tmp_path) for a in argv], capsys)
    one_line_error(rc, err, "-o", "directory")


def test_fit_matrix_writes_no_json_when_the_png_is_bad(tmp_path, capsys):
    rc, err = run_cli(["fit-matrix", "--models", "lambert", "-o", tmp_path / "x.exr", "--out",
                       tmp_path / "m.json", "-q"], capsys)
    one_line_error(rc, err, "-o", ".png")
    assert _listing(tmp_path) == []


def test_outputs_commit_all_or_none(tmp_path):
    from jaxrt.fsutil import Outputs

    a, b = tmp_path / "a.exr", tmp_path / "b.png"
    a.write_text("old a")
    outs = Outputs()
    outs.add(a, ".exr", "-o")
    outs.add(b, ".png", "--png")
    with pytest.raises(RuntimeError):
        with outs.writing() as tmp:
            tmp[a].write_text("new a")
            raise RuntimeError("the second writer fails")
    assert a.read_text() == "old a" and not b.exists()
    assert _listing(tmp_path) == ["a.exr"]  # no temporary files left
    with outs.writing() as tmp:
        tmp[a].write_text("new a")
        tmp[b].write_text("new b")
    assert a.read_text() == "new a" and b.read_text() == "new b"
    assert _listing(tmp_path) == ["a.exr", "b.png"]


def test_outputs_refuse_bad_paths(tmp_path):
    from jaxrt.fsutil import Outputs

    (tmp_path / "d.png").mkdir()
    for path, suffix, needle in [
        (tmp_path / "d.png", ".png", "directory"),
        (tmp_path / "x.jpg", ".png", ".png"),
        (tmp_path / "missing" / "x.png", ".png", "does not exist"),
        ("/sys/x.png", ".png", "cannot write"),
    ]:
        with pytest.raises(InputError) as e:
            Outputs().add(path, suffix, "-o")
        assert needle in str(e.value) and "-o" in str(e.value), str(e.value)
    outs = Outputs()
    outs.add(tmp_path / "x.png", ".png", "-o")
    with pytest.raises(InputError, match="also"):
        outs.add(tmp_path / "." / "x.png", ".png", "--plot")


# ---------------------------------------------------------------------------------------------
# 5. lights that give nothing


def _lamp_scene(integrator="whitted", facing=True):
    """Only an emissive quad facing the camera (rho_d = 0: it reflects nothing) and no point light."""
    return tiny(
        camera={"position": [0.0, 0.0, 3.0], "look_at": [0.0, 0.0, 0.0], "width": 8, "height": 6},
        lights=[],
        materials={"lamp": {"model": "lambert", "rho_d": 0.0, "emission": [2.0, 1.0, 0.5]}},
        objects=[{"name": "quad", "primitive": "plane", "size": [1.5, 1.5],
                  "rotate": [90.0 if facing else -90.0, 0.0, 0.0], "material": "lamp"}],
        render={"integrator": integrator, "max_depth": 1},
    )


def test_zero_emission_is_not_a_light():
    doc = _lamp_scene()
    doc["materials"]["lamp"]["emission"] = 0.0
    bad(doc, "lights")


@pytest.mark.parametrize("facing", [True, False])
def test_whitted_sees_emitters_as_the_path_tracer_does(facing):
    from jaxrt import integrators

    w = np.asarray(integrators.frame(S.load(_lamp_scene("whitted", facing))))
    p = np.asarray(integrators.frame(S.load(_lamp_scene("path", facing))))
    np.testing.assert_allclose(w, p, rtol=1e-6, atol=1e-7)
    if facing:
        assert np.isclose(w.max(), 2.0) and (w[..., 0] == 2.0).sum() > 4
    else:  # emitters are one-sided in both integrators
        assert w.max() == 0.0


def test_whitted_sees_emitters_in_mirrors():
    from jaxrt import integrators

    doc = _lamp_scene()
    doc["camera"].update(position=[0.0, 3.0, 3.0], look_at=[0.0, 0.0, 0.0])
    doc["materials"]["mirror"] = {"model": "lambert", "rho_d": 0.0, "delta": 1.0}
    doc["objects"] = [
        # faces down, away from the camera, where the floor reflects the view through the centre
        {"name": "quad", "primitive": "plane", "size": [1.0, 1.0], "rotate": [180.0, 0.0, 0.0],
         "translate": [0.0, 1.0, -1.0], "material": "lamp"},
        {"name": "floor", "primitive": "plane", "size": [20.0, 20.0], "material": "mirror"},
    ]
    doc["render"]["max_depth"] = 2
    img = np.asarray(integrators.frame(S.load(doc)))
    assert np.isclose(img[..., 0].max(), 2.0)  # the quad's underside, seen in the floor


def test_whitted_renders_cornell_area(data_dir):
    from jaxrt import integrators

    sc = S.load("cornell_area", overrides={"camera.width": 16, "camera.height": 16, "render.integrator": "whitted",
                                           "render.max_depth": 1, "render.spp": 1})
    img = np.asarray(integrators.frame(sc))
    assert img.max() > 1.0  # the ceiling light is seen


# ---------------------------------------------------------------------------------------------
# 6. CLI option ranges, scene/mesh file errors, light indices, duplicate names


def test_exposure_out_of_range_is_one_line(capsys):
    rc, err = run_cli(["render", "spheres", "--exposure", "1024", "-q"], capsys)
    one_line_error(rc, err, "--exposure", "64")


@pytest.mark.parametrize("flag,value", [("--max-steps", -1), ("--max-steps", 0), ("--starts", 0)])
def test_fit_solver_options_are_checked(flag, value, capsys):
    rc, err = run_cli(["fit", "--demo", flag, value, "-q"], capsys)
    one_line_error(rc, err, flag)


@pytest.mark.parametrize("models", [",", " , ", "phong,phong"])
def test_fit_matrix_models_are_checked(models, capsys):
    rc, err = run_cli(["fit-matrix", "--models", models, "-q"], capsys)
    one_line_error(rc, err, "--models")


def test_argparse_errors_are_one_line(capsys):
    rc, err = run_cli(["render", "spheres", "--width", "abc"], capsys)
    one_line_error(rc, err, "--width")


def test_binary_scene_file_names_the_file(tmp_path):
    p = tmp_path / "scene.toml"
    p.write_bytes(bytes(range(256)))
    with pytest.raises(InputError, match=str(p)):
        S.parse(p)


def test_obj_face_index_errors_are_one_based(tmp_path):
    from jaxrt.geometry import mesh

    p = tmp_path / "bad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(InputError) as e:
        mesh.load(p)
    msg = str(e.value)
    assert "line 4" in msg and "4" in msg and "1..3" in msg, msg
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n")  # 0 is no OBJ index
    with pytest.raises(InputError, match="line 4"):
        mesh.load(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nf 1 2 3\n")  # relative indices are fine
    assert mesh.load(p).num_faces == 2


def test_mesh_path_that_is_a_directory(tmp_path):
    (tmp_path / "d.obj").mkdir()
    doc = tiny()
    doc["objects"].append({"mesh": "d.obj", "material": "red"})
    bad(doc, "[[objects] #3] mesh", "directory", base_dir=tmp_path)


def test_with_light_index_must_exist():
    sc = S.load(tiny())
    with pytest.raises(InputError, match="light 5"):
        sc.with_light(5, position=[0.0, 1.0, 0.0])
    with pytest.raises(InputError):
        sc.with_light(-1, intensity=1.0)
    sc.with_light(0, intensity=3.0)


def test_duplicate_object_names_are_an_error():
    doc = tiny()
    doc["objects"][1]["name"] = "ball"
    bad(doc, "[[objects] #2] name", "'ball'", "[[objects] #1]")


def test_unnamed_objects_still_get_distinct_names():
    doc = tiny()
    doc["objects"] = [{"primitive": "sphere", "material": "red", "subdivisions": 0},
                      {"primitive": "sphere", "material": "red", "subdivisions": 0},
                      {"name": "sphere.2", "primitive": "sphere", "material": "red", "subdivisions": 0}]
    names = [o.name for o in S.parse(doc).objects]
    assert len(set(names)) == 3 and names[2] == "sphere.2"


def test_duplicate_instance_names_are_an_error():
    doc = tiny()
    doc["groups"] = [{"name": "g", "objects": [{"primitive": "sphere", "material": "red", "subdivisions": 0}]}]
    doc["instances"] = [{"group": "g", "name": "a"}, {"group": "g", "name": "a", "translate": [1.0, 0.0, 0.0]}]
    bad(doc, "[[instances] #2] name", "'a'")
    doc["instances"][1]["name"] = "ball"  # an object's name
    bad(doc, "[[instances] #2] name", "'ball'")


# ---------------------------------------------------------------------------------------------
# 7. fit targets that cannot be renders; fits that did not work say so


@pytest.fixture(scope="module")
def fit_setup_small():
    from fitting import setup as fit_setup

    return fit_setup.prepare(tiny(), "lambert", object="ball")


@pytest.mark.parametrize("value,needle", [(-1.0, "negative pixel"), (3e38, r"at most 1e\+12")])
def test_fit_refuses_targets_that_cannot_be_renders(fit_setup_small, value, needle):
    from fitting import setup as fit_setup

    targets = np.full(fit_setup_small.mask.shape + (3,), value, np.float32)
    with pytest.raises(InputError, match=needle):
        fit_setup.fit(None, targets, "lambert", setup=fit_setup_small, starts=1, progress=False)


def test_fit_accepts_noise_below_zero(fit_setup_small):
    from fitting import setup as fit_setup

    clean = np.asarray(fit_setup.render_with(fit_setup_small, fit_setup_small.model.params(rho_d=0.4)))
    noisy = clean + np.random.default_rng(1).normal(0.0, 0.01 * clean.max(), clean.shape).astype(np.float32)
    assert noisy.min() < 0
    r, _ = fit_setup.fit(None, noisy, "lambert", setup=fit_setup_small, starts=1, progress=False)
    assert abs(np.mean(r.params["rho_d"]) - 0.4) < 0.05


def test_fit_cli_refuses_negative_targets(tmp_path, capsys):
    from jaxrt import image

    p = tmp_path / "t.exr"
    image.write_exr(p, -np.ones((384, 512, 3), np.float32))  # the size `spheres` renders
    rc, err = run_cli(["fit", p, "--scene", "spheres", "--model", "lambert", "-q"], capsys)
    one_line_error(rc, err, str(p), "negative pixel")


def test_fit_reports_not_converged_and_meaningless_errors():
    import jax.numpy as jnp

    import brdfs
    from fitting import report
    from fitting.solve import fit_images

    model = brdfs.get("phong")

    def shade(p, gb):  # the image depends on rho_d only: rho_s and s are undetermined
        return jnp.broadcast_to(p["rho_d"] * gb, (1, 4, 4, 3))

    target = np.full((1, 4, 4, 3), 0.3, np.float32)
    r = fit_images(shade, jnp.asarray(1.0), target, model, starts=1, max_steps=1, progress=False)
    assert not r.converged
    text = " ".join(r.warnings)
    assert "not converged" in text and "s" in text and "meaningless" in text, r.warnings
    assert "rho_s" in r.meaningless and "s" in r.meaningless and "rho_d" not in r.meaningless
    out = report.format_result(r)
    assert "meaningless" in out and "NOT converged" in out
    assert r.to_json()["warnings"] == r.warnings


def test_fit_reports_a_target_the_model_cannot_reach():
    import jax.numpy as jnp

    import brdfs
    from fitting.solve import fit_images

    def shade(p, gb):
        return jnp.broadcast_to(p["rho_d"] * gb, (1, 4, 4, 3))

    target = np.full((1, 4, 4, 3), 50.0, np.float32)  # rho_d <= 1 renders at most 1
    r = fit_images(shade, jnp.asarray(1.0), target, brdfs.get("lambert"), starts=1, progress=False)
    assert r.relative_rmse > 0.9
    assert any("cannot reproduce" in w for w in r.warnings), r.warnings


# ---------------------------------------------------------------------------------------------
# 9. --confine / JAXRT_CONFINE: scene paths stay inside the scene's folder and the data folder


@pytest.fixture()
def scene_dir(tmp_path):
    from jaxrt.geometry import mesh

    inside = tmp_path / "scene"
    (inside / "sub").mkdir(parents=True)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    for d in (inside / "sub", outside):
        (d / "tri.obj").write_text(tri)
    (inside / "link.obj").symlink_to(outside / "tri.obj")
    assert mesh.load(inside / "link.obj").num_faces == 1
    return inside, outside


@pytest.mark.parametrize("ref,ok", [("sub/tri.obj", True), ("../elsewhere/tri.obj", False),
                                    ("{outside}/tri.obj", False), ("link.obj", False),
                                    ("sub/../sub/tri.obj", True)])
def test_confine_refuses_mesh_paths_outside_the_scene_folder(scene_dir, ref, ok):
    inside, outside = scene_dir
    doc = tiny()
    doc["objects"].append({"mesh": ref.format(outside=outside), "material": "red"})
    S.parse(doc, base_dir=inside)  # allowed without confinement
    if ok:
        S.parse(doc, base_dir=inside, confine=True)
    else:
        bad(doc, "[[objects] #3] mesh", "outside", "confine", base_dir=inside, confine=True)


def test_confine_covers_textures_and_environment_maps(scene_dir):
    from jaxrt import image

    inside, outside = scene_dir
    image.write_png(outside / "t.png", np.full((2, 2, 3), 0.5, np.float32))
    image.write_exr(outside / "sky.exr", np.ones((2, 4, 3), np.float32))
    doc = tiny()
    doc["materials"]["red"]["rho_d"] = {"texture": str(outside / "t.png")}
    bad(doc, "materials.red.rho_d", "outside", base_dir=inside, confine=True)
    doc = tiny(environment={"file": "../elsewhere/sky.exr"})
    bad(doc, "[environment] file", "outside", base_dir=inside, confine=True)


def test_confine_allows_the_data_folder(scene_dir, monkeypatch):
    inside, outside = scene_dir
    monkeypatch.setenv("JAXRT_DATA", str(outside))
    doc = tiny()
    doc["objects"].append({"mesh": str(outside / "tri.obj"), "material": "red"})
    S.parse(doc, base_dir=inside, confine=True)


def test_confine_from_the_environment_and_the_cli(scene_dir, monkeypatch, capsys):
    inside, outside = scene_dir
    doc = tiny()
    doc["objects"].append({"mesh": "../elsewhere/tri.obj", "material": "red"})
    monkeypatch.setenv("JAXRT_CONFINE", "1")
    bad(doc, "outside", base_dir=inside)
    monkeypatch.delenv("JAXRT_CONFINE")
    scene = inside / "s.toml"
    scene.write_text(f"""
[camera]
position = [0.0, 1.0, 4.0]
look_at = [0.0, 0.5, 0.0]
width = 8
height = 6
[[lights]]
position = [2.0, 4.0, 3.0]
intensity = 20.0
[materials.red]
model = "lambert"
[[objects]]
mesh = "../elsewhere/tri.obj"
material = "red"
""")
    for argv in (["render", scene, "--confine", "-o", inside / "x.exr"],
                 ["view", scene, "--confine"],
                 ["fit", inside / "t.exr", "--scene", scene, "--model", "lambert", "--confine"]):
        if argv[0] == "fit":
            from jaxrt import image

            image.write_exr(inside / "t.exr", np.zeros((6, 8, 3), np.float32))
        rc, err = run_cli(argv, capsys)
        one_line_error(rc, err, "mesh", "outside")
    assert not (inside / "x.exr").exists()


# ---------------------------------------------------------------------------------------------
# 10. figures people look at


def test_heat_map_labels_contrast_with_their_cells():
    from fitting import report

    names = ["a", "b", "c"]
    m = np.array([[1e-5, 0.3, 1.0], [0.01, 1e-5, 0.2], [0.5, 0.05, 1e-5]])
    fig = report.matrix_figure(names, m, "t")
    ax = fig.axes[0]
    im = ax.images[0]
    for t in ax.texts:
        j, i = (round(x) for x in t.get_position())
        r, g, b, _ = im.cmap(im.norm(im.get_array()[i, j]))
        lum = 0.2126 * r ** 2.2 + 0.7152 * g ** 2.2 + 0.0722 * b ** 2.2
        # black on light cells, white on dark ones: a contrast ratio of at least 4.5 either way
        contrast = (lum + 0.05) / 0.05 if t.get_color() == "black" else 1.05 / (lum + 0.05)
        assert contrast >= 4.5, (t.get_text(), t.get_color(), lum)
    assert {t.get_color() for t in ax.texts} == {"black", "white"}


def test_fit_picture_is_cropped_to_the_object_with_a_unit_colour_bar():
    from fitting import report

    h = w = 96
    yy, xx = np.mgrid[:h, :w]
    mask = ((yy - 50) ** 2 + (xx - 40) ** 2 < 12 ** 2).astype(np.float32)[None]
    target = np.repeat(mask[..., None] * 0.5, 3, -1)
    fig = report.comparison_figure(target, target * 1.05, mask)
    err_ax = fig.axes[2]
    shape = err_ax.images[0].get_array().shape
    assert shape[0] < 40 and shape[1] < 40  # the 24-pixel disc and a margin, not the 96-pixel frame
    labels = [a.get_ylabel() for a in fig.axes[3:]]
    assert any("W/(m²·sr)" in l for l in labels), labels


def test_lobe_grid_has_one_legend_and_states_each_panel_scale():
    from jaxrt.cli.brdf_report import lobe_figure

    fig = lobe_figure([0, 30, 60])
    assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
    for ax in fig.axes:
        assert "/sr" in ax.get_title() or "R, 1 − R" in ax.get_title(), ax.get_title()
        assert len(ax.get_yticks()) <= 2


def test_correlated_parameters_are_explained_not_alarmed():
    from fitting import report
    from fitting.solve import FitResult

    r = FitResult(model="cook_torrance", params={"rho_s": 0.5, "eta": 1.5}, stderr={"rho_s": 0.01, "eta": 0.02},
                  fixed=[], rmse=1e-3, delta_e_mean=0.1, delta_e_max=0.2, iterations=5, total_iterations=9,
                  starts=2, starts_at_best=2, wall_time_s=1.0, us_per_iteration=1.0, condition_number=1e5,
                  ill_conditioned=True, correlated=[("rho_s", "eta", 0.995)], converged=True, relative_rmse=0.01)
    text = report.format_result(r)
    assert "ill-conditioned" not in text and "combination" in text and "include the trade-off" in text
