"""Object groups and instancing: scene syntax, `InstancedGeometry`, and per-hit accessors.

A scene file may define groups (several meshes/primitives with their materials and transforms)
once and place them many times:

    [[groups]]
    name = "pair"
    [[groups.objects]]                 # same keys as [[objects]]; a group cannot contain groups
    primitive = "sphere"
    material = "red"
    [[instances]]
    group = "pair"
    name = "pair_a"                    # optional; default GROUP.K
    translate = [1.0, 0.0, 0.0]        # also scale (number or 3, > 0) and rotate (XYZ degrees),
    rotate = [0.0, 45.0, 0.0]          # p_world = R @ (scale * p_group) + translate, as for objects
    material = "gold"                  # optional: overrides the material of every object in the group

A scene with [[instances]] builds an `InstancedGeometry`: every group is one prototype (its
objects' own transforms are baked into the prototype's vertices, in group space), stored once with
its own BVH; plain [[objects]] of the same scene form one more prototype placed once with the
identity. Instances hold only a 3x4 transform and a few ints (`jaxrt.bvh_instanced`). Scenes
without [[instances]] build the plain `scene.Geometry` exactly as before.

Objects of an instanced scene: every (instance, group object) pair is one scene object named
"INSTANCE/OBJECT" (plain objects keep their names); its material is `object_material[object]`,
so a group's material override, or `set_object_material` (used by `sweep.use_model`), is a value
change of an (O,) array, O = instances x objects per group. Sweeps and fits (`sweep.substitute`)
still address plain [[objects]] only.

Hit identity: `prim` is a virtual face id (instance face offset + local face; see
`bvh_instanced.decode`). Code that needs a hit's material or object uses `face_material` /
`face_object`, which work on both geometry kinds.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrt import bvh_instanced
from jaxrt.errors import InputError


@dataclasses.dataclass(frozen=True)
class GroupSpec:
    name: str
    objects: tuple  # scene.ObjectSpec, in group space


@dataclasses.dataclass(frozen=True)
class InstanceSpec:
    name: str
    group: str
    scale: Any  # (3,) or None
    rotate: tuple | None  # XYZ degrees
    translate: tuple | None
    material: str | None  # override of every object's material in the group


class InstancedGeometry(eqx.Module):
    """Prototypes stored once plus instances (see module docstring).

    vertices/normals/tangents (V, 3): all prototypes, in prototype (group) space; uvs (V, 2) texture
    coordinates (zeros where a mesh has none); faces (F, 3)
    int32 into them; face_object (F,) int32: object index within the face's prototype;
    proto_face_offset (P,) int32: first face of each prototype; inst_object_base (I,) int32: scene
    object id of each instance's first object; object_material (O,) int32 material id per scene
    object; tree: `bvh_instanced.InstancedBVH` (holds the instance transforms and prototype ids).
    """

    vertices: Float[Array, "V 3"]
    normals: Float[Array, "V 3"]
    tangents: Float[Array, "V 3"]
    uvs: Float[Array, "V 2"]
    faces: Int[Array, "F 3"]
    face_object: Int[Array, " F"]
    proto_face_offset: Int[Array, " P"]
    inst_object_base: Int[Array, " I"]
    object_material: Int[Array, " O"]
    tree: bvh_instanced.InstancedBVH
    object_names: tuple[str, ...] = eqx.field(static=True)


def is_instanced(geometry) -> bool:
    return isinstance(geometry, InstancedGeometry)


# --------------------------------------------------------------------------- parse


def parse(doc: dict, file: str, materials: dict, base, parse_object, names_seen: set[str]):
    """Validate [[groups]] and [[instances]] of a parsed TOML document.

    parse_object(checker, names_seen) parses one object table (scene._parse_object). Returns
    (groups, instances) as tuples of GroupSpec / InstanceSpec; ((), ()) when the scene has none.
    Raises InputError naming the file, table and key.
    """
    from jaxrt.scene import _Checker, _parse_transform, _unique_name

    raw_groups, raw_inst = doc.get("groups"), doc.get("instances")
    if raw_groups is None and raw_inst is None:
        return (), ()
    top = _Checker(file, "top level", {k: doc[k] for k in ("groups", "instances") if k in doc})
    if raw_groups is not None and (not isinstance(raw_groups, list) or not raw_groups):
        top.fail("groups", "expected one or more [[groups]] tables")
    groups: dict[str, GroupSpec] = {}
    for i, g in enumerate(raw_groups or []):
        gc = _Checker(file, f"[groups] #{i + 1}", g)
        name = gc.string("name")
        if not name or "/" in name:
            gc.fail("name", f"{name!r}: expected a non-empty name without '/'")
        if name in groups:
            gc.fail("name", f"{name!r}: a group of this name is already defined")
        objs = gc.raw("objects", None)
        if not isinstance(objs, list) or not objs:
            gc.fail("objects", "expected one or more [[groups.objects]] tables")
        gc.done()
        seen: set[str] = set()
        specs = []
        for j, o in enumerate(objs):
            oc = _Checker(file, f"[groups] {name}: [objects] #{j + 1}", o)
            if "group" in o:
                oc.fail("group", "groups cannot contain groups (nested instancing is not supported); "
                                 "place each group with [[instances]]")
            specs.append(parse_object(oc, seen))
        groups[name] = GroupSpec(name, tuple(specs))
    if raw_inst is None:
        return tuple(groups.values()), ()
    if not isinstance(raw_inst, list) or not raw_inst:
        top.fail("instances", "expected one or more [[instances]] tables")
    instances = []
    counts: dict[str, int] = {}
    for i, t in enumerate(raw_inst):
        ic = _Checker(file, f"[instances] #{i + 1}", t)
        group = ic.raw("group")
        if not isinstance(group, str) or group not in groups:
            ic.fail("group", f"{group!r} is not a defined group; groups: {', '.join(groups) or '(none)'}")
        name = ic.string("name", None)
        if name is None:
            counts[group] = counts.get(group, 0) + 1
            name = f"{group}.{counts[group]}"
        if not name or "/" in name:
            ic.fail("name", f"{name!r}: expected a non-empty name without '/'")
        name = _unique_name(name, names_seen)
        scale, rotate, translate = _parse_transform(ic)
        material = ic.string("material", None, choices=tuple(materials))
        ic.done()
        instances.append(InstanceSpec(name, group, scale, rotate, translate, material))
    return tuple(groups.values()), tuple(instances)


def instance_matrix(scale, rotate, translate) -> np.ndarray:
    """(3, 4) float64 [R diag(s) | t]: p' = R @ (s * p) + t, R from XYZ Euler degrees (as mesh.transformed)."""
    import trimesh.transformations as tf

    s = np.ones(3) if scale is None else np.asarray(scale, np.float64)
    r = np.eye(3) if rotate is None else tf.euler_matrix(*np.radians(rotate), axes="sxyz")[:3, :3]
    t = np.zeros(3) if translate is None else np.asarray(translate, np.float64)
    if not (np.all(np.isfinite(s)) and np.all(s > 0) and np.all(np.isfinite(t)) and math.isfinite(np.sum(r))):
        raise InputError(f"instance transform: bad scale {scale!r} / rotate {rotate!r} / translate {translate!r}")
    return np.concatenate([r * s[None, :], t[:, None]], axis=1)


# --------------------------------------------------------------------------- build


def build_geometry(spec, mat_names: tuple[str, ...], cache: dict) -> InstancedGeometry:
    """`InstancedGeometry` of a parsed scene with [[instances]] (host side; builds the two-level BVH)."""
    from jaxrt import mesh as _mesh
    from jaxrt.scene import _object_meshes

    protos = []  # (vertices, normals, tangents, faces (local), face_object, [(piece name, material)])

    def add_proto(objs):
        pieces = [pc for o in objs for pc in _object_meshes(o, cache)]
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
    tree = bvh_instanced.build([(p[0], p[3]) for p in protos], inst_proto, np.asarray(xforms))
    v_off = np.cumsum([0] + [len(p[0]) for p in protos])[:-1]
    f_off = np.cumsum([0] + [len(p[3]) for p in protos])[:-1]
    return InstancedGeometry(
        vertices=jnp.asarray(np.concatenate([p[0] for p in protos])),
        normals=jnp.asarray(np.concatenate([p[1] for p in protos])),
        tangents=jnp.asarray(np.concatenate([p[2] for p in protos])),
        uvs=jnp.asarray(np.concatenate([p[6] for p in protos])),
        faces=jnp.asarray(np.concatenate([p[3] + o for p, o in zip(protos, v_off)]).astype(np.int32)),
        face_object=jnp.asarray(np.concatenate([p[4] for p in protos])),
        proto_face_offset=jnp.asarray(f_off.astype(np.int32)),
        inst_object_base=jnp.asarray(np.asarray(obj_base, np.int32)),
        object_material=jnp.asarray(np.asarray(obj_mat, np.int32)),
        tree=tree,
        object_names=tuple(names),
    )


# --------------------------------------------------------------------------- per-hit accessors


def _face(geometry: InstancedGeometry, prim):
    """(instance, prototype face index into geometry.faces) of virtual face ids."""
    tree = geometry.tree
    inst, local = bvh_instanced.decode(tree, prim)
    return inst, geometry.proto_face_offset[tree.inst_proto[inst]] + local


def face_object(geometry, prim: Int[Array, "..."]) -> Int[Array, "..."]:
    """Scene-object id of faces `prim` (any shape; -1 reads face 0: mask misses yourself)."""
    if not is_instanced(geometry):
        return geometry.object_id[jnp.maximum(prim, 0)]
    inst, face = _face(geometry, prim)
    return geometry.inst_object_base[inst] + geometry.face_object[face]


def face_material(geometry, prim: Int[Array, "..."]) -> Int[Array, "..."]:
    """Material id of faces `prim` (any shape; -1 reads face 0: mask misses yourself)."""
    if not is_instanced(geometry):
        return geometry.material[jnp.maximum(prim, 0)]
    return geometry.object_material[face_object(geometry, prim)]


def surface_arrays(geometry: InstancedGeometry, prim, u, v):
    """World-space (p, ng, ns (not normalised), tangent, material, uv) of instanced hits, each (B, ...).

    Vertices map with the instance's object-to-world matrix A|b, the interpolated normal with the
    inverse transpose (A^-1)^T (read from the stored world-to-object matrix), tangents with A.
    """
    tree = geometry.tree
    inst, face = _face(geometry, prim)
    f = geometry.faces[face]
    m = tree.object_to_world[inst]
    a = m[:, :, :3]
    a_inv = tree.world_to_object[inst][:, :, :3]
    v0, v1, v2 = (jnp.einsum("bij,bj->bi", a, geometry.vertices[f[:, k]]) + m[:, :, 3] for k in range(3))
    w = (1.0 - u - v)[:, None]
    p = w * v0 + u[:, None] * v1 + v[:, None] * v2
    ng = jnp.cross(v1 - v0, v2 - v0)
    n_obj = sum(c * geometry.normals[f[:, k]] for k, c in enumerate((w, u[:, None], v[:, None])))
    ns = jnp.einsum("bji,bj->bi", a_inv, n_obj)
    t_obj = sum(c * geometry.tangents[f[:, k]] for k, c in enumerate((w, u[:, None], v[:, None])))
    tg = jnp.einsum("bij,bj->bi", a, t_obj)
    mat = geometry.object_material[geometry.inst_object_base[inst] + geometry.face_object[face]]
    uv = w * geometry.uvs[f[:, 0]] + u[:, None] * geometry.uvs[f[:, 1]] + v[:, None] * geometry.uvs[f[:, 2]]
    return p, ng, ns, tg, mat, uv


def set_object_material(geometry, obj: int, material: int):
    """A copy of either geometry kind in which scene object `obj` has material id `material`."""
    if not is_instanced(geometry):
        mat = jnp.where(geometry.object_id == obj, jnp.int32(material), geometry.material)
        return eqx.tree_at(lambda g: g.material, geometry, mat)
    return eqx.tree_at(lambda g: g.object_material, geometry,
                       geometry.object_material.at[obj].set(jnp.int32(material)))


def object_triangles(geometry, obj: int) -> np.ndarray:
    """World-space triangles (n, 3, 3) float64 of scene object `obj` (host side)."""
    if not is_instanced(geometry):
        f = np.asarray(geometry.faces)[np.asarray(geometry.object_id) == obj]
        return np.asarray(geometry.vertices, np.float64)[f]
    base = np.asarray(geometry.inst_object_base)
    inst = int(np.searchsorted(base, obj, side="right") - 1)
    tree = geometry.tree
    p = int(np.asarray(tree.inst_proto)[inst])
    f_off = np.asarray(geometry.proto_face_offset)
    end = f_off[p + 1] if p + 1 < len(f_off) else geometry.faces.shape[0]
    sel = np.arange(f_off[p], end)
    sel = sel[np.asarray(geometry.face_object)[sel] == obj - base[inst]]
    m = np.asarray(tree.object_to_world, np.float64)[inst]
    tri = np.asarray(geometry.vertices, np.float64)[np.asarray(geometry.faces)[sel]]
    return tri @ m[:, :3].T + m[:, 3]


def triangle_count(geometry) -> int:
    """Triangles in the scene, counting every instance's copy (host side)."""
    if not is_instanced(geometry):
        return int(geometry.faces.shape[0])
    f_off = np.asarray(geometry.proto_face_offset)
    counts = np.diff(np.concatenate([f_off, [geometry.faces.shape[0]]]))
    return int(counts[np.asarray(geometry.tree.inst_proto)].sum())


def device_bytes(tree_like) -> int:
    """Total bytes of the array leaves of a pytree (e.g. a Scene)."""
    return int(sum(x.nbytes for x in jax.tree.leaves(tree_like) if hasattr(x, "nbytes")))
