"""Scene-file validation (no JAX work needed) and procedural shapes."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from test_render_util import lab_dict

from jaxrt import scene as S
from jaxrt.geometry import shapes
from jaxrt.errors import InputError


def _write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _bad(d, *needles):
    with pytest.raises(InputError) as e:
        S.parse(d)
    msg = str(e.value)
    assert "\n" not in msg
    for n in needles:
        assert n in msg, msg
    return msg


def _mod(path, value):
    d = copy.deepcopy(lab_dict())
    cur = d
    for k in path[:-1]:
        cur = cur[k]
    if value is _DEL:
        del cur[path[-1]]
    else:
        cur[path[-1]] = value
    return d


_DEL = object()


def test_valid_lab_parses_with_defaults():
    spec = S.parse(lab_dict())
    assert spec.camera.aperture == 0.0 and spec.camera.up == (0.0, 1.0, 0.0)
    assert spec.render.spp == 1 and spec.render.integrator == "whitted"
    assert spec.materials["mirror"].delta == 1.0 and spec.materials["glass"].delta == 0.0


@pytest.mark.parametrize(
    "path,value,needles",
    [
        (("camera", "fov"), 40, ["[camera] fov", "unknown key", "vfov"]),
        (("camera", "vfov"), 180, ["[camera] vfov", "(0, 180)"]),
        (("camera", "vfov"), "wide", ["[camera] vfov", "expected a finite number"]),
        (("camera", "width"), 0, ["[camera] width", "[1, 16384]"]),
        (("camera", "width"), 64.5, ["[camera] width", "integer"]),
        (("camera", "position"), [0, 1], ["[camera] position", "3 finite numbers"]),
        (("camera", "look_at"), _DEL, ["[camera] look_at", "required"]),
        (("camera", "up"), [0.0, 12.0, 5.6], ["[camera] up", "parallel"]),
        (("lights",), [], ["lights", "[[lights]]"]),
        (("lights", 0, "intensity"), -1.0, ["[[lights] #1] intensity", ">= 0"]),
        (("lights", 0, "colour"), 1.0, ["[[lights] #1] colour", "unknown key"]),
        (("materials", "floor", "model"), "oren_nayar", ["[materials.floor] model", "lambert", "glass"]),
        (("materials", "floor", "rho_d"), 1.5, ["[materials.floor] rho_d", "[0, 1]"]),
        (("materials", "plastic", "s"), 0.5, ["[materials.plastic] s", "[1, 1e+06]"]),
        (("materials", "floor", "roughness"), 0.5, ["[materials.floor] roughness", "unknown key", "rho_d"]),
        (("materials", "floor", "delta"), 2.0, ["[materials.floor] delta", "[0, 1]"]),
        (("materials", "glass", "delta"), 0.5, ["[materials.glass] delta", "unknown key"]),
        (("objects", 0, "material"), "gold", ["[[objects] #1] material", "'gold' is not allowed", "floor"]),
        (("objects", 0, "primitive"), "torus", ["[[objects] #1] primitive", "sphere, plane, box"]),
        (("objects", 1, "mesh"), "cube.obj", ["[[objects] #2]", "exactly one of"]),
        (("objects", 1, "size"), [1, 2], ["[[objects] #2] size", "3 finite numbers"]),
        (("objects", 1, "scale"), 0, ["[[objects] #2] scale"]),
        (("render", "integrator"), "bdpt", ["[render] integrator", "whitted, path"]),
        (("render", "max_depth"), 0, ["[render] max_depth", "[1, 16]"]),
        (("render", "spp"), True, ["[render] spp", "integer"]),
        (("render", "background"), [0, -1, 0], ["[render] background", ">= 0"]),
        (("extra",), 1, ["[top level] extra", "unknown key"]),
    ],
)
def test_each_kind_of_bad_input_gives_one_line(path, value, needles):
    _bad(_mod(path, value), *needles)


def test_missing_mesh_file_names_the_path(tmp_path):
    d = lab_dict()
    d["objects"].append({"mesh": "no_such_mesh.obj", "material": "floor"})
    msg = _bad(d, "[[objects] #7] mesh", "no_such_mesh.obj", "no such file")
    assert str(tmp_path) not in msg


def test_file_errors(tmp_path):
    with pytest.raises(InputError, match="no such scene file"):
        S.load(tmp_path / "nope.toml")
    p = _write(tmp_path, "[camera\nposition = 1")
    with pytest.raises(InputError, match="not valid TOML"):
        S.parse(p)
    p = _write(tmp_path, "camera = 3\n")
    with pytest.raises(InputError, match=r"\[camera\]: expected a table"):
        S.parse(p)


def test_mesh_paths_resolve_relative_to_the_scene_file(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    text = """
[camera]
position = [0, 0, 5]
look_at = [0, 0, 0]
[[lights]]
position = [0, 0, 5]
intensity = 1
[materials.m]
model = "lambert"
[[objects]]
mesh = "sub/tri.obj"
material = "m"
"""
    p = _write(tmp_path, text)
    spec = S.parse(p)
    assert spec.objects[0].mesh == tmp_path / "sub" / "tri.obj" and spec.objects[0].name == "tri"


def test_overrides_are_validated_too():
    with pytest.raises(InputError, match=r"\[camera\] width"):
        S.parse(lab_dict(), overrides={"camera.width": -3})
    assert S.parse(lab_dict(), overrides={"render.spp": 4}).render.spp == 4


def test_find_scene_resolves_shipped_names():
    assert S.find_scene("spheres").name == "spheres.toml"
    with pytest.raises(InputError, match="shipped scenes: .*spheres"):
        S.find_scene("no_such_scene")


def test_every_shipped_scene_validates():
    # parse only touches the data registry for mesh names; the lookups need $JAXRT_DATA
    import os

    for p in sorted(S.SCENES_DIR.glob("*.toml")):
        if p.stem != "spheres" and not os.environ.get("JAXRT_DATA"):
            continue
        spec = S.parse(p)
        emissive = any(max(m.emission) > 0 for m in spec.materials.values())
        assert spec.objects and (spec.lights or spec.environment is not None or emissive)


def test_sphere_normals_are_exact_and_box_is_flat():
    sph = shapes.sphere(radius=2.0, subdivisions=2)
    v = np.asarray(sph.vertices, np.float64)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 2.0, rtol=1e-6)
    np.testing.assert_allclose(sph.normals, v / 2.0, atol=1e-6)
    box = shapes.box(size=(1.0, 2.0, 3.0))
    bv = np.asarray(box.vertices)
    np.testing.assert_allclose(bv.min(0), [-0.5, -1.0, -1.5])
    np.testing.assert_allclose(bv.max(0), [0.5, 1.0, 1.5])
    # every triangle's vertex normals equal its geometric normal, pointing outward
    tri = bv[np.asarray(box.faces)]
    ng = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    np.testing.assert_allclose(np.asarray(box.normals)[np.asarray(box.faces)], np.repeat(ng[:, None], 3, 1), atol=1e-6)
    assert np.all(np.sum(ng * tri.mean(1), 1) > 0)
    pl = shapes.plane(size=(2.0, 4.0))
    tri = np.asarray(pl.vertices)[np.asarray(pl.faces)]
    ng = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(ng[:, 1] > 0) and np.allclose(tri[..., 1], 0.0)


def test_build_groups_materials_by_model():
    scn = S.load(lab_dict())
    m = scn.materials
    assert m.models == ("lambert", "phong", "glass")
    for name in ("floor", "box", "mirror", "black"):
        i = m.index(name)
        assert m.models[int(m.model_id[i])] == "lambert"
    i = m.index("box")
    np.testing.assert_allclose(m.params[0]["rho_d"][int(m.row[i])], [0.7, 0.7, 0.7])
    # every face carries the material of its object
    names = scn.geometry.object_names
    fmat = np.asarray(scn.geometry.material)
    fobj = np.asarray(scn.geometry.object_id)
    assert set(fmat[fobj == names.index("slab")]) == {m.index("glass")}
    with pytest.raises(InputError, match=r"floor.*rho_d.*\[0, 1\]"):
        scn.with_material("floor", rho_d=2.0)


@pytest.mark.filterwarnings("ignore:.*zero-area")
def test_a_sphere_too_small_for_float32_is_one_line_naming_the_object():
    # a radius the parser accepts (> 0) but whose triangles underflow in float32: building gave NaN
    # normals and an error naming neither the scene nor the object
    d = copy.deepcopy(lab_dict())
    d["objects"] = [{"name": "ball", "primitive": "sphere", "radius": 1e-30, "subdivisions": 1,
                     "material": d["objects"][0]["material"]}]
    spec = S.parse(d)
    with pytest.raises(InputError) as e:
        S.build(spec)
    msg = str(e.value)
    assert "\n" not in msg and "object 'ball'" in msg, msg


def test_tiny_sphere_keeps_exact_normals():
    # normals come from the unit sphere, then the vertices are scaled: exact at any radius
    sph = shapes.sphere(radius=1e-12, subdivisions=1)
    n = np.asarray(sph.normals, np.float64)
    assert np.all(np.isfinite(n))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(sph.vertices, np.float64), n * 1e-12, rtol=1e-5)


def test_on_shapes_sees_the_scene_before_its_tree_and_changes_nothing():
    """`build(spec, on_shapes=f)` calls f once, before the BVH is built, with the scene whose tree
    arrays are shapes only (the built tree's shapes and dtypes) and every other array the built
    scene's own; the scene it returns is the one `build(spec)` returns, bit for bit."""
    import jax

    spec = S.parse(lab_dict())
    seen = []
    got = S.build(spec, on_shapes=seen.append)
    ref = S.build(spec)
    assert len(seen) == 1
    shaped = seen[0]
    tree = shaped.geometry.tree
    assert all(isinstance(x, jax.ShapeDtypeStruct) for x in jax.tree.leaves(tree))
    assert jax.tree.structure(shaped) == jax.tree.structure(ref)
    for a, b in zip(jax.tree.leaves(shaped), jax.tree.leaves(ref), strict=True):
        assert (a.shape, a.dtype) == (b.shape, b.dtype)
    assert jax.tree.structure(got) == jax.tree.structure(ref)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(ref), strict=True):
        assert not isinstance(a, jax.ShapeDtypeStruct)
        assert a.dtype == b.dtype and np.array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(jax.tree.leaves(dataclasses.replace(shaped.geometry, tree=None)),
                    jax.tree.leaves(dataclasses.replace(got.geometry, tree=None)), strict=True):
        assert a is b  # the arrays beside the tree are placed once, not again after the build


def test_on_shapes_is_not_called_for_instanced_scenes():
    seen = []  # a two-level tree's shapes depend on its instances' builds: nothing to call it with
    S.build(S.parse(S.find_scene("instances"), overrides={"camera.width": 8, "camera.height": 8}),
            on_shapes=seen.append)
    assert seen == []
