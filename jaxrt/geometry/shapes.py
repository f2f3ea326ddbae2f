"""Procedural primitives (sphere, plane, box) as triangle meshes.

Each primitive is built in its own object space and returned as a `jaxrt.geometry.mesh.Mesh`; the scene
loader places it with `Mesh.transformed`. Triangulation comes from trimesh; only the normals are
set here, because the analytic ones are exact (a sphere's normal is its unit position) and a box
must keep flat faces rather than averaged corner normals.
"""

from __future__ import annotations

import numpy as np

from jaxrt.geometry import mesh as _mesh


def sphere(radius: float = 1.0, subdivisions: int = 4, name: str = "sphere") -> "_mesh.Mesh":
    """Icosphere of `radius` centred at the origin; `subdivisions` levels (20·4^k triangles).

    Vertex normals are the exact sphere normals, so smooth shading shows no faceting in the
    highlight (silhouettes stay polygonal).
    """
    import trimesh  # loaded where first used: it is slow to import

    # The unit sphere's vertices give the normals, then scale: normals stay exact for any radius the
    # scene file allows (normalising vertices of a tiny sphere in floating point gives NaN).
    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    n = np.asarray(tm.vertices, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    # Latitude-longitude uv: u = 0.5 + atan2(x, z) / 2 pi around +y (u = 0.5 faces +z), v = 1 at the
    # north pole (+y), so an equirectangular image maps upright (textures use v = 1 for the top row).
    uv = np.stack([0.5 + np.arctan2(n[:, 0], n[:, 2]) / (2 * np.pi), 1.0 - np.arccos(np.clip(n[:, 1], -1, 1)) / np.pi], 1)
    faces = np.asarray(tm.faces, np.int64).copy()
    # Faces straddling the seam (u jumps from ~1 to ~0) get copies of their small-u vertices at
    # u + 1, so uv interpolates across the face instead of sweeping through the whole texture.
    fu = uv[faces, 0]
    low = ((fu.max(1) - fu.min(1)) > 0.5)[:, None] & (fu < 0.5)
    dup = np.unique(faces[low])
    remap = np.full(len(n), -1, np.int64)
    remap[dup] = len(n) + np.arange(len(dup))
    faces[low] = remap[faces[low]]
    n = np.concatenate([n, n[dup]])
    v = n * float(radius)
    uv = np.concatenate([uv, uv[dup] + np.array([1.0, 0.0])])
    return _mesh.Mesh.from_arrays(
        v.astype(np.float32), faces.astype(np.int32), normals=n.astype(np.float32),
        uvs=uv.astype(np.float32), name=name,
    )


def plane(size: tuple[float, float] = (1.0, 1.0), name: str = "plane") -> "_mesh.Mesh":
    """Rectangle in the xz-plane (y = 0), normal +y, extents size[0] along x and size[1] along z."""
    sx, sz = 0.5 * float(size[0]), 0.5 * float(size[1])
    v = np.array([[-sx, 0, -sz], [sx, 0, -sz], [sx, 0, sz], [-sx, 0, sz]], np.float32)
    f = np.array([[0, 2, 1], [0, 3, 2]], np.int32)  # counter-clockwise seen from +y
    n = np.tile(np.array([[0, 1, 0]], np.float32), (4, 1))
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    return _mesh.Mesh.from_arrays(v, f, normals=n, uvs=uv, name=name)


def box(size: tuple[float, float, float] = (1.0, 1.0, 1.0), name: str = "box") -> "_mesh.Mesh":
    """Axis-aligned box centred at the origin with edge lengths `size`, flat-shaded (36 unshared vertices);
    each face's uv spans [0, 1]^2 over its two in-plane axes."""
    import trimesh

    tm = trimesh.creation.box(extents=np.asarray(size, np.float64))
    # unshare corners: each triangle gets its own vertices so every face keeps its own normal
    faces = np.asarray(tm.faces, np.int64)
    v = np.asarray(tm.vertices, np.float64)[faces.reshape(-1)]
    n = np.repeat(np.asarray(tm.face_normals, np.float64), 3, axis=0)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    # each face maps to [0, 1]^2 by its two in-plane coordinates (in x, y, z order)
    size = np.asarray(size, np.float64)
    axis = np.argmax(np.abs(n), axis=1)
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    rows = np.arange(len(v))[:, None]
    uv = v[rows, other] / size[other] + 0.5
    return _mesh.Mesh.from_arrays(v.astype(np.float32), f, normals=n.astype(np.float32),
                                  uvs=uv.astype(np.float32), name=name)


PRIMITIVES = {"sphere": sphere, "plane": plane, "box": box}
