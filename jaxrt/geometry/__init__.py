"""Scene geometry: one abstract interface, triangle and instanced geometry, meshes and primitives.

`AbstractGeometry` is what integrators, fitting and sweeps program against; `TriangleGeometry`
(all triangles in one BVH) and `InstancedGeometry` (prototypes placed by instances over a
two-level BVH) implement it. `mesh` loads and validates triangle meshes (trimesh), `shapes`
builds the procedural primitives, `data` finds the test meshes through `JAXRT_DATA`.
"""

from jaxrt.geometry.base import AbstractGeometry
from jaxrt.geometry.instanced import InstancedGeometry
from jaxrt.geometry.mesh import Mesh
from jaxrt.geometry.triangles import TriangleGeometry

__all__ = ["AbstractGeometry", "InstancedGeometry", "Mesh", "TriangleGeometry"]
