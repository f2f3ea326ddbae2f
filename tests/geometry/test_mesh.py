"""Mesh loading (every format, gzip, multi-object), transforms, normals, tangents, validation."""

from __future__ import annotations

import gzip
import json
import warnings

import numpy as np
import pytest
import trimesh

from jaxrt.geometry import data
from jaxrt.geometry import mesh
from jaxrt.errors import InputError


def _tetra():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


def _same_triangles(m: mesh.Mesh, v, f):
    """The loaded mesh has the same triangles (as vertex coordinates) in the same order."""
    np.testing.assert_allclose(m.vertices[m.faces], np.asarray(v, np.float32)[np.asarray(f)], atol=1e-6)


@pytest.mark.parametrize("ext,gz", [(e, g) for e in ["obj", "ply_ascii", "ply", "stl", "glb", "off"] for g in (False, True)]
                         + [("gltf", False)])  # a .gltf refers to side files, so it is not gzipped
def test_load_every_format(tmp_path, ext, gz):
    v, f = _tetra()
    tm = trimesh.Trimesh(v, f, process=False)
    if ext == "ply_ascii":
        blob, suffix = trimesh.exchange.ply.export_ply(tm, encoding="ascii"), "ply"
    elif ext == "gltf":
        files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(tm))
        for name, b in files.items():
            (tmp_path / name).write_bytes(b)
        m = mesh.load(tmp_path / "model.gltf")
        _same_triangles(m, v, f)
        return
    else:
        blob, suffix = tm.export(file_type=ext), ext
    blob = blob.encode() if isinstance(blob, str) else blob
    path = tmp_path / f"tet.{suffix}"
    if gz:
        path = path.with_name(path.name + ".gz")
        path.write_bytes(gzip.compress(blob))
    else:
        path.write_bytes(blob)
    m = mesh.load(path)
    if ext == "stl":  # STL has no shared vertices and no index order to keep; compare as sets
        got = {tuple(np.round(t.ravel(), 6)) for t in m.vertices[m.faces]}
        want = {tuple(np.round(t.ravel(), 6)) for t in v[f].astype(np.float32)}
        assert got == want
    else:
        _same_triangles(m, v, f)
    assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32 and m.normals.dtype == np.float32
    assert m.names == ("tet",) and np.all(m.object_id == 0)
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1, atol=1e-6)


def test_obj_objects_keep_file_order(data_dir, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    m = mesh.load(data.find("cornell_box"))
    side = json.loads(data.find("cornell_box_json").read_text())["groups_triangle_ranges_half_open"]
    assert m.names == tuple(side)
    for i, (name, g) in enumerate(side.items()):
        a, b = g["triangles"]
        assert np.all(m.object_id[a:b] == i), name
    # first triangle of the file: 'f 1 2 3' of the floor
    np.testing.assert_allclose(m.vertices[m.faces[0]], [[552.8, 0, 0], [0, 0, 0], [0, 0, 559.2]], atol=1e-4)


def test_obj_groups_and_file_normals(tmp_path):
    text = ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvn 0 0 -1\nvn 0 0 -1\nvn 0 0 -1\nvn 0 0 -1\n"
            "g first\nf 1//1 3//3 2//2\ng second\nf 1//1 2//2 4//4\nf 1//1 4//4 3//3\ng third\nf 2//2 3//3 4//4\n")
    p = tmp_path / "groups.obj"
    p.write_text(text)
    m = mesh.load(p)
    assert m.names == ("first", "second", "third")
    np.testing.assert_array_equal(m.object_id, [0, 1, 1, 2])
    # normals from the file (deliberately not the geometric ones) survive loading
    p = tmp_path / "normals.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 -1\nvn 0 0 -1\nvn 0 0 -1\nf 1//1 2//2 3//3\n")
    np.testing.assert_allclose(mesh.load(p).normals, np.tile([0, 0, -1], (3, 1)), atol=1e-6)


def test_area_weighted_normals_and_flat():
    # a "roof": two faces of very different areas meeting at the ridge vertex 0
    v = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, -0.1, 0.1]], np.float64)
    f = np.array([[0, 1, 2], [0, 3, 1]])
    m = mesh.Mesh.from_arrays(v, f)
    n1 = np.cross(v[1] - v[0], v[2] - v[0])
    n2 = np.cross(v[3] - v[0], v[1] - v[0])
    want = (n1 + n2) / np.linalg.norm(n1 + n2)  # |cross| = 2 * area: the sum is area weighted
    np.testing.assert_allclose(m.normals[0], want, atol=1e-6)
    mf = mesh.Mesh.from_arrays(v, f, flat=True)
    assert mf.vertices.shape == (6, 3)
    np.testing.assert_allclose(mf.normals[:3], np.tile(n1 / np.linalg.norm(n1), (3, 1)), atol=1e-6)
    np.testing.assert_allclose(mf.normals[3:], np.tile(n2 / np.linalg.norm(n2), (3, 1)), atol=1e-6)


def test_uv_tangents_follow_dpdu_and_are_continuous():
    # a curved strip z = sin(x), u = x: tangent must be the unit dP/du = (1, 0, cos x)/norm
    xs = np.linspace(0, 3, 31)
    ys = np.array([0.0, 1.0])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), np.sin(X.ravel())], 1)
    uv = np.stack([X.ravel(), Y.ravel()], 1)
    idx = np.arange(len(v)).reshape(len(xs), 2)
    f = np.concatenate([np.stack([idx[:-1, 0], idx[1:, 0], idx[1:, 1]], 1), np.stack([idx[:-1, 0], idx[1:, 1], idx[:-1, 1]], 1)])
    m = mesh.Mesh.from_arrays(v, f, uvs=uv)
    t = m.tangents.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.sum(t * m.normals, axis=1), 0, atol=1e-5)
    want = np.stack([np.ones_like(v[:, 0]), 0 * v[:, 0], np.cos(v[:, 0])], 1)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    inner = (v[:, 0] > 0) & (v[:, 0] < 3)  # one-sided differences at the ends
    assert np.min(np.sum(t[inner] * want[inner], axis=1)) > 0.99
    # continuity: neighbouring vertices along the strip have close tangents
    ti = t[idx[:, 0]]
    assert np.min(np.sum(ti[1:] * ti[:-1], axis=1)) > 0.98
    # without UVs: still unit and orthogonal to the normal
    m2 = mesh.Mesh.from_arrays(v, f)
    np.testing.assert_allclose(np.sum(m2.tangents * m2.normals, axis=1), 0, atol=1e-5)


def test_transformed():
    s = trimesh.creation.icosphere(2)
    m = mesh.Mesh.from_arrays(s.vertices, s.faces, uvs=np.c_[s.vertices[:, 0], s.vertices[:, 1]])
    m2 = m.transformed(scale=(2.0, 1.0, 1.0), rotation=(0, 0, 90), translation=(1, 2, 3))
    # scale x by 2, then rotate 90 deg about z: (x, y, z) -> (-y, 2x, z), then translate
    p = m.vertices.astype(np.float64)
    want = np.stack([-p[:, 1], 2 * p[:, 0], p[:, 2]], 1) + [1, 2, 3]
    np.testing.assert_allclose(m2.vertices, want, atol=1e-5)
    # normals: an ellipsoid x^2/4 + y^2 + z^2 = 1 has gradient (x/4... ) in the scaled frame
    q = np.stack([2 * p[:, 0], p[:, 1], p[:, 2]], 1)  # scaled positions
    g = np.stack([q[:, 0] / 4, q[:, 1], q[:, 2]], 1)
    g = np.stack([-g[:, 1], g[:, 0], g[:, 2]], 1)  # rotated
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    # vertex normals of the faceted sphere only approximate the sphere's normals; compare the map
    n0 = m.normals.astype(np.float64)
    n_want = np.stack([n0[:, 0] / 2, n0[:, 1], n0[:, 2]], 1)
    n_want = np.stack([-n_want[:, 1], n_want[:, 0], n_want[:, 2]], 1)
    n_want /= np.linalg.norm(n_want, axis=1, keepdims=True)
    np.testing.assert_allclose(m2.normals, n_want, atol=1e-5)
    assert np.mean(np.sum(m2.normals * g, axis=1)) > 0.99
    np.testing.assert_allclose(np.sum(m2.tangents * m2.normals, axis=1), 0, atol=1e-5)
    r = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(m.transformed(rotation=r).vertices, m.transformed(rotation=(0, 0, 90)).vertices, atol=1e-6)
    with pytest.raises(InputError, match="scale"):
        m.transformed(scale=-1.0)
    with pytest.raises(InputError, match="rotation"):
        m.transformed(rotation=np.eye(3) * 2)


def test_concatenate_renumbers_objects():
    v, f = _tetra()
    a = mesh.Mesh.from_arrays(v, f, name="a")
    b = mesh.Mesh.from_arrays(v + 5, f[:2], name="b")
    c = mesh.concatenate([a, b, a])
    assert c.names == ("a", "b", "a")
    np.testing.assert_array_equal(c.object_id, [0] * 4 + [1] * 2 + [2] * 4)
    np.testing.assert_allclose(c.vertices[c.faces[4:6]], (v + 5)[f[:2]].astype(np.float32))
    assert c.faces.max() == len(c.vertices) - 1


def test_validation_errors(tmp_path):
    v, f = _tetra()
    with pytest.raises(InputError, match="NaN or Inf"):
        mesh.Mesh.from_arrays(np.where(np.arange(12).reshape(4, 3) == 4, np.nan, v), f, name="bad")
    with pytest.raises(InputError, match="face indices"):
        mesh.Mesh.from_arrays(v, f + 1, name="bad")
    with pytest.raises(InputError, match="empty mesh"):
        mesh.Mesh.from_arrays(np.zeros((0, 3)), np.zeros((0, 3), int))
    p = tmp_path / "shape.xyz"
    p.write_text("nothing")
    with pytest.raises(InputError, match=r"shape\.xyz.*unsupported"):
        mesh.load(p)
    with pytest.raises(InputError, match="not found"):
        mesh.load(tmp_path / "missing.obj")
    p = tmp_path / "nan.obj"
    p.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="nan.obj"):
        mesh.load(p)
    p = tmp_path / "empty.obj"
    p.write_text("# nothing\n")
    with pytest.raises(InputError, match="empty.obj"):
        mesh.load(p)


def test_zero_area_triangles_removed_with_count():
    v, f = _tetra()
    f2 = np.concatenate([f, [[0, 0, 1], [1, 2, 1]]])
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        m = mesh.Mesh.from_arrays(v, f2, name="degenerate")
    assert len(w) == 1 and "removed 2 zero-area" in str(w[0].message)
    np.testing.assert_array_equal(m.faces, f)


def test_glb_nodes_are_objects_with_transforms(tmp_path):
    v, f = _tetra()
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(v, f, process=False), node_name="left", geom_name="g0")
    shift = np.eye(4)
    shift[:3, 3] = [10, 0, 0]
    scene.add_geometry(trimesh.Trimesh(v, f[:2], process=False), node_name="right", geom_name="g1", transform=shift)
    p = tmp_path / "two.glb"
    p.write_bytes(scene.export(file_type="glb"))
    m = mesh.load(p)
    assert sorted(m.names) == ["left", "right"]
    right = m.names.index("right")
    tri_r = m.vertices[m.faces[m.object_id == right]]
    np.testing.assert_allclose(tri_r, (v + [10, 0, 0])[f[:2]].astype(np.float32), atol=1e-5)
    assert np.sum(m.object_id == right) == 2 and np.sum(m.object_id != right) == 4


def _ascii_ply(vertices, faces, vertex_props="property float x\nproperty float y\nproperty float z\n",
               face_prop="property list uchar int vertex_indices\n", counts=None) -> bytes:
    counts = [3] * len(faces) if counts is None else counts
    head = (f"ply\nformat ascii 1.0\ncomment made by a test\nelement vertex {len(vertices)}\n{vertex_props}"
            f"element face {len(faces)}\n{face_prop}end_header\n")
    body = "".join(" ".join(repr(float(x)) for x in v) + " \n" for v in vertices)
    body += "".join(f"{c} " + " ".join(str(i) for i in f) + "\n" for c, f in zip(counts, faces))
    return (head + body).encode()


def test_ascii_ply_fast_path_equals_trimesh(tmp_path, monkeypatch):
    """The one-call reader of the common ASCII PLY layout (`mesh._ascii_ply_triangles`) gives the Mesh
    trimesh's reader gives, value for value (vertices rounded to the declared float type), and leaves
    every other layout (extra properties, polygons, binary) to trimesh."""
    rng = np.random.default_rng(5)
    verts = rng.normal(size=(40, 3)) * 3.7
    faces = rng.integers(0, 40, size=(60, 3))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    cases = {
        "plain.ply": _ascii_ply(verts, faces),
        "double.ply.gz": gzip.compress(_ascii_ply(verts, faces, vertex_props="property double x\nproperty double y\n"
                                                                            "property double z\n")),
        "normals.ply": _ascii_ply(np.concatenate([verts, verts / np.linalg.norm(verts, axis=1, keepdims=True)], 1),
                                  faces, vertex_props="".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))),
        "quads.ply": _ascii_ply(verts, np.concatenate([faces, faces[:, :1]], 1), counts=[4] * len(faces)),
    }
    fast_layout = {"plain.ply": True, "double.ply.gz": True, "normals.ply": False, "quads.ply": False}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        raw = gzip.decompress(data) if name.endswith(".gz") else data
        assert (mesh._ascii_ply_triangles(raw) is not None) == fast_layout[name], name
        ours = mesh.load(tmp_path / name)
        with monkeypatch.context() as m:
            m.setattr(mesh, "_ascii_ply_triangles", lambda raw: None)
            theirs = mesh.load(tmp_path / name)
        for field in ("vertices", "faces", "normals", "tangents", "object_id"):
            np.testing.assert_array_equal(getattr(ours, field), getattr(theirs, field), err_msg=f"{name} {field}")
        assert ours.names == theirs.names
    # the float type is honoured: a float32 file's vertices are float32 values
    v = mesh.load(tmp_path / "plain.ply").vertices
    np.testing.assert_array_equal(v, verts.astype(np.float32).astype(np.float64))
    # a binary file is not this layout
    binary = trimesh.Trimesh(verts, faces, process=False).export(file_type="ply", encoding="binary")
    assert mesh._ascii_ply_triangles(binary) is None
