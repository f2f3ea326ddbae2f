"""Acceleration structures: BVH builders and the traversal back ends.

    tree = accel.build(vertices, faces)                 # `BVH` pytree (host build, numpy)
    hit = accel.intersect(tree, origins, directions)    # closest hit: t, prim, u, v
    hit, p, ng = accel.intersect_points(tree, origins, directions)   # and hit points, geometric normals
    blocked = accel.occluded(tree, origins, directions, tmax)
    hit = accel.intersect_few(triangles, origins, directions)    # a few (L, 9) triangles, no tree

Modules: `builder` (the LBVH topology, threading and layouts shared by every builder), `sah`
(binned SAH topology), `morton` (Morton codes), `predicates` (the exact ray/triangle and slab
predicates shared by every traversal), `traverse_xla` (the portable stackless loop),
`traverse_pallas` (one Pallas kernel for NVIDIA GPUs), `traverse_cpu` (a C++ XLA FFI kernel),
`traverse_embree` (Embree 3's packet traversal in a C++ XLA FFI kernel, the CPU default where installed),
`two_level` (instanced geometry: a top-level tree over instances of bottom-level trees) and `bvh`
(the `BVH` pytree and the dispatch between back ends).
"""

from jaxrt.accel.bvh import (BVH, IMPLS, RENDER_TREE, BVHStats, Hit, build, intersect, intersect_few, intersect_points,
                             intersect_points_shadowed, node_visits, occluded, stats, uses_embree, with_table_key)
from jaxrt.accel.two_level import InstancedBVH

__all__ = [
    "BVH", "BVHStats", "Hit", "IMPLS", "InstancedBVH", "RENDER_TREE",
    "build", "intersect", "intersect_few", "intersect_points", "intersect_points_shadowed", "node_visits", "occluded", "stats", "uses_embree", "with_table_key",
]
