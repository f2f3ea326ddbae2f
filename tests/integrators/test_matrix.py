"""Every integrator x every geometry kind x AOVs on/off, through the compiled frame and the CLI.

The same small scene is written twice, once with plain [[objects]] (`TriangleGeometry`) and once with
its spheres placed by [[instances]] of a group (`InstancedGeometry`). Independent checks: the two
kinds describe the same surfaces, so their images and AOVs agree; Whitted and path tracing shoot the
same camera rays at 1 spp, so their AOVs agree exactly; the nearest depth of each sphere is its
closed-form distance from the camera.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

import jaxrt
from jaxrt import integrators
from jaxrt.cli import main as cli
from jaxrt.geometry import InstancedGeometry, TriangleGeometry
from jaxrt.shading import AOV_NAMES

W, H = 24, 18
RADIUS = 0.5


def _doc(kind: str) -> dict:
    doc = {
        "camera": {"position": [0.0, 0.0, 4.0], "look_at": [0.0, 0.0, 0.0], "vfov": 40.0, "width": W, "height": H},
        "lights": [{"position": [2.0, 3.0, 4.0], "intensity": 20.0}],
        "materials": {"red": {"model": "lambert", "rho_d": [0.8, 0.2, 0.2]},
                      "grey": {"model": "phong", "rho_d": 0.5, "rho_s": 0.3, "s": 20.0},
                      "floor": {"model": "lambert", "rho_d": 0.4}},
        "render": {"spp": 1, "max_depth": 2},
    }
    floor = {"primitive": "plane", "name": "floor", "material": "floor", "size": [8.0, 8.0],
             "translate": [0.0, -0.5, 0.0]}
    balls = [("left", "red", -0.6), ("right", "grey", 0.6)]
    if kind == "triangles":
        doc["objects"] = [floor] + [{"primitive": "sphere", "name": n, "material": m, "radius": RADIUS,
                                     "subdivisions": 3, "translate": [x, 0.0, 0.0]} for n, m, x in balls]
    else:
        doc["objects"] = [floor]
        doc["groups"] = [{"name": "ball", "objects": [{"primitive": "sphere", "name": "s", "material": "red",
                                                      "radius": RADIUS, "subdivisions": 3}]}]
        doc["instances"] = [{"group": "ball", "name": n, "material": m, "translate": [x, 0.0, 0.0]}
                            for n, m, x in balls]
    return doc


KINDS = {"triangles": TriangleGeometry, "instances": InstancedGeometry}


@pytest.fixture(scope="module")
def renders():
    out = {}
    for kind in KINDS:
        for integ in integrators.names():
            doc = copy.deepcopy(_doc(kind))
            doc["render"]["integrator"] = integ
            sc = jaxrt.load_scene(doc)
            assert isinstance(sc.geometry, KINDS[kind])
            out[kind, integ] = (sc, jaxrt.frame(sc), jaxrt.frame(sc, aovs=True))
    return out


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("integ", ["whitted", "path"])
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_every_integrator_renders_every_geometry_kind(renders, kind, integ):
    sc, img, (img2, aovs) = renders[kind, integ]
    img, img2 = np.asarray(img), np.asarray(img2)
    assert img.shape == (H, W, 3) and np.all(np.isfinite(img)) and img.max() > 0
    np.testing.assert_allclose(img2, img, rtol=1e-5, atol=1e-6)  # AOVs never change the image
    assert set(aovs) == set(AOV_NAMES)
    assert aovs["depth"].shape == (H, W) and aovs["normal"].shape == (H, W, 3)
    assert aovs["albedo"].shape == (H, W, 3) and aovs["object_id"].shape == (H, W)
    oid = np.asarray(aovs["object_id"])
    names = sc.geometry.object_names
    assert oid.min() >= -1 and oid.max() < len(names)
    seen = {names[i] for i in np.unique(oid) if i >= 0}
    assert "floor" in seen and {"left", "right"} <= {n.split("/")[0] for n in seen}
    depth = np.asarray(aovs["depth"])
    assert np.all(depth[oid < 0] == 0) and np.all(depth[oid >= 0] > 0)
    for i, n in enumerate(names):
        if n.split("/")[0] in ("left", "right"):
            nearest = np.hypot(0.6, 4.0) - RADIUS  # |centre - camera| - r
            assert depth[oid == i].min() == pytest.approx(nearest, rel=3e-3)
    nrm = np.asarray(aovs["normal"])
    np.testing.assert_allclose(np.linalg.norm(nrm[oid >= 0], axis=-1), 1.0, atol=1e-4)


@pytest.mark.parametrize("integ", ["whitted", "path"])
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_instanced_and_triangle_geometry_agree(renders, integ):
    _, img_t, (_, a_t) = renders["triangles", integ]
    sc_i, img_i, (_, a_i) = renders["instances", integ]
    names_t = renders["triangles", integ][0].geometry.object_names
    names_i = sc_i.geometry.object_names
    # instanced objects are named INSTANCE/OBJECT; map both to the instance name
    base = lambda n: n.split("/")[0]  # noqa: E731
    ot, oi = np.asarray(a_t["object_id"]), np.asarray(a_i["object_id"])
    lt = np.where(ot >= 0, np.array([base(n) for n in names_t] + [""])[ot], "")
    li = np.where(oi >= 0, np.array([base(n) for n in names_i] + [""])[oi], "")
    agree = lt == li
    assert agree.mean() > 0.98  # a silhouette pixel may pick the neighbouring triangle
    np.testing.assert_allclose(np.asarray(a_i["depth"])[agree], np.asarray(a_t["depth"])[agree], rtol=1e-4)
    np.testing.assert_allclose(np.asarray(img_i)[agree], np.asarray(img_t)[agree], rtol=2e-3, atol=2e-4)


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_whitted_and_path_aovs_agree(renders, kind):
    _, _, (_, aw) = renders[kind, "whitted"]
    _, _, (_, ap) = renders[kind, "path"]
    # the same first hits: integer AOVs equal, float ones to rounding (the Whitted frame makes its camera
    # rays in its slot order, a differently shaped program that XLA may contract into FMAs otherwise,
    # so a direction, and the depth along it, can differ in the last bit; a different hit would differ
    # by far more than the tolerance)
    for k in AOV_NAMES:
        a, w = np.asarray(ap[k]), np.asarray(aw[k])
        if np.issubdtype(w.dtype, np.integer):
            np.testing.assert_array_equal(a, w, err_msg=k)
        else:
            np.testing.assert_allclose(a, w, rtol=1e-6, atol=1e-6, err_msg=k)


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_cli_renders_instanced_scene_with_path_tracing(tmp_path, capsys):
    """`jaxrt render instances --integrator path` used to crash building AOVs (the path tracer had
    its own AOV code without the instanced branch)."""
    out = tmp_path / "inst.exr"
    rc = cli(["render", "instances", "--integrator", "path", "--width", "16", "--height", "12", "--spp", "1",
              "--aovs", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    from jaxrt import image

    chans = image.read_exr(out, channels=True)
    img = chans["RGB"]
    assert np.all(np.isfinite(img)) and img.max() > 0
    assert {"depth", "object_id"} <= set(chans)
