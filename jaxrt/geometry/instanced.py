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
identity. Instances hold only a 3x4 transform and a few ints (`jaxrt.accel.two_level`). Scenes
without [[instances]] build a `TriangleGeometry`.

Objects of an instanced scene: every (instance, group object) pair is one scene object named
"INSTANCE/OBJECT" (plain objects keep their names); its material is `object_material[object]`,
so a group's material override, or `set_object_material` (`with_object_material`, used by sweeps and fits), is a value
change of an (O,) array, O = instances x objects per group. Sweeps and fits (`jaxrt.scene.edit`)
still address plain [[objects]] only.

Hit identity: `prim` is a virtual face id (instance face offset + local face; see
`jaxrt.accel.two_level.decode`). Both geometry kinds implement `jaxrt.geometry.AbstractGeometry`,
so code that needs a hit's material or object calls `face_material` / `face_object` and never asks
which kind it has.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrt.accel import two_level
from jaxrt.geometry.base import AbstractGeometry
from jaxrt.shading.surface import Surface, interpolate, make_surface


class InstancedGeometry(AbstractGeometry):
    """Prototypes stored once plus instances (see module docstring).

    vertices/normals/tangents (V, 3): all prototypes, in prototype (group) space; uvs (V, 2) texture
    coordinates (zeros where a mesh has none); faces (F, 3) int32 into them; proto_face_object (F,)
    int32: object index within the face's prototype; proto_face_offset (P,) int32: first face of
    each prototype; inst_object_base (I,) int32: scene object id of each instance's first object;
    object_material (O,) int32 material id per scene object; tree: `jaxrt.accel.InstancedBVH`
    (holds the instance transforms and prototype ids).
    """

    vertices: Float[Array, "V 3"]
    normals: Float[Array, "V 3"]
    tangents: Float[Array, "V 3"]
    uvs: Float[Array, "V 2"]
    faces: Int[Array, "F 3"]
    proto_face_object: Int[Array, " F"]
    proto_face_offset: Int[Array, " P"]
    inst_object_base: Int[Array, " I"]
    object_material: Int[Array, " O"]
    tree: two_level.InstancedBVH
    object_names: tuple[str, ...] = eqx.field(static=True)
    num_faces: int = eqx.field(static=True)  # virtual face ids: every instance's copy counted

    def intersect(self, origins, directions, tmin=0.0, tmax=jnp.inf, *, order=None):
        # (order is a hint the two-level traversal does not take)
        return two_level.intersect(self.tree, origins, directions, tmin=tmin, tmax=tmax)

    def occluded(self, origins, directions, tmax, *, from_end=False, order=None):
        # the two-level traversal always traces forwards (from_end and order are hints)
        return two_level.occluded(self.tree, origins, directions, tmax)

    def _face(self, prim):
        """(instance, prototype face index into self.faces) of virtual face ids."""
        inst, local = two_level.decode(self.tree, prim)
        return inst, self.proto_face_offset[self.tree.inst_proto[inst]] + local

    def _object(self, inst, face):
        return self.inst_object_base[inst] + self.proto_face_object[face]

    def triangles(self, prim):
        inst, face = self._face(prim)
        f = self.faces[face]
        m = self.tree.object_to_world[inst]
        a = m[..., :3]
        return tuple(jnp.einsum("...ij,...j->...i", a, self.vertices[f[..., k]]) + m[..., 3] for k in range(3))

    def surface(self, prim, u, v) -> Surface:
        """Vertices map with the instance's object-to-world matrix A|b, the interpolated normal with
        the inverse transpose (A^-1)^T (read from the stored world-to-object matrix), tangents with A."""
        inst, face = self._face(prim)
        f = self.faces[face]
        a = self.tree.object_to_world[inst][:, :, :3]
        a_inv = self.tree.world_to_object[inst][:, :, :3]
        v0, v1, v2 = self.triangles(prim)
        ns = jnp.einsum("bji,bj->bi", a_inv, interpolate(self.normals, f, u, v))
        tg = jnp.einsum("bij,bj->bi", a, interpolate(self.tangents, f, u, v))
        mat = self.object_material[self._object(inst, face)]
        return make_surface(v0, v1, v2, ns, tg, mat, u, v, interpolate(self.uvs, f, u, v))

    def face_object(self, prim):
        return self._object(*self._face(prim))

    def face_material(self, prim):
        return self.object_material[self.face_object(prim)]

    def with_object_material(self, obj, material):
        return eqx.tree_at(lambda g: g.object_material, self, self.object_material.at[obj].set(jnp.int32(material)))

    def object_triangles(self, obj):
        base = np.asarray(self.inst_object_base)
        inst = int(np.searchsorted(base, obj, side="right") - 1)
        tree = self.tree
        p = int(np.asarray(tree.inst_proto)[inst])
        f_off = np.asarray(self.proto_face_offset)
        end = f_off[p + 1] if p + 1 < len(f_off) else self.faces.shape[0]
        sel = np.arange(f_off[p], end)
        sel = sel[np.asarray(self.proto_face_object)[sel] == obj - base[inst]]
        m = np.asarray(tree.object_to_world, np.float64)[inst]
        tri = np.asarray(self.vertices, np.float64)[np.asarray(self.faces)[sel]]
        return tri @ m[:, :3].T + m[:, 3]

    @property
    def triangle_count(self) -> int:
        return self.num_faces

    @property
    def face_count(self) -> int:
        return self.num_faces
