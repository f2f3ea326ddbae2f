"""Validated spec -> `Scene`: loads meshes, places primitives and instances, builds the BVH, and
groups materials by model into stacked parameter tables.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from collections.abc import Callable, Mapping
from typing import Any

import jax
import numpy as np

import brdfs
from jaxrt import accel, envmap, integrators
from jaxrt import cache as _cache
from jaxrt.accel import two_level
from jaxrt.camera import Camera
from jaxrt.errors import InputError
from jaxrt.geometry import mesh as _mesh
from jaxrt.geometry import shapes
from jaxrt.geometry.instanced import InstancedGeometry
from jaxrt.geometry.triangles import TriangleGeometry
from jaxrt.shading import textures as _tx
from jaxrt.lights import AreaLights, PointLights
from jaxrt.scene.parse import find_scene, parse
from jaxrt.scene.spec import ObjectSpec, SceneSpec
from jaxrt.scene.tables import MAX_MAGNITUDE
from jaxrt.scene.types import Materials, Scene, Settings


def _put(x, dtype=None):
    # a plain host-to-device transfer: jnp.asarray of host data compiles a small staging program
    # for every new shape and dtype, a dozen compilations per scene
    return jax.device_put(np.asarray(x, dtype))


def object_meshes(o: ObjectSpec, cache: dict):
    """[(scene-object name, mesh, material name)] for one [[objects]] entry, transformed to world.

    Through `jaxrt.cache`: a later process with the same object (mesh file contents, parts,
    primitive, transform) reads the result instead of loading, splitting and transforming again.
    `cache` shares loaded mesh files between the objects of one build.
    """
    spec = {k: v for k, v in dataclasses.asdict(o).items() if k != "mesh"}
    key = {"object": spec, "files": [] if o.mesh is None else [str(o.mesh)]}
    pieces = _cache.cached_meshes("object", key, lambda: [([n, mat], m) for n, m, mat in _object_meshes(o, cache)],
                                  sources=(shapes, sys.modules[__name__]))
    return [(n, m, mat) for (n, mat), m in pieces]


def _object_meshes(o: ObjectSpec, cache: dict):
    if o.primitive is not None:
        try:
            m = shapes.PRIMITIVES[o.primitive](**o.primitive_args, name=o.name)
        except InputError as e:  # e.g. a primitive too small for float32 triangles
            detail = str(e).removeprefix(f"{o.name}: ")
            raise InputError(f"object {o.name!r} ({o.primitive} {o.primitive_args}): {detail}") from None
        pieces = [(o.name, m, o.material)]
    else:
        key = (str(o.mesh), o.flat)
        if key not in cache:
            try:
                cache[key] = _cache.load_mesh(o.mesh, flat=o.flat)
            except InputError:
                raise
            except (ValueError, OSError) as e:
                raise InputError(f"object {o.name!r}: cannot load mesh {o.mesh}: {e}") from None
        m = cache[key]
        names = tuple(m.names)
        unknown = [p for p in (o.parts or ()) if p not in names]
        unknown += [p for p in o.part_materials if p not in names]
        if unknown:
            raise InputError(
                f"object {o.name!r}: {o.mesh.name} has no part {unknown[0]!r}; parts: {', '.join(names)}"
            )
        if o.parts is None and not o.part_materials:
            pieces = [(o.name, m, o.material)]
        else:
            pieces = []
            oid = np.asarray(m.object_id)
            for k, part in enumerate(names):
                if o.parts is not None and part not in o.parts:
                    continue
                f = np.asarray(m.faces)[oid == k]
                sub = _mesh.Mesh.from_arrays(
                    np.asarray(m.vertices), f, normals=np.asarray(m.normals),
                    uvs=None if m.uvs is None else np.asarray(m.uvs), name=part,
                )
                pieces.append((f"{o.name}/{part}", sub, o.part_materials.get(part, o.material)))
    out = []
    for name, m, mat in pieces:
        if o.scale is not None or o.rotate is not None or o.translate is not None:
            m = m.transformed(
                scale=1.0 if o.scale is None else np.asarray(o.scale),
                rotation=(0.0, 0.0, 0.0) if o.rotate is None else o.rotate,
                translation=(0.0, 0.0, 0.0) if o.translate is None else o.translate,
            )
        check_extent(np.asarray(m.vertices), f"object {name!r}")
        out.append((name, m, mat))
    return out


def check_extent(vertices: np.ndarray, where: str) -> None:
    """Vertices placed in the world must stay within ±MAX_MAGNITUDE (jaxrt.scene.tables), where
    the squares the renderer forms stay finite in float32."""
    with np.errstate(over="ignore", invalid="ignore"):
        peak = float(np.max(np.abs(vertices))) if vertices.size else 0.0
    if not peak <= MAX_MAGNITUDE:
        raise InputError(f"{where}: after its scale and translate the geometry reaches {peak:g}; "
                         f"coordinates must stay within ±{MAX_MAGNITUDE:g}")



def build(spec: SceneSpec, *, on_shapes: Callable[[Scene], Any] | None = None) -> Scene:
    """Turn a validated spec into the `Scene` pytree (loads meshes, builds the BVH).

    on_shapes: called once, before the BVH is built, with the scene whose tree arrays are only
    `jax.ShapeDtypeStruct`s (`jaxrt.accel.bvh.shapes`; every other array is the scene's own), so a
    caller can compile the scene's programs, which need only shapes, while the tree is built on the
    host (the full dragon's SAH build takes seconds). Not called where the tree's shapes cannot be
    known first (instanced scenes, leaves of more than one triangle).
    """
    # materials grouped by model, in order of first appearance
    mat_names = tuple(spec.materials)
    models: list[str] = []
    rows: dict[str, list] = {}
    model_id, row, delta = [], [], []
    for n in mat_names:
        ms = spec.materials[n]
        if ms.model not in models:
            models.append(ms.model)
            rows[ms.model] = []
        model_id.append(models.index(ms.model))
        row.append(len(rows[ms.model]))
        # a measured material's spec holds its raw data; the sampler's tables are added here (in JAX)
        model = brdfs.get(ms.model)
        rows[ms.model].append(brdfs.measured.complete(model, ms.params) if brdfs.is_measured(model) else ms.params)
        delta.append(ms.delta)
    tables = tuple(
        {p: _put(np.stack([np.asarray(r[p]) for r in rows[mname]]))
         for p in (brdfs.get(mname).param_names or tuple(rows[mname][0]))}
        for mname in models
    )
    texs, bindings = [], []
    for n, mid, r in zip(mat_names, model_id, row):
        for pname, ts in spec.materials[n].textures.items():
            bindings.append((mid, r, pname, len(texs)))
            texs.append(_tx.make(ts.texels, ts.kind, ts.wrap, ts.uv_scale, ts.uv_offset))
    materials = Materials(
        params=tables,
        model_id=_put(model_id, np.int32),
        row=_put(row, np.int32),
        delta=_put(delta, np.float32),
        models=tuple(models),
        names=mat_names,
        textures=tuple(texs),
        bindings=tuple(bindings),
        # "" for opaque materials, so that the set of choices in use is static (jaxrt.shading.material)
        fresnel=tuple(spec.materials[n].fresnel if brdfs.get(spec.materials[n].model).delta else ""
                      for n in mat_names),
    )

    cache: dict = {}
    pending = None
    if spec.instances:
        geometry = build_instanced(spec, mat_names, cache)
    else:
        meshes, obj_names, face_mat, face_obj = [], [], [], []
        for o in spec.objects:
            for name, m, mat in object_meshes(o, cache):
                nf = int(np.asarray(m.faces).shape[0])
                face_mat.append(np.full(nf, mat_names.index(mat), np.int32))
                face_obj.append(np.full(nf, len(obj_names), np.int32))
                obj_names.append(name)
                meshes.append(m)
        whole = _mesh.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        verts = np.asarray(whole.vertices, np.float32)
        faces = np.asarray(whole.faces, np.int32)
        if not np.all(np.isfinite(verts)):
            raise InputError(f"{spec.source}: scene geometry contains non-finite vertices")
        leaf = accel.RENDER_TREE.get("leaf_size", 1)
        tree = None if on_shapes is None else accel.bvh.shapes(len(faces), leaf_size=leaf)
        if tree is not None:
            pending = verts, faces  # the tree is built last, after `on_shapes` has the other arrays
        else:
            tree = _cache.build_bvh(verts, faces, **accel.RENDER_TREE)
        geometry = TriangleGeometry(
            vertices=_put(verts),
            normals=_put(np.asarray(whole.normals, np.float32)),
            tangents=_put(np.asarray(whole.tangents, np.float32)),
            faces=_put(faces),
            material=_put(np.concatenate(face_mat)),
            object_id=_put(np.concatenate(face_obj)),
            tree=tree,
            object_names=tuple(obj_names),
            # mesh.concatenate drops UVs unless every mesh has them: keep them, zeros where a mesh has none
            uvs=_put(np.concatenate([np.zeros((m.num_vertices, 2), np.float32) if m.uvs is None
                                            else np.asarray(m.uvs, np.float32) for m in meshes])),
        )

    lights = PointLights(
        position=_put(np.reshape([l[0] for l in spec.lights], (-1, 3)), np.float32),
        intensity=_put(np.reshape([l[1] for l in spec.lights], (-1, 3)), np.float32),
    )
    emission = np.asarray([spec.materials[n].emission for n in mat_names], np.float32).reshape(-1, 3)
    if spec.instances:
        emitting = [n for n in mat_names if max(spec.materials[n].emission) > 0]
        if emitting:
            raise InputError(f"{spec.source}: materials.{emitting[0]}.emission: emissive materials are not "
                             "supported in scenes with [[instances]] yet; use plain [[objects]] for lights")
        fmat = np.zeros(0, np.int32)
    else:
        fmat = np.concatenate(face_mat)
    area_lights = AreaLights(
        emission=_put(emission),
        prims=_put(np.nonzero(emission.max(axis=1)[fmat] > 0)[0].astype(np.int32)),
    )
    environment = None
    if spec.environment is not None:
        e = spec.environment
        if e.file is None:
            radiance = np.asarray(e.radiance) * e.scale
            peak = float(radiance.max())
        else:
            environment = envmap.load(e.file, scale=e.scale, rotate=e.rotate)
            peak = float(np.max(np.asarray(environment.texels)))
        if not peak <= MAX_MAGNITUDE:
            what = "radiance" if e.file is None else f"{e.file}: texels"
            raise InputError(f"{spec.source}: [environment] scale: {what} × scale reaches {peak:g}; "
                             f"radiance must stay within {MAX_MAGNITUDE:g}")
        if e.file is None:
            environment = envmap.constant(radiance)
    c = spec.camera
    camera = Camera(
        position=_put(c.position, np.float32), look_at=_put(c.look_at, np.float32),
        up=_put(c.up, np.float32), vfov=_put(c.vfov, np.float32),
        aperture=_put(c.aperture, np.float32), focus_distance=_put(c.focus_distance, np.float32),
        width=c.width, height=c.height,
    )
    r = spec.render
    has_glass = any(brdfs.get(m).delta for m in models)
    settings = Settings(
        background=_put(r.background, np.float32),
        seed=_put(r.seed, np.int32),
        integrator=r.integrator,
        max_depth=r.max_depth,
        spp=r.spp,
        ray_budget=r.ray_budget if r.ray_budget is not None else (2 if has_glass else 1),
        glass_shadows=r.glass_shadows,
        photons=r.photons,
        radius=r.radius,
        camera_samples=r.camera_samples,
        grid_levels=r.grid_levels,
        photon_aim=r.photon_aim if r.photon_aim is not None else integrators.sppm.default_photon_aim(
            any(brdfs.get(spec.materials[n].model).delta or spec.materials[n].delta > 0 for n in mat_names)),
        alpha=r.alpha,
    )
    scene = Scene(geometry, materials, lights, camera, settings, source=spec.source, area_lights=area_lights,
                  environment=environment, glare=spec.glare)
    if pending is not None:
        on_shapes(scene)
        tree = _cache.build_bvh(*pending, **accel.RENDER_TREE)
        scene = dataclasses.replace(scene, geometry=dataclasses.replace(scene.geometry, tree=tree))
    return scene



def load(
    source: str | os.PathLike | Mapping, base_dir: str | os.PathLike | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> Scene:
    """Validate then build a scene.

    Args:
        source: a TOML path, a shipped scene name (`spheres`), or an already-parsed dict.
        base_dir: directory that relative mesh paths are resolved against (default: the file's).
        overrides: {"camera.width": 64, "render.spp": 4, ...} applied before validation.
    Raises:
        InputError: one line naming file, table and key, and what is allowed.
    """
    if not isinstance(source, Mapping):
        source = find_scene(source)
    return build(parse(source, base_dir=base_dir, overrides=overrides))


def instance_matrix(scale, rotate, translate) -> np.ndarray:
    """(3, 4) float64 [R diag(s) | t]: p' = R @ (s * p) + t, R from XYZ Euler degrees (as mesh.transformed)."""
    import trimesh.transformations as tf

    s = np.ones(3) if scale is None else np.asarray(scale, np.float64)
    r = np.eye(3) if rotate is None else tf.euler_matrix(*np.radians(rotate), axes="sxyz")[:3, :3]
    t = np.zeros(3) if translate is None else np.asarray(translate, np.float64)
    if not (np.all(np.isfinite(s)) and np.all(s > 0) and np.all(np.isfinite(t)) and math.isfinite(np.sum(r))):
        raise InputError(f"instance transform: bad scale {scale!r} / rotate {rotate!r} / translate {translate!r}")
    return np.concatenate([r * s[None, :], t[:, None]], axis=1)



def build_instanced(spec: SceneSpec, mat_names: tuple[str, ...], cache: dict) -> InstancedGeometry:
    """`InstancedGeometry` of a parsed scene with [[instances]] (host side; builds the two-level BVH)."""
    protos = []  # (vertices, normals, tangents, faces (local), face_object, [(piece name, material)])

    def add_proto(objs):
        pieces = [pc for o in objs for pc in object_meshes(o, cache)]
        meshes = [m for _, m, _ in pieces]
        whole = _mesh.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        f_obj = np.concatenate([np.full(len(np.asarray(m.faces)), k, np.int32) for k, m in enumerate(meshes)])
        # mesh.concatenate drops UVs unless every mesh has them: keep them, zeros where a mesh has none
        uvs = np.concatenate([np.zeros((m.num_vertices, 2), np.float32) if m.uvs is None
                              else np.asarray(m.uvs, np.float32) for m in meshes])
        protos.append((np.asarray(whole.vertices, np.float32), np.asarray(whole.normals, np.float32),
                       np.asarray(whole.tangents, np.float32), np.asarray(whole.faces, np.int32), f_obj,
                       [(n, mat) for n, _, mat in pieces], uvs))
        return len(protos) - 1

    inst_proto, xforms, names, obj_mat, obj_base = [], [], [], [], []

    def place(p, m, prefix, override):
        inst_proto.append(p)
        xforms.append(m)
        obj_base.append(len(names))
        for piece, mat in protos[p][5]:
            names.append(prefix + piece)
            obj_mat.append(mat_names.index(override or mat))

    if spec.objects:
        place(add_proto(spec.objects), np.eye(3, 4), "", None)
    group_proto: dict[str, int] = {}
    groups = {g.name: g for g in spec.groups}
    for inst in spec.instances:
        if inst.group not in group_proto:
            group_proto[inst.group] = add_proto(groups[inst.group].objects)
        place(group_proto[inst.group], instance_matrix(inst.scale, inst.rotate, inst.translate),
              inst.name + "/", inst.material)
    for v, *_ in protos:
        if not np.all(np.isfinite(v)):
            raise InputError(f"{spec.source}: scene geometry contains non-finite vertices")
    for inst in spec.instances:  # the world-space extent of each placement (corners of its bounds)
        v = protos[group_proto[inst.group]][0]
        lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)
        m = instance_matrix(inst.scale, inst.rotate, inst.translate)
        check_extent(corners @ m[:, :3].T + m[:, 3], f"{spec.source}: instance {inst.name!r}")
    tree = two_level.build([(p[0], p[3]) for p in protos], inst_proto, np.asarray(xforms))
    v_off = np.cumsum([0] + [len(p[0]) for p in protos])[:-1]
    f_off = np.cumsum([0] + [len(p[3]) for p in protos])[:-1]
    return InstancedGeometry(
        vertices=_put(np.concatenate([p[0] for p in protos])),
        normals=_put(np.concatenate([p[1] for p in protos])),
        tangents=_put(np.concatenate([p[2] for p in protos])),
        uvs=_put(np.concatenate([p[6] for p in protos])),
        faces=_put(np.concatenate([p[3] + o for p, o in zip(protos, v_off)]).astype(np.int32)),
        proto_face_object=_put(np.concatenate([p[4] for p in protos])),
        proto_face_offset=_put(f_off.astype(np.int32)),
        inst_object_base=_put(np.asarray(obj_base, np.int32)),
        object_material=_put(np.asarray(obj_mat, np.int32)),
        tree=tree,
        object_names=tuple(names),
        num_faces=int(sum(len(protos[p][3]) for p in inst_proto)),
    )
