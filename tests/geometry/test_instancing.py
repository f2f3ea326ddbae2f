"""Object groups and instancing (jaxrt.accel.two_level, jaxrt.geometry.instanced).

References are independent of the two-level code: every instance's triangles are copied and
transformed explicitly in float64 numpy and intersected by brute force (test_bvh's Moller-Trumbore
and its acceptance rules for float32-undecidable rays); renders of the instanced scene are compared
with renders of the same scene written as plain (copied) objects, which go through the single-level
BVH.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxrt.accel import two_level as bi
from jaxrt import cli, image
from jaxrt.geometry import TriangleGeometry
from jaxrt.geometry import instanced as instancing
from jaxrt.geometry import mesh
from jaxrt.geometry import shapes
import jaxrt as R
from jaxrt import scene as S
from jaxrt.errors import InputError
from test_bvh import brute_force, check_against_reference, ray_mix

REPO = Path(__file__).resolve().parents[2]
SCENE = REPO / "scenes" / "instances.toml"
SMALL = {"camera.width": 40, "camera.height": 30}


def _rot(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _copies(protos, inst_proto, xf):
    """float64 world triangles of every instance, concatenated in instance order (so the row index
    is the virtual face id: instance offset + local face)."""
    out = []
    for p, m in zip(inst_proto, np.asarray(xf, np.float64)):
        v = np.asarray(protos[p].vertices, np.float64) @ m[:, :3].T + m[:, 3]
        out.append(v[np.asarray(protos[p].faces)])
    return np.concatenate(out)


@pytest.fixture(scope="module")
def fns():
    return jax.jit(bi.intersect), jax.jit(bi.occluded)


@pytest.mark.slow  # (~60 s; the default suite keeps test_instanced_render_equals_copied_objects)
def test_two_level_matches_brute_force(fns):
    rng = np.random.default_rng(7)
    protos = [shapes.sphere(0.6, 2), shapes.box((1.0, 0.4, 0.7)), shapes.plane((1.5, 1.0))]
    inst_proto, xf = [], []
    for i in range(14):  # overlapping instances: rotated, non-uniformly scaled, within a 2.4-wide cube
        inst_proto.append(i % 3)
        a = _rot(rng) * rng.uniform(0.5, 1.6, 3)[None, :]
        xf.append(np.concatenate([a, rng.uniform(-1.2, 1.2, (3, 1))], 1))
    # axis-aligned instances (exact zero matrix entries), and one exact duplicate (ties across instances)
    inst_proto += [1, 2, 0]
    xf += [np.array([[2.0, 0, 0, 0.1], [0, 1, 0, -0.2], [0, 0, 0.5, 0.3]]),
           np.array([[1.0, 0, 0, 0], [0, 1, 0, 0.25], [0, 0, 1, 0]]), xf[0]]
    xf = np.asarray(xf, np.float32)
    tree = bi.build([(p.vertices, p.faces) for p in protos], inst_proto, xf)
    tri = _copies(protos, inst_proto, xf)
    flat = mesh.Mesh.from_arrays(tri.reshape(-1, 3).astype(np.float32), np.arange(3 * len(tri)).reshape(-1, 3))
    o, d, tmin, tmax = ray_mix(flat, 1500, seed=2)  # outside-in, inside-out, grazing, axis-parallel, limits
    # watertightness within an instance: rays aimed exactly at shared vertices and edge midpoints of
    # the (rotated, non-uniformly scaled) closed convex sphere and box instances 0 and 1, from outside
    # towards the instance's centre, so that each enters the solid there (at t = 2/3)
    aims, src = [], []
    for i in (0, 1):
        pm = protos[inst_proto[i]]
        e = np.asarray(pm.faces)[:, [0, 1]]
        pts = np.concatenate([pm.vertices, 0.5 * (pm.vertices[e[:, 0]] + pm.vertices[e[:, 1]])]).astype(np.float64)
        w = pts[rng.choice(len(pts), 100)] @ xf[i, :, :3].T.astype(np.float64) + xf[i, :, 3]
        aims.append(w)
        src.append(xf[i, :, 3] + 3.0 * (w - xf[i, :, 3]))  # the centre maps to the translation
    aims, src = np.concatenate(aims), np.concatenate(src)
    n_mix = len(o)
    o = np.concatenate([o, src.astype(np.float32)])
    d = np.concatenate([d, (aims - src).astype(np.float32) * 1.5])
    tmin = np.concatenate([tmin, np.zeros(len(aims), np.float32)])
    tmax = np.concatenate([tmax, np.full(len(aims), np.inf, np.float32)])
    f_hit, f_occ = fns
    hit = f_hit(tree, o, d, tmin, tmax)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    ref_t, ref_p = brute_force(tri, o64, d64, tmin.astype(np.float64), tmax.astype(np.float64))
    # Rays within 1e-5 (cosine) of their triangle's plane get float32 barycentrics that are off by
    # up to ~1e-4 across the ray: the single-level BVH gives the same on the copied triangles, so
    # test_bvh's barycentric bound does not apply to them; their (instance, face) and t still must.
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    cos = np.abs(np.einsum("ij,ij->i", nrm[np.maximum(ref_p, 0)], d64)) / (
        np.linalg.norm(nrm[np.maximum(ref_p, 0)], axis=1) * np.linalg.norm(d64, axis=1))
    extreme = (ref_p >= 0) & (cos < 1e-5)
    assert extreme.sum() <= 5
    keep = ~extreme
    sub = type(hit)(*(np.asarray(x)[keep] for x in hit))
    check_against_reference(tri, o64[keep], d64[keep], tmin[keep].astype(np.float64),
                            tmax[keep].astype(np.float64), sub)
    prim = np.asarray(hit.prim)
    t = np.asarray(hit.t, np.float64)
    assert np.array_equal(prim[extreme], ref_p[extreme])
    aimed = slice(n_mix, None)  # no aimed ray leaks through its instance (t = 2/3 at the aim point)
    assert np.all(prim[aimed] >= 0) and np.all(t[aimed] <= 2.0 / 3.0 * (1.0 + 1e-5))
    assert np.all(np.abs(t[extreme] - ref_t[extreme]) <= 1e-5 * ref_t[extreme])
    assert 0.3 < np.mean(ref_p >= 0) < 0.95
    # many rays cross several instances (brute force per instance), and (instance, face) is exact for
    # all but the few float32-undecidable rays that check_against_reference accepted
    starts = np.concatenate([[0], np.cumsum([len(protos[p].faces) for p in inst_proto])])
    inf = np.full(len(o), np.inf)
    crossed = sum(brute_force(tri[a:b], o64, d64, np.zeros(len(o)), inf)[1] >= 0
                  for a, b in zip(starts[:-1], starts[1:]))
    assert np.mean(crossed >= 2) > 0.2
    # the duplicate (last) instance ties with instance 0 everywhere: either answer is exact
    canon = lambda q: np.where(q >= starts[-2], q - starts[-2] + starts[0], q)  # noqa: E731
    # (the aimed rays are excluded here: at a shared edge or vertex either neighbour is right)
    assert np.mean(canon(prim[:n_mix]) == canon(ref_p[:n_mix])) >= 0.995
    # decode: virtual id -> (instance, local face) agrees with the copied layout
    inst, local = (np.asarray(x) for x in bi.decode(tree, hit.prim))
    ok = prim >= 0
    assert np.array_equal(starts[inst[ok]] + local[ok], prim[ok])
    blocked = np.asarray(f_occ(tree, o, d, tmax, tmin))
    assert np.array_equal(blocked, prim >= 0)


def test_build_rejects_bad_transforms():
    box = shapes.box()
    with pytest.raises(InputError, match="singular"):
        bi.build([(box.vertices, box.faces)], [0], np.zeros((1, 3, 4), np.float32))
    with pytest.raises(InputError, match="negative-determinant"):
        bi.build([(box.vertices, box.faces)], [0], np.diag([1.0, -1.0, 1.0, 0.0])[:3].astype(np.float32)[None])
    with pytest.raises(InputError, match="finite"):
        bi.build([(box.vertices, box.faces)], [0], np.full((1, 3, 4), np.nan, np.float32))
    with pytest.raises(InputError, match="prototype index"):
        bi.build([(box.vertices, box.faces)], [1], np.eye(3, 4, dtype=np.float32)[None])


# --------------------------------------------------------------------------- scenes and renders


def _expand(doc: dict) -> dict:
    """The same scene written without groups: every (instance, group object) becomes a plain object
    with the composed transform R(s (s_o p + t_o)) + T = R diag(s s_o) p + (s R t_o + T)."""
    import trimesh.transformations as tf

    groups = {g["name"]: g for g in doc["groups"]}
    objects = [dict(o) for o in doc.get("objects", [])]
    counts: dict[str, int] = {}
    for inst in doc["instances"]:
        counts[inst["group"]] = counts.get(inst["group"], 0) + 1
        name = inst.get("name", f"{inst['group']}.{counts[inst['group']]}")
        s = float(inst.get("scale", 1.0))  # the shipped scene uses uniform instance scales
        rot = inst.get("rotate", [0.0, 0.0, 0.0])
        r = tf.euler_matrix(*np.radians(rot), axes="sxyz")[:3, :3]
        for o in groups[inst["group"]]["objects"]:
            assert "rotate" not in o
            c = dict(o)
            c["name"] = f"{name}/{o['name']}"
            c["scale"] = (s * np.broadcast_to(np.asarray(o.get("scale", 1.0), float), (3,))).tolist()
            c["rotate"] = list(rot)
            c["translate"] = (s * r @ np.asarray(o.get("translate", [0.0, 0.0, 0.0]), float)
                              + np.asarray(inst.get("translate", [0.0, 0.0, 0.0]), float)).tolist()
            if "material" in inst:
                c["material"] = inst["material"]
            objects.append(c)
    out = {k: v for k, v in doc.items() if k not in ("groups", "instances")}
    out["objects"] = objects
    return out


@pytest.fixture(scope="module")
def shipped():
    with open(SCENE, "rb") as f:
        doc = tomllib.load(f)
    inst = S.load(SCENE, overrides=SMALL)
    copy_doc = _expand(doc)
    copy = S.load(copy_doc, overrides=SMALL)
    img_i, aov_i = (jax.tree.map(np.asarray, x) for x in R.frame(inst, aovs=True))
    img_c, aov_c = (jax.tree.map(np.asarray, x) for x in R.frame(copy, aovs=True))
    return dict(doc=doc, inst=inst, copy_doc=copy_doc, copy=copy, img_i=img_i, aov_i=aov_i, img_c=img_c, aov_c=aov_c)


def _close(a, b):
    # float32 rounding differs (object-space vs pre-transformed vertices); a pixel whose ray or
    # shadow ray is decided differently would differ by O(1), so the bound is tight
    return np.max(np.abs(a - b)) <= 1e-4 * max(np.max(np.abs(b)), 1.0)


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_instanced_render_equals_copied_objects(shipped):
    inst, copy = shipped["inst"], shipped["copy"]
    assert isinstance(inst.geometry, instancing.InstancedGeometry) and isinstance(copy.geometry, TriangleGeometry)
    assert inst.geometry.object_names == copy.geometry.object_names  # floor, then pair.K/base, pair.K/ball
    assert inst.geometry.triangle_count == copy.geometry.faces.shape[0]
    img_i, img_c, aov_i, aov_c = (shipped[k] for k in ("img_i", "img_c", "aov_i", "aov_c"))
    assert np.all(np.isfinite(img_i)) and img_i.max() > 0.1
    assert _close(img_i, img_c)
    assert np.array_equal(aov_i["object_id"], aov_c["object_id"])
    assert len(np.unique(aov_i["object_id"])) > 20  # many instances in view
    hit = aov_c["object_id"] >= 0
    assert np.max(np.abs(aov_i["depth"] - aov_c["depth"])[hit] / aov_c["depth"][hit]) < 1e-5
    assert np.max(np.abs(aov_i["normal"] - aov_c["normal"])) < 1e-4
    # the group-level override in the file: every object of the front row is gold, the others keep theirs
    geo, mats = inst.geometry, inst.materials
    for k, name in enumerate(geo.object_names):
        want = "gold" if name.split("/")[0] in {f"pair.{i}" for i in range(16, 21)} else (
            {"base": "clay", "ball": "red"}.get(name.split("/")[-1], "floor"))
        assert mats.names[int(geo.object_material[k])] == want, name


def test_group_material_override_changes_exactly_its_pixels(shipped):
    inst = shipped["inst"]
    target = "pair.8"
    ids = [k for k, n in enumerate(inst.geometry.object_names) if n.startswith(target + "/")]
    assert len(ids) == 2
    geo = inst.geometry
    gold = inst.materials.index("gold")
    for k in ids:
        geo = geo.with_object_material(k, gold)
    inst2 = eqx_replace_geometry(inst, geo)
    img2 = np.asarray(R.frame(inst2, aovs=True)[0])  # a value change: no recompile
    # reference: the copied scene with the same objects' materials changed in the file
    doc2 = dict(shipped["copy_doc"])
    doc2["objects"] = [dict(o, material="gold") if o["name"].startswith(target + "/") else o
                       for o in doc2["objects"]]
    img_c2 = np.asarray(R.frame(S.load(doc2, overrides=SMALL), aovs=True)[0])
    assert _close(img2, img_c2)
    img = shipped["img_i"]
    oid = shipped["aov_i"]["object_id"]
    changed = np.any(np.abs(img2 - img) > 1e-6, axis=-1)
    group = np.isin(oid, ids)
    lit = np.any(img > 0, axis=-1) | np.any(img2 > 0, axis=-1)
    assert group.sum() >= 4
    assert np.all(changed[group & lit])
    floor = oid == inst.geometry.object_names.index("floor")
    assert not np.any(changed & ~group & ~floor)  # elsewhere only the floor's mirror images may change


def eqx_replace_geometry(sc, geo):
    import equinox as eqx

    return eqx.tree_at(lambda s: s.geometry, sc, geo)


def test_cli_renders_instanced_scene(shipped, tmp_path, capsys):
    exr = tmp_path / "inst.exr"
    rc = cli.main(["render", str(SCENE), "-o", str(exr), "--width", str(SMALL["camera.width"]),
                   "--height", str(SMALL["camera.height"]), "--aovs"])
    assert rc == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert f"{shipped['inst'].geometry.triangle_count} triangles" in out
    ch = image.read_exr(exr, channels=True)
    assert np.all(np.isfinite(ch["RGB"])) and np.array_equal(ch["RGB"], shipped["img_i"])


def _doc(**extra):
    d = {"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "width": 8, "height": 8},
         "lights": [{"position": [0, 5, 5], "intensity": 10}],
         "materials": {"a": {"model": "lambert"}, "b": {"model": "lambert"}},
         "groups": [{"name": "g", "objects": [{"primitive": "box", "material": "a"}]}],
         "instances": [{"group": "g"}]}
    d.update(extra)
    return d


@pytest.mark.parametrize("change,needle", [
    ({"instances": [{"group": "nope"}]}, ["[instances] #1] group", "'nope' is not a defined group", "g"]),
    ({"instances": [{"group": "g", "scale": 0}]}, ["[instances] #1] scale"]),
    ({"instances": [{"group": "g", "scale": [1, -1, 1]}]}, ["[instances] #1] scale", ">= 1e-30"]),
    ({"instances": [{"group": "g", "rotate": [0, "x", 0]}]}, ["[instances] #1] rotate", "3 finite numbers"]),
    ({"instances": [{"group": "g", "translate": [0, 0]}]}, ["[instances] #1] translate"]),
    ({"instances": [{"group": "g", "material": "c"}]}, ["[instances] #1] material", "'c' is not allowed"]),
    ({"instances": [{"group": "g", "colour": 1}]}, ["[instances] #1] colour", "unknown key"]),
    ({"instances": []}, ["instances", "one or more"]),
    ({"groups": [{"name": "g", "objects": [{"group": "g"}]}]}, ["[groups] g: [objects] #1", "cannot contain groups"]),
    ({"groups": [{"name": "g", "objects": []}]}, ["[groups] #1] objects", "one or more"]),
    ({"groups": [{"name": "g", "objects": [{"primitive": "box", "material": "zz"}]}]},
     ["[groups] g: [objects] #1] material"]),
    ({"groups": [{"name": "g", "objects": [{"primitive": "box", "material": "a"}]}] * 2}, ["already defined"]),
])
def test_bad_group_and_instance_fields(change, needle):
    with pytest.raises(InputError) as e:
        S.parse(_doc(**change))
    for n in needle:
        assert n in str(e.value), (n, str(e.value))


def test_instances_parse_names_and_override():
    spec = S.parse(_doc(instances=[{"group": "g"}, {"group": "g", "name": "x", "material": "b", "scale": 2}]))
    assert [i.name for i in spec.instances] == ["g.1", "x"] and spec.instances[1].material == "b"
    assert spec.objects == ()
    geo = S.build(spec).geometry
    assert geo.object_names == ("g.1/box", "x/box")
    assert list(np.asarray(geo.object_material)) == [0, 1]
    from jaxrt import sweep

    with pytest.raises(InputError, match=r"address \[\[objects\]\] only"):
        sweep.substitute(spec, None, None)
    # a scene without groups keeps the plain single-level geometry
    plain = _doc(objects=[{"primitive": "box", "material": "a"}])
    del plain["groups"], plain["instances"]
    assert isinstance(S.load(plain).geometry, TriangleGeometry)


# --------------------------------------------------------------------------- 1000 bunnies


@pytest.mark.data
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_thousand_bunnies_memory_and_rays(data_dir, fns, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    base = {"camera": {"position": [0, 0, 30], "look_at": [0, 0, 0], "width": 8, "height": 8},
            "lights": [{"position": [0, 50, 50], "intensity": 10}], "materials": {"m": {"model": "lambert"}}}
    one = S.load(dict(base, objects=[{"mesh": "bunny", "material": "m"}]))
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(*[np.arange(10.0)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.25 - 1.125
    insts = [{"group": "b", "translate": list(map(float, g)), "rotate": [0.0, float(a), 0.0], "scale": float(s)}
             for g, a, s in zip(grid, rng.uniform(0, 360, 1000), rng.uniform(0.8, 1.3, 1000))]
    many = S.load(dict(base, groups=[{"name": "b", "objects": [{"mesh": "bunny", "material": "m"}]}],
                       instances=insts))
    b1, bn = S.device_bytes(one), S.device_bytes(many)
    assert bn < 1.2 * b1 + 1000 * 400, (b1, bn)
    assert many.geometry.triangle_count == 1000 * one.geometry.faces.shape[0]

    # rays aimed at a few instances from outside the grid, against brute force over every instance
    # whose world box (float64, from the explicitly transformed vertices) the ray crosses
    geo, tree = many.geometry, many.geometry.tree
    v = np.asarray(geo.vertices, np.float64)
    f = np.asarray(geo.faces)
    xf = np.asarray(tree.object_to_world, np.float64)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    lo, hi = v.min(0), v.max(0)
    pts = lo + corners * (hi - lo)
    w = np.einsum("nij,cj->nci", xf[:, :, :3], pts) + xf[:, None, :, 3]
    blo, bhi = w.min(1), w.max(1)
    targets = rng.choice(1000, 4, replace=False)
    o, d = [], []
    for i in targets:
        tri = v[f[rng.integers(0, len(f), 3)]]
        p = np.einsum("kj,kjc->kc", rng.dirichlet([1, 1, 1], 3), tri) @ xf[i, :, :3].T + xf[i, :, 3]
        src = rng.normal(size=(3, 3))
        src = 4.0 * src / np.linalg.norm(src, axis=1, keepdims=True)
        o.append(src)
        d.append(p - src)
    o = np.concatenate(o).astype(np.float32)
    d = np.concatenate(d).astype(np.float32)
    hit = fns[0](tree, o, d, 0.0, np.inf)
    prim, t = np.asarray(hit.prim), np.asarray(hit.t, np.float64)
    nf = len(f)
    for r in range(len(o)):
        o64, d64 = o[r].astype(np.float64), d[r].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (blo - o64) / d64, (bhi - o64) / d64
        near = np.nanmax(np.minimum(t0, t1), 1)
        far = np.nanmin(np.maximum(t0, t1), 1)
        cand = np.flatnonzero(near <= far)
        tri = np.concatenate([v[f] @ xf[c, :, :3].T + xf[c, :, 3] for c in cand])
        ref_t, ref_p = brute_force(tri, o64[None], d64[None], np.zeros(1), np.full(1, np.inf), block=1)
        ref = cand[ref_p[0] // nf] * nf + ref_p[0] % nf if ref_p[0] >= 0 else -1
        assert prim[r] == ref, (r, prim[r], ref)
        if ref >= 0:
            assert abs(t[r] - ref_t[0]) <= 1e-5 * ref_t[0]
    assert np.mean(prim >= 0) > 0.5


@pytest.mark.slow
@pytest.mark.data
def test_bunny_field_scene_is_finite(data_dir, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    sc = S.load("bunnies", overrides={"camera.width": 32, "camera.height": 24})
    assert sc.geometry.triangle_count == 100 * 69451 + 2  # + the table
    img, aovs = R.frame(sc, aovs=True)
    img, oid = np.asarray(img), np.asarray(aovs["object_id"])
    assert np.all(np.isfinite(img)) and img.max() > 0.05
    assert len(np.unique(oid[oid > 0])) > 20  # many distinct bunnies in view (object 0 is the table)
