"""All triangles of a scene in one set with one BVH: the geometry of scenes without instances."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrt import accel
from jaxrt.geometry.base import AbstractGeometry
from jaxrt.shading.surface import Surface, interpolate, make_surface, surface_at


class TriangleGeometry(AbstractGeometry):
    """All triangles of the scene in one set (original face order) plus its BVH.

    vertices/normals/tangents: (V, 3) world space; faces: (F, 3) int32; material: (F,) material id
    per face; object_id: (F,) scene-object id per face; tree: the `jaxrt.accel.BVH`; uvs: (V, 2)
    texture coordinates (zeros where a mesh has none), or None.
    """

    vertices: Float[Array, "V 3"]
    normals: Float[Array, "V 3"]
    tangents: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    material: Int[Array, " F"]
    object_id: Int[Array, " F"]
    tree: accel.BVH
    object_names: tuple[str, ...] = eqx.field(static=True)
    uvs: Float[Array, "V 2"] | None = None

    def intersect(self, origins, directions, tmin=0.0, tmax=jnp.inf, *, order=None):
        return accel.intersect(self.tree, origins, directions, tmin=tmin, tmax=tmax, order=order)

    def occluded(self, origins, directions, tmax, *, from_end=False, order=None):
        # from the light: coherent origins (see `jaxrt.accel.occluded`)
        return accel.occluded(self.tree, origins, directions, tmax, from_end=from_end, order=order)

    def intersect_surface(self, origins, directions, tmin=0.0, tmax=jnp.inf):
        # the hit point and geometric normal come with the hit (`accel.intersect_points`: Embree
        # computes them from the triangle it has at hand), so the corners are not gathered here;
        # they are the BVH's triangles (built from `vertices`), equal to `surface`'s up to float32
        # rounding, and not differentiable
        hit, p, ng = accel.intersect_points(self.tree, origins, directions, tmin=tmin, tmax=tmax)
        return hit, self._surface_at_hits(hit, p, ng)

    def shadows_in_traversal(self) -> bool:
        """Whether `intersect_surface_shadowed` is available: the CPU with Embree (one call for the
        hits and their shadow rays, `accel.intersect_points_shadowed`)."""
        return accel.uses_embree()

    def intersect_surface_shadowed(self, origins, directions, tmin, tmax, lights):
        """`intersect_surface`, and whether each hit's shadow segment to each point light (L, 3) is
        blocked, (B, L), traced in the same call (`accel.intersect_points_shadowed`; only where
        `shadows_in_traversal()`). Not differentiable."""
        hit, p, ng, occ = accel.intersect_points_shadowed(self.tree, origins, directions, tmin, tmax, lights)
        return hit, self._surface_at_hits(hit, p, ng), occ

    def _surface_at_hits(self, hit, p, ng):
        f = self.faces[jnp.maximum(hit.prim, 0)]  # (B, 3)
        u, v = hit.u, hit.v
        uv = None if self.uvs is None else interpolate(self.uvs, f, u, v)
        return surface_at(p, ng, interpolate(self.normals, f, u, v), interpolate(self.tangents, f, u, v),
                          self.face_material(hit.prim), uv)

    def triangles(self, prim):
        f = self.faces[jnp.maximum(prim, 0)]
        return tuple(self.vertices[f[..., k]] for k in range(3))

    def surface(self, prim, u, v) -> Surface:
        f = self.faces[jnp.maximum(prim, 0)]  # (B, 3)
        v0, v1, v2 = self.triangles(prim)
        uv = None if self.uvs is None else interpolate(self.uvs, f, u, v)
        return make_surface(v0, v1, v2, interpolate(self.normals, f, u, v), interpolate(self.tangents, f, u, v),
                            self.face_material(prim), u, v, uv)

    def face_material(self, prim):
        return self.material[jnp.maximum(prim, 0)]

    def face_object(self, prim):
        return self.object_id[jnp.maximum(prim, 0)]

    def with_object_material(self, obj, material):
        mat = jnp.where(self.object_id == obj, jnp.int32(material), self.material)
        return eqx.tree_at(lambda g: g.material, self, mat)

    def object_triangles(self, obj):
        f = np.asarray(self.faces)[np.asarray(self.object_id) == obj]
        return np.asarray(self.vertices, np.float64)[f]

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])
