"""Triangle meshes: loading (through trimesh), validation, transforms and concatenation.

A `Mesh` is a frozen dataclass of numpy arrays (host data; the BVH and the renderer turn it into
jnp arrays):

  vertices  (V, 3) float32   positions, in the file's units
  faces     (F, 3) int32     vertex indices, counter-clockwise seen from the front, in the file's
                             face order (zero-area faces removed, the rest keep their order)
  normals   (V, 3) float32   unit shading normals: from the file where it has them, else
                             area-weighted averages of the face normals
  uvs       (V, 2) float32   texture coordinates, or None when the file has none
  tangents  (V, 3) float32   unit, orthogonal to `normals`; dP/du of the UV parameterisation where
                             UVs exist (so continuous across faces), else the projection of a fixed
                             reference axis (+x, or +y where the normal is within ~8 deg of x)
  object_id (F,)   int32     which object each face belongs to, 0..len(names)-1
  names     tuple[str, ...]  one name per object

A file with several objects (OBJ `o`/`g` groups, glTF/GLB nodes) loads as several objects in one
Mesh: `names` in the file's order, `object_id` per face, faces in the file's order. glTF node
transforms are applied. With `flat=True` every face gets its own three vertices and the face's
geometric normal (flat shading).

Bad input raises `jaxrt.errors.InputError` naming the file: unsupported extension, unreadable
file, empty mesh, NaN/Inf vertices, out-of-range indices. Zero-area triangles are dropped with one
`warnings.warn` line that counts them.
"""

from __future__ import annotations

import dataclasses
import gzip
import io
import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxrt.errors import InputError

#: File extensions `load` accepts (each also with a trailing `.gz`).
SUPPORTED_EXTENSIONS = ("obj", "ply", "stl", "glb", "gltf", "off")


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A validated triangle mesh (see the module docstring for every field's shape and meaning)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray | None
    tangents: np.ndarray
    object_id: np.ndarray
    names: tuple[str, ...]

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @classmethod
    def from_arrays(
        cls,
        vertices,
        faces,
        normals=None,
        uvs=None,
        name: str = "mesh",
        *,
        flat: bool = False,
    ) -> "Mesh":
        """Build a Mesh from arrays (procedural shapes); validated exactly like `load`.

        vertices (V,3), faces (F,3) integer, normals (V,3) or None (area-weighted), uvs (V,2) or
        None. One object called `name`. Errors name `name` as the source.
        """
        return _make_mesh(vertices, faces, normals, uvs, np.zeros(len(np.asarray(faces)), np.int32),
                          (name,), source=name, flat=flat)

    def transformed(self, scale=1.0, rotation=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> "Mesh":
        """Return a copy with p' = R @ (scale * p) + translation.

        scale: a positive number or 3 positive numbers (per axis). rotation: XYZ Euler angles in
        degrees (rotate about x, then y, then z, fixed axes) or a 3x3 rotation matrix. Normals
        transform with the inverse transpose, tangents with the linear map (then re-orthogonalised);
        both stay unit length. A negative-determinant map is refused (it would flip the winding).
        """
        src = f"transform of {self.names[0] if len(self.names) == 1 else 'mesh'}"
        s = np.broadcast_to(np.asarray(scale, np.float64), (3,)) if np.ndim(scale) <= 1 else None
        if s is None or s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise InputError(f"{src}: scale must be a positive number or 3 positive numbers, got {scale!r}")
        rot = np.asarray(rotation, np.float64)
        if rot.shape == (3,):
            if not np.all(np.isfinite(rot)):
                raise InputError(f"{src}: rotation angles must be finite degrees, got {rotation!r}")
            import trimesh.transformations as tf

            r = tf.euler_matrix(*np.radians(rot), axes="sxyz")[:3, :3]
        elif rot.shape == (3, 3):
            r = rot
            if not (np.all(np.isfinite(r)) and np.allclose(r @ r.T, np.eye(3), atol=1e-5)
                    and np.linalg.det(r) > 0):
                raise InputError(f"{src}: rotation matrix must be a proper rotation (orthonormal, det +1)")
        else:
            raise InputError(f"{src}: rotation must be 3 Euler angles in degrees or a 3x3 matrix, got shape {rot.shape}")
        t = np.asarray(translation, np.float64)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"{src}: translation must be 3 finite numbers, got {translation!r}")
        lin = r * s[None, :]  # R @ diag(s)
        v = self.vertices.astype(np.float64) @ lin.T + t
        n = _unit(self.normals.astype(np.float64) @ np.linalg.inv(lin))  # (lin^-T n) as row vectors
        tg = self.tangents.astype(np.float64) @ lin.T
        tg = _orthonormal_tangent(n, tg)
        return dataclasses.replace(self, vertices=v.astype(np.float32), normals=n.astype(np.float32),
                                   tangents=tg.astype(np.float32))


def concatenate(meshes: Sequence[Mesh]) -> Mesh:
    """One triangle set from several meshes, in the given order.

    Object ids are renumbered 0..k-1 across all objects of all meshes, and `names` concatenated.
    UVs are kept only if every mesh has them (else None); tangents are kept per vertex either way.
    """
    meshes = list(meshes)
    if not meshes:
        raise InputError("mesh.concatenate: needs at least one mesh")
    v_off = np.cumsum([0] + [m.num_vertices for m in meshes])[:-1]
    o_off = np.cumsum([0] + [len(m.names) for m in meshes])[:-1]
    uvs = (np.concatenate([m.uvs for m in meshes]) if all(m.uvs is not None for m in meshes) else None)
    return Mesh(
        vertices=np.concatenate([m.vertices for m in meshes]),
        faces=np.concatenate([m.faces + np.int32(o) for m, o in zip(meshes, v_off)]).astype(np.int32),
        normals=np.concatenate([m.normals for m in meshes]),
        uvs=uvs,
        tangents=np.concatenate([m.tangents for m in meshes]),
        object_id=np.concatenate([m.object_id + np.int32(o) for m, o in zip(meshes, o_off)]).astype(np.int32),
        names=tuple(n for m in meshes for n in m.names),
    )


def load(path: str | os.PathLike, *, flat: bool = False, name: str | None = None) -> Mesh:
    """Load a triangle mesh file: OBJ, PLY (ASCII/binary), STL, GLB/glTF, OFF, or any of them gzipped.

    `name` overrides the object name of a single-object file (default: the file stem); files with
    several objects keep the names from the file. Returns a validated `Mesh`.
    """
    import trimesh

    path = Path(path)
    suffixes = [s.lower().lstrip(".") for s in path.suffixes]
    gz = bool(suffixes) and suffixes[-1] == "gz"
    ext = (suffixes[-2] if gz and len(suffixes) >= 2 else (suffixes[-1] if suffixes and not gz else ""))
    if ext not in SUPPORTED_EXTENSIONS:
        raise InputError(
            f"{path}: unsupported mesh format {''.join(path.suffixes) or '(no extension)'!r}; "
            f"allowed: {', '.join('.' + e for e in SUPPORTED_EXTENSIONS)} (optionally followed by .gz)")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not a mesh file")
    if not path.is_file():
        raise InputError(f"{path}: mesh file not found")
    try:
        raw = gzip.open(path).read() if gz else path.read_bytes()
    except (OSError, EOFError) as e:
        raise InputError(f"{path}: cannot read mesh file ({e})") from None
    stem = path.name[: -len(".gz")] if gz else path.name
    stem = stem[: -(len(ext) + 1)]
    kwargs = dict(process=False)
    if ext == "obj":
        kwargs.update(split_objects=True, split_groups=True, group_material=False, maintain_order=True)
        # trimesh reads index 0 (no OBJ index) as -1 without a word; report it as the file numbers it
        if _OBJ_ZERO_INDEX.search(raw) and (why := _obj_index_error(raw)):
            raise InputError(f"{path}: {why}")
    try:
        if ext == "gltf" and not gz:  # side files (buffers) resolve relative to the path
            loaded = trimesh.load(str(path), file_type=ext, **kwargs)
        elif ext == "ply" and (arrays := _ascii_ply_triangles(raw)) is not None:
            loaded = trimesh.Trimesh(vertices=arrays[0], faces=arrays[1], **kwargs)
        else:
            loaded = trimesh.load(io.BytesIO(raw), file_type=ext, **kwargs)
    except Exception as e:  # trimesh raises many kinds for malformed files
        # an out-of-range face index surfaces as numpy's 0-based IndexError: say it in the file's terms
        why = _obj_index_error(raw) if ext == "obj" else None
        raise InputError(f"{path}: {why}" if why else
                         f"{path}: cannot parse as {ext.upper()} ({type(e).__name__}: {e})") from None

    parts = _parts(loaded, raw if ext == "obj" else None)
    parts = [(n, g) for n, g in parts if len(getattr(g, "faces", ())) > 0]
    if not parts:
        raise InputError(f"{path}: the file contains no triangles")
    if len(parts) == 1:
        parts = [(name or stem, parts[0][1])]
    verts, faces, norms, uvs, oid = [], [], [], [], []
    off = 0
    has_normals = all("vertex_normals" in g._cache.cache for _, g in parts)
    has_uvs = all(_uv_of(g) is not None for _, g in parts)
    for i, (_, g) in enumerate(parts):
        v = np.asarray(g.vertices, np.float64)
        f = np.asarray(g.faces, np.int64)
        verts.append(v)
        faces.append(f + off)
        if has_normals:
            norms.append(np.asarray(g.vertex_normals, np.float64))
        if has_uvs:
            uvs.append(_uv_of(g))
        oid.append(np.full(len(f), i, np.int32))
        off += len(v)
    return _make_mesh(
        np.concatenate(verts), np.concatenate(faces), np.concatenate(norms) if has_normals else None,
        np.concatenate(uvs) if has_uvs else None, np.concatenate(oid), tuple(n for n, _ in parts),
        source=str(path), flat=flat)


# ---------------------------------------------------------------------------------------------
# internals


# a face entry whose vertex index is 0 (or -0): "f 1 2 0", "f 0/1/1 ..."
_OBJ_ZERO_INDEX = re.compile(rb"(?m)^[ \t]*f[ \t][^\n]*?(?<=[ \t])-?0+(?=[/ \t\r\n]|$)")


def _obj_index_error(raw: bytes) -> str | None:
    """The first face vertex index of an OBJ file that names no vertex, as "line N: ..." in the
    file's own terms (1-based; negative indices count back from the last vertex read), or None."""
    lines = raw.splitlines()
    total = sum(1 for l in lines if l.split()[:1] == [b"v"])
    seen = 0
    for lineno, line in enumerate(lines, 1):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == b"v":
            seen += 1
        elif tok[0] == b"f":
            for t in tok[1:]:
                try:
                    i = int(t.split(b"/")[0])
                except ValueError:
                    return f"line {lineno}: face entry {t.decode(errors='replace')!r} does not start with a vertex index"
                if not (1 <= i <= total or -seen <= i <= -1):
                    return (f"line {lineno}: face index {i} names no vertex; the file has {total} vertices, "
                            f"and OBJ indices are 1-based (1..{total}) or negative (-1 = the last vertex read)")
    return None


_PLY_FLOATS = {"float": np.float32, "float32": np.float32, "double": np.float64, "float64": np.float64}


def _ascii_ply_triangles(raw: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices, faces) of the commonest ASCII PLY layout, or None for any other file (trimesh reads it).

    The layout: `element vertex N` with exactly the float properties x, y, z, then `element face M` with
    one `list <count type> <index type> vertex_indices` (or vertex_index) property, no other element,
    every face a triangle. Why: trimesh's ASCII reader parses each line with its own `numpy.fromstring`
    call and stacks the rows, ~3 CPU s for the Stanford dragon (1.3M lines); one `numpy.fromstring` of
    the whole body reads the same numbers (the same C conversion) in a fraction of that. The values
    are those trimesh gives: vertices rounded to the declared float type, faces as integers; anything
    unexpected (other properties, polygons, a count that does not match) returns None."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0 or end > 4096:
        return None
    nl = raw.find(b"\n", end)
    if nl < 0:
        return None
    lines = [l.split() for l in raw[:end].decode("ascii", errors="replace").splitlines()]
    lines = [l for l in lines if l and l[0] not in ("ply", "comment", "obj_info")]
    try:
        fmt, elements, props = None, [], []
        for l in lines:
            if l[0] == "format":
                fmt = l[1]
            elif l[0] == "element":
                elements.append((l[1], int(l[2])))
                props.append([])
            elif l[0] == "property" and props:
                props[-1].append(l[1:])
            else:
                return None
    except (IndexError, ValueError):
        return None
    if fmt != "ascii" or [e for e, _ in elements] != ["vertex", "face"]:
        return None
    (_, nv), (_, nf) = elements
    vprops, fprops = props
    if [p[-1] for p in vprops] != ["x", "y", "z"] or any(len(p) != 2 or p[0] not in _PLY_FLOATS for p in vprops):
        return None
    if len({p[0] for p in vprops}) != 1 or len(fprops) != 1:
        return None
    fp = fprops[0]
    if len(fp) != 4 or fp[0] != "list" or fp[3] not in ("vertex_indices", "vertex_index"):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # fromstring's text mode is what is wanted here
        values = np.fromstring(raw[nl + 1:], sep=" ")
    if values.size != 3 * nv + 4 * nf:
        return None
    vertices = values[: 3 * nv].reshape(nv, 3).astype(_PLY_FLOATS[vprops[0][0]])
    rows = values[3 * nv:].reshape(nf, 4)
    if nf == 0 or not np.all(rows[:, 0] == 3):
        return None
    faces = rows[:, 1:]
    if not np.all((faces == np.floor(faces)) & (faces >= 0) & (faces < max(nv, 1))):
        return None
    return vertices, faces.astype(np.int64)


def _uv_of(g) -> np.ndarray | None:
    uv = getattr(getattr(g, "visual", None), "uv", None)
    if uv is None or len(uv) != len(g.vertices):
        return None
    return np.asarray(uv, np.float64)


def _parts(loaded, obj_text: bytes | None) -> list[tuple[str, object]]:
    """(name, Trimesh) per object, in the file's order, with scene-graph transforms applied."""
    import trimesh

    if isinstance(loaded, trimesh.Trimesh):
        return [("", loaded)]
    if not isinstance(loaded, trimesh.Scene):
        return []
    parts = []
    for node in loaded.graph.nodes_geometry:
        transform, geom_name = loaded.graph[node]
        g = loaded.geometry[geom_name]
        if not isinstance(g, trimesh.Trimesh):
            continue
        if not np.allclose(transform, np.eye(4)):
            g = g.copy()
            g.apply_transform(transform)
        parts.append((str(node), g))
    if obj_text is not None:
        # trimesh's OBJ loader returns objects in reverse order; restore the file's order
        # from the first appearance of each `o`/`g` name.
        order = {}
        for m in re.finditer(rb"^[ \t]*[og][ \t]+(.+?)[ \t]*\r?$", obj_text, re.MULTILINE):
            order.setdefault(m.group(1).decode("utf-8", "replace"), len(order))
        rank = {n: order.get(n, len(order) + len(parts) - i) for i, (n, _) in enumerate(parts)}
        parts.sort(key=lambda p: rank[p[0]])
    return parts


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def _reference_tangent(n: np.ndarray) -> np.ndarray:
    ref = np.where(np.abs(n[:, :1]) < 0.99, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    return ref


def _orthonormal_tangent(n: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Gram-Schmidt t against unit n; falls back to the reference axis where t is (near) parallel to n."""
    t_in = np.linalg.norm(t, axis=-1)
    t = t - n * np.sum(t * n, axis=-1, keepdims=True)
    bad = ~(np.linalg.norm(t, axis=-1) > 1e-6 * t_in)
    if np.any(bad):
        r = _reference_tangent(n[bad])
        t[bad] = r - n[bad] * np.sum(r * n[bad], axis=-1, keepdims=True)
    return _unit(t)


def _make_mesh(vertices, faces, normals, uvs, object_id, names, *, source: str, flat: bool) -> Mesh:
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{source}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not (f.size == 0 or np.issubdtype(f.dtype, np.integer)):
        raise InputError(f"{source}: faces must be an integer array of shape (F, 3), got {f.shape} {f.dtype}")
    if len(v) == 0 or len(f) == 0:
        raise InputError(f"{source}: empty mesh ({len(v)} vertices, {len(f)} faces); at least one triangle is needed")
    if not np.all(np.isfinite(v)):
        bad = int(np.sum(~np.all(np.isfinite(v), axis=1)))
        raise InputError(f"{source}: {bad} vertices have NaN or Inf coordinates; all must be finite")
    if np.any(np.abs(v) > 1e30):
        raise InputError(f"{source}: vertex coordinates must be below 1e30 in magnitude")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"{source}: face indices must be in [0, {len(v) - 1}], found {f.min()}..{f.max()}")
    if normals is not None:
        normals = np.asarray(normals, np.float64)
        if normals.shape != v.shape or not np.all(np.isfinite(normals)):
            raise InputError(f"{source}: normals must be finite with shape {v.shape}, got {normals.shape}")
    if uvs is not None:
        uvs = np.asarray(uvs, np.float64)
        if uvs.shape != (len(v), 2) or not np.all(np.isfinite(uvs)):
            raise InputError(f"{source}: uvs must be finite with shape ({len(v)}, 2), got {uvs.shape}")
    object_id = np.asarray(object_id, np.int32)

    # Zero-area test in float32, the precision the tracer works in: such a face can never be hit.
    v32 = v.astype(np.float32)
    cross32 = np.cross(v32[f[:, 1]] - v32[f[:, 0]], v32[f[:, 2]] - v32[f[:, 0]])
    keep = np.any(cross32 != 0, axis=1)
    if not np.all(keep):
        nbad = int(np.sum(~keep))
        warnings.warn(f"{source}: removed {nbad} zero-area triangle(s) of {len(f)}", stacklevel=3)
        f, object_id = f[keep], object_id[keep]
        if len(f) == 0:
            raise InputError(f"{source}: every triangle has zero area; nothing to render")

    fc = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |fc| = 2 * area
    if flat:
        v = v[f].reshape(-1, 3)
        normals = np.repeat(_unit(fc), 3, axis=0)
        uvs = uvs[f].reshape(-1, 2) if uvs is not None else None
        f = np.arange(len(v)).reshape(-1, 3)
    elif normals is None:
        acc = np.zeros_like(v)
        for k in range(3):
            np.add.at(acc, f[:, k], fc)
        normals = acc
    # Vertices no face uses, or whose faces cancel, fall back to +z (they are never shaded).
    nl = np.linalg.norm(normals, axis=1)
    normals = np.where((nl > 0)[:, None], normals / np.where(nl > 0, nl, 1.0)[:, None], [0.0, 0.0, 1.0])

    if uvs is not None:
        # Per-face dP/du from the UV Jacobian, accumulated area-weighted: continuous where UVs are.
        p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        t0, t1, t2 = uvs[f[:, 0]], uvs[f[:, 1]], uvs[f[:, 2]]
        e1, e2 = p1 - p0, p2 - p0
        d1, d2 = t1 - t0, t2 - t0
        det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
        ok = np.abs(det) > 1e-20
        dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / np.where(ok, det, 1.0)[:, None]
        # weight by area so large faces dominate; normalise per face first so scale of UVs does not matter
        w = np.linalg.norm(fc, axis=1, keepdims=True) * ok[:, None]
        dpdu = _unit(dpdu) * w
        acc = np.zeros_like(v)
        for k in range(3):
            np.add.at(acc, f[:, k], dpdu)
        tangents = _orthonormal_tangent(normals, acc)
    else:
        tangents = _orthonormal_tangent(normals, _reference_tangent(normals).copy())

    return Mesh(
        vertices=v.astype(np.float32),
        faces=f.astype(np.int32),
        normals=normals.astype(np.float32),
        uvs=None if uvs is None else uvs.astype(np.float32),
        tangents=tangents.astype(np.float32),
        object_id=object_id.astype(np.int32),
        names=tuple(str(n) for n in names),
    )
