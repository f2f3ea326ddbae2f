"""The one geometry interface every integrator, the fitting code and the sweeps program against.

pbrt-v4 has one `Primitive` interface (`Intersect`, `IntersectP`) with `TransformedPrimitive` for
instances; here `AbstractGeometry` plays that role for the two kinds of scene geometry: all
triangles in one set with one BVH (`TriangleGeometry`), and prototypes stored once and placed by
instances over a two-level BVH (`InstancedGeometry`). Code above the geometry layer never asks
which kind it has: it calls these methods.

A hit is identified by `prim` (a face id in the geometry's own numbering; -1 is a miss) and
barycentrics (u, v): the hit point is (1 - u - v)·v0 + u·v1 + v·v2. Traversal is integer work
outside autodiff; `surface` recomputes the differentiable hit point from (prim, u, v).
"""

from __future__ import annotations

import abc

import equinox as eqx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxrt.accel import Hit
from jaxrt.shading.surface import Surface


class AbstractGeometry(eqx.Module):
    """Scene geometry: traversal, per-hit surface data, and object/material bookkeeping.

    Every implementation has `object_names` (static: one name per scene object, index = object id)
    and a `tree` (its acceleration structure).
    """

    object_names: eqx.AbstractVar[tuple[str, ...]]

    @abc.abstractmethod
    def intersect(self, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
                  tmin: Float[Array, " N"] | float = 0.0, tmax: Float[Array, " N"] | float = float("inf"), *,
                  order: Int[Array, " N"] | None = None) -> Hit:
        """Closest hit with t in [tmin, tmax] (see `jaxrt.accel.intersect`). order: a hint, a permutation
        of the rays in which a GPU kernel may take them (live rays first, say); the results are the same."""

    @abc.abstractmethod
    def occluded(self, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
                 tmax: Float[Array, " N"] | float, *, from_end: bool = False,
                 order: Int[Array, " N"] | None = None) -> Bool[Array, " N"]:
        """Any hit with t in [0, tmax] (shadow rays). from_end: a hint that the rays may be traced
        from their far ends (coherent shadow rays from a light); order: as for `intersect`;
        implementations may ignore both."""

    @abc.abstractmethod
    def surface(self, prim: Int[Array, " B"], u: Float[Array, " B"], v: Float[Array, " B"]) -> Surface:
        """World-space surface at barycentrics (u, v) of faces `prim` (differentiable in the vertex
        data); a miss (-1) reads face 0: mask misses yourself."""

    def intersect_surface(self, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
                          tmin: Float[Array, " N"] | float = 0.0,
                          tmax: Float[Array, " N"] | float = float("inf")) -> tuple[Hit, Surface]:
        """`intersect` and the `surface` of its hits, for passes that are not differentiated (the
        surface may come from the traversal's own hit points and geometric normals, which are not
        differentiable: `TriangleGeometry`). Misses: mask them yourself."""
        hit = self.intersect(origins, directions, tmin, tmax)
        return hit, self.surface(hit.prim, hit.u, hit.v)

    def shadows_in_traversal(self) -> bool:
        """Whether `intersect_surface_shadowed` is implemented here (static): a traversal that traces
        the hits' shadow rays to point lights in the same call (`TriangleGeometry` on the CPU with
        Embree). Others: False, and the integrator traces shadow rays with `occluded`."""
        return False

    def intersect_surface_shadowed(self, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
                                   tmin: Float[Array, " N"] | float, tmax: Float[Array, " N"] | float,
                                   lights: Float[Array, "L 3"]) -> tuple[Hit, Surface, Bool[Array, "N L"]]:
        """`intersect_surface` and whether each hit's shadow segment to each point light is blocked
        (the segments of `jaxrt.integrators.whitted.shadow_segments`), where `shadows_in_traversal()`."""
        raise NotImplementedError(f"{type(self).__name__} traces shadow rays with `occluded`")

    @abc.abstractmethod
    def triangles(self, prim: Int[Array, " B"]) -> tuple[Float[Array, "B 3"], Float[Array, "B 3"], Float[Array, "B 3"]]:
        """World-space corners (v0, v1, v2) of faces `prim` (e.g. for sampling points on emitters)."""

    @abc.abstractmethod
    def face_material(self, prim: Int[Array, "..."]) -> Int[Array, "..."]:
        """Material id of faces `prim` (any shape; -1 reads face 0)."""

    @abc.abstractmethod
    def face_object(self, prim: Int[Array, "..."]) -> Int[Array, "..."]:
        """Scene-object id of faces `prim` (any shape; -1 reads face 0)."""

    @abc.abstractmethod
    def with_object_material(self, obj: int, material: int) -> "AbstractGeometry":
        """A copy in which scene object `obj` wears material id `material` (a value change: never
        recompiles)."""

    @abc.abstractmethod
    def object_triangles(self, obj: int) -> Float[np.ndarray, "n 3 3"]:
        """World-space triangles of scene object `obj`, float64, host side."""

    @property
    @abc.abstractmethod
    def triangle_count(self) -> int:
        """Triangles in the scene, counting every instance's copy (host side)."""

    @property
    @abc.abstractmethod
    def face_count(self) -> int:
        """Number of distinct face ids `prim` can take (static)."""

    def object_index(self, name: str) -> int:
        """The id of the scene object called `name`; InputError listing the names otherwise."""
        from jaxrt.errors import InputError

        if name not in self.object_names:
            raise InputError(f"no object named {name!r}; objects: {', '.join(self.object_names)}")
        return self.object_names.index(name)
