"""On-disk caches: compiled XLA programs, loaded meshes and built BVHs, reused across processes.

Everything lives in one per-user folder, `cache_dir()`:

    $JAXRT_CACHE_DIR             when set, else $XDG_CACHE_HOME/jaxrt, else ~/.cache/jaxrt
      xla/                       JAX's persistent compilation cache (`enable_compilation_cache`)
      arrays/<kind>-<hash>.arrays  content-addressed arrays: meshes (`load_mesh`), BVHs (`build_bvh`),
                                 anything else through `cached_arrays`

``JAXRT_CACHE=off`` turns both off: nothing is read or written and the folder is not created.
``JAXRT_CACHE_SIZE`` (default 2G) bounds the two subfolders together; when an array entry is stored,
and when a process enables the compilation cache, the least recently used entries are deleted until
the total fits (array entries count as used when read; compiled programs when written, since JAX's
cache does not record reads). `info()` reports the folder, entry counts, bytes and the bound;
`clear()` empties both subfolders (``jaxrt cache info`` / ``jaxrt cache clear`` from a shell). Other
files in the folder (the data registry's meshes, the native traversal kernel's library) are left
alone. Sizes for orientation: the full dragon's mesh entry is ~30 MB and its render BVH ~175 MB
(~330 MB where the GPU kernel's node tables are stored too); a CPU frame program is ~0.1-2 MB.

Array entries. `cached_arrays(kind, key, build)` hashes (FORMAT_VERSION, kind, key) into a file
name; on a miss it calls `build()` and stores the arrays as one file of consecutive NumPy ``.npy``
records (`numpy.lib.format`, never pickle: a record of the entry's metadata, then one per array)
through a temporary file in the same folder and `os.replace`, so readers only ever see whole
files and concurrent writers of one key are safe (the last rename wins; both wrote the same
content). Each entry records its key and a sha256 of its arrays (names, dtypes, shapes and bytes),
checked on every read: a truncated, corrupt or stale entry gives one `CacheWarning`, is rebuilt and
overwritten. A folder that cannot be written (read-only, full, no permission) gives one
`CacheWarning` per process and folder, then results are still returned, just not stored (entries
already there are still read). Bad cache contents never fail a load: the worst case is a rebuild.
Plain records rather than a zip (``.npz``): numpy reads a record of a real file with one `fromfile`,
while a zip member is read in 256 KiB pieces with a CRC each, which made reading the dragon's BVH
entry (175 MB) ~0.5 s of a warm render's ~3 s on an H200's host; the sha256 (~1.2 GB/s with SHA
instructions) is then the only pass over the bytes besides the read.

`load_mesh` and `build_bvh` are `jaxrt.geometry.mesh.load` and `jaxrt.accel.build` through that cache, with
results bit-identical to the uncached calls (every array equal, same dtypes). Their keys hold
everything the result depends on: the file's sha256 and name, `flat` and `name` for meshes; the
vertex and face bytes, builder, layout, leaf size and the SAH builder's module settings for BVHs;
and for both, a hash of the source files that compute the result and the versions of the libraries
that do (numpy, trimesh; JAX where the GPU node tables are stored), so an upgrade or a code change
never reads an old entry.

Compiled programs. `enable_compilation_cache()` points JAX's persistent compilation cache at
``xla/`` and caches every compilation (no minimum compile time or size: most of a render's
compilations take well under JAX's default one-second threshold on a CPU). JAX keys an entry on the
lowered program, so tracing still runs in every process; only XLA compilation is skipped. A traced
program that calls the native CPU kernel registers its FFI target while tracing (`jaxrt.accel.traverse_cpu.
available()` runs inside `jaxrt.accel.bvh`'s traversal), which is before JAX looks the program up in the
cache, so a cached program that calls the kernel always finds it registered. JAX writes entries
in place (not through a rename): a process that reads an entry while another writes it warns
(``Error reading persistent compilation cache entry``) and compiles for itself; it never fails.
JAX does not replace an entry that is there, so one left truncated by a killed writer or a full
disk makes each later process warn and compile that program until `clear()` or the size bound
removes it.

Process-local counters (`stats()`: hits, misses, writes, rebuilds, evictions, bypasses) let tests
and benchmarks see what the cache did without timing it.
"""

from __future__ import annotations

import builtins
import contextlib
import dataclasses
import hashlib
import json
import os
import re
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxrt import _config

if TYPE_CHECKING:
    from jaxrt.accel import BVH
    from jaxrt.accel.sah import SahSettings
    from jaxrt.geometry.mesh import Mesh

__all__ = [
    "FORMAT_VERSION",
    "CacheInfo",
    "CacheStats",
    "CacheWarning",
    "build_bvh",
    "cached_meshes",
    "cache_dir",
    "cached_arrays",
    "clear",
    "enable_compilation_cache",
    "enabled",
    "entry_path",
    "info",
    "load_mesh",
    "sharing_trees",
    "stats",
]

#: Version of the array entries' format; part of every key, so a new format never reads an old entry.
FORMAT_VERSION = 2
#: File name ending of array entries (entries of format 1 were .npz files; they are still counted,
#: trimmed and cleared, never read).
_SUFFIX = ".arrays"
_OLD_SUFFIXES = (".npz",)

_KIND = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
_TMP_PREFIX = ".tmp-"
_TMP_MAX_AGE_S = 3600.0  # temporary files older than this are left over from a killed writer


class CacheWarning(RuntimeWarning):
    """A cache entry could not be used or stored; the result is computed instead (nothing fails)."""


@dataclasses.dataclass(frozen=True)
class CacheInfo:
    """What `info()` found: the folder, whether caching is on, entries and bytes per part, the bound."""

    dir: Path
    enabled: bool
    array_entries: int
    array_bytes: int
    compiled_entries: int
    compiled_bytes: int
    bound: int

    @property
    def entries(self) -> int:
        return self.array_entries + self.compiled_entries

    @property
    def bytes(self) -> int:
        return self.array_bytes + self.compiled_bytes


@dataclasses.dataclass(frozen=True)
class CacheStats:
    """This process's array-cache counters (see `stats`).

    hits: entries read and verified; misses: builds because no entry existed; writes: entries
    stored; rebuilds: entries found corrupt, truncated or stale and rebuilt; evictions: entries
    deleted by the size bound; bypasses: calls with caching off (JAXRT_CACHE=off).
    """

    hits: int = 0
    misses: int = 0
    writes: int = 0
    rebuilds: int = 0
    evictions: int = 0
    bypasses: int = 0


# Process-local bookkeeping (counters; warnings already given; folders found unwritable; the folder
# this module pointed JAX at). Nothing here changes what a call returns, only what it reports.
_lock = threading.Lock()
_counts: dict[str, int] = {}
_warned: set[tuple[str, str]] = set()
_unwritable: set[str] = set()
_jax_dir: list[str] = []


def cache_dir() -> Path:
    """The cache folder (JAXRT_CACHE_DIR, else $XDG_CACHE_HOME/jaxrt, else ~/.cache/jaxrt); not created here."""
    return _config.config().cache_dir


def enabled() -> bool:
    """Whether the caches are on (JAXRT_CACHE is not "off")."""
    return _config.config().cache


def stats() -> CacheStats:
    """This process's array-cache counters since it started."""
    with _lock:
        return CacheStats(**_counts)


def _count(name: str, n: int = 1) -> None:
    with _lock:
        _counts[name] = _counts.get(name, 0) + n


def _warn_once(tag: str, where: str, message: str) -> None:
    with _lock:
        if (tag, where) in _warned:
            return
        _warned.add((tag, where))
    warnings.warn(message, CacheWarning, stacklevel=4)


# ---------------------------------------------------------------------------------------------
# the compilation cache


def enable_compilation_cache() -> bool:
    """Point JAX's persistent compilation cache at ``cache_dir()/xla``; True where it is on after the call.

    Call it before the first compilation worth keeping (the CLI, a notebook or a script's start);
    calling it again is cheap and changes nothing unless JAXRT_CACHE_DIR changed. Sets
    ``jax_compilation_cache_dir``, ``jax_persistent_cache_min_compile_time_secs = 0`` and
    ``jax_persistent_cache_min_entry_size_bytes = -1`` (every compilation is cached; the last two
    only where their JAX_* environment variables do not set them). Returns False, changing nothing,
    when JAXRT_CACHE=off, and when the folder cannot be created or written (with one `CacheWarning`).
    A cache folder configured for JAX by other means (``JAX_COMPILATION_CACHE_DIR``, or
    ``jax.config.update`` before this call) is left as it is, and True is returned.
    """
    cfg = _config.config()
    if not cfg.cache:
        return False
    import jax

    xla = cfg.cache_dir / "xla"
    current = jax.config.jax_compilation_cache_dir
    if current and current not in _jax_dir:
        return True  # configured by the user: theirs wins
    if current == str(xla):
        return True
    try:
        _probe(xla)
    except OSError as e:
        # one warning per cache folder, whichever cache meets the problem first
        _warn_once("unwritable", str(cfg.cache_dir), f"jaxrt cache: cannot store entries in {xla} ({_reason(e)}); "
                                                     f"continuing without caching compiled programs")
        return False
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES" not in os.environ:
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    jax.config.update("jax_compilation_cache_dir", str(xla))
    if current:  # our earlier folder (JAXRT_CACHE_DIR changed): JAX opens its cache once, so reopen it
        from jax.experimental.compilation_cache import compilation_cache as cc

        cc.reset_cache()
    with _lock:
        _jax_dir[:] = [str(xla)]
    _trim(cfg.cache_dir, cfg.cache_size)
    return True


def _probe(folder: Path) -> None:
    """Create `folder` and check that a file can be written in it (raises OSError where not)."""
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, suffix=".probe", dir=folder)
    os.close(fd)
    os.unlink(tmp)


def _reason(e: OSError) -> str:
    return e.strerror or type(e).__name__


# ---------------------------------------------------------------------------------------------
# the array cache


def _canonical(key: Mapping) -> str:
    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, os.PathLike):
            return os.fspath(o)
        raise TypeError(f"jaxrt.cache: key values must be JSON data (str, number, bool, None, list, dict); "
                        f"got {type(o).__name__}")

    return json.dumps(dict(key), sort_keys=True, separators=(",", ":"), allow_nan=False, default=default)


def _digest(arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.reshape(-1).view(np.uint8) if a.size else b"")
    return h.hexdigest()


def _checked(arrays: Any, kind: str) -> dict[str, np.ndarray]:
    if not isinstance(arrays, Mapping):
        raise TypeError(f"jaxrt.cache: the build function for {kind!r} must return a dict of arrays, "
                        f"got {type(arrays).__name__}")
    out = {}
    for name, a in arrays.items():
        if not isinstance(name, str) or not name.isidentifier() or name.startswith("__"):
            raise ValueError(f"jaxrt.cache: array names must be identifiers not starting with '__'; got {name!r}")
        a = np.asarray(a)
        if a.dtype.hasobject:
            raise TypeError(f"jaxrt.cache: array {name!r} of {kind!r} has dtype object (it would need pickle)")
        out[name] = a
    return out


def _read(path: Path, key_json: str) -> dict[str, np.ndarray]:
    """The verified arrays of entry `path` (raises on anything wrong: missing, truncated, corrupt, stale)."""
    with open(path, "rb") as fh:
        meta = json.loads(np.lib.format.read_array(fh, allow_pickle=False).tobytes().decode())
        if meta.get("format") != FORMAT_VERSION or meta.get("key") != key_json:
            raise ValueError("stale entry (written for another key or format)")
        names = meta["arrays"]
        if not isinstance(names, list) or len(set(names)) != len(names):
            raise ValueError("the entry's record of its arrays is malformed")
        # read_array raises on a short record (a truncated file); bytes after the last are corruption
        arrays = {n: np.lib.format.read_array(fh, allow_pickle=False) for n in names}
        if fh.read(1):
            raise ValueError("the entry has bytes after its last array")
    if _digest(arrays) != meta["sha256"]:
        raise ValueError("checksum mismatch")
    return arrays


def _write(folder: Path, path: Path, arrays: dict[str, np.ndarray], key_json: str) -> None:
    """Store `arrays` at `path` through a temporary file and a rename (raises OSError)."""
    folder.mkdir(parents=True, exist_ok=True)
    meta = json.dumps({"format": FORMAT_VERSION, "key": key_json, "arrays": list(arrays),
                       "sha256": _digest(arrays)}).encode()
    fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, suffix=_SUFFIX + ".part", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.lib.format.write_array(fh, np.frombuffer(meta, np.uint8), allow_pickle=False)
            for name in arrays:
                np.lib.format.write_array(fh, np.asarray(arrays[name]), allow_pickle=False)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def entry_path(kind: str, key: Mapping) -> Path:
    """The file that holds (or would hold) the entry of `cached_arrays(kind, key, ...)`."""
    if not _KIND.match(kind):
        raise ValueError(f"jaxrt.cache: kind must be 1-32 lower-case letters, digits or _ (starting with a letter); "
                         f"got {kind!r}")
    key_json = _canonical({"format": FORMAT_VERSION, "kind": kind, "key": key})
    return _config.config().cache_dir / "arrays" / f"{kind}-{hashlib.sha256(key_json.encode()).hexdigest()[:32]}{_SUFFIX}"


def cached_arrays(kind: str, key: Mapping, build: Callable[[], Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The arrays `build()` returns for `key`, from the cache when an entry for (kind, key) is there.

    kind: a short lower-case name (letters, digits, _) that prefixes the entry's file name.
    key: JSON data (str, numbers, bool, None, lists, dicts; numpy scalars and paths converted) that
    determines the result completely. build: returns a dict of numpy arrays (names are identifiers
    not starting with "__"; no object dtype); called on a miss, and on every call with JAXRT_CACHE=off.
    Errors raised by `build` propagate; problems with the cache never do (see the module docstring).
    """
    path = entry_path(kind, key)
    cfg = _config.config()
    key_json = _canonical({"format": FORMAT_VERSION, "kind": kind, "key": key})
    if not cfg.cache:
        _count("bypasses")
        return _checked(build(), kind)
    folder = path.parent
    existed = path.is_file()
    if existed:
        try:
            arrays = _read(path, key_json)
        except Exception as e:  # noqa: BLE001 -- any bad entry means: rebuild it
            _warn_once("corrupt", str(path), f"jaxrt cache: {path}: unreadable entry ({type(e).__name__}: "
                                             f"{str(e)[:200]}); rebuilding it")
            _count("rebuilds")
        else:
            _count("hits")
            try:
                os.utime(path)  # least recently used = oldest modification time
            except OSError:
                pass
            return arrays
    else:
        _count("misses")
    arrays = _checked(build(), kind)
    size = sum(a.nbytes for a in arrays.values())
    if str(folder) in _unwritable or size > cfg.cache_size:
        return arrays
    try:
        _write(folder, path, arrays, key_json)
    except OSError as e:
        with _lock:
            _unwritable.add(str(folder))
        _warn_once("unwritable", str(cfg.cache_dir), f"jaxrt cache: cannot store entries in {folder} ({_reason(e)}); "
                                                     f"continuing without storing meshes and BVHs")
        return arrays
    _count("writes")
    _trim(cfg.cache_dir, cfg.cache_size, keep=path)
    return arrays


def _entries(root: Path) -> list[tuple[float, int, list[Path]]]:
    """(last use, bytes, files) per entry of both parts; leftover temporary files are deleted on the way."""
    out = []
    now = time.time()
    arrays = root / "arrays"
    for p in _listdir(arrays):
        st = _stat(p)
        if st is None:
            continue
        if p.name.startswith(_TMP_PREFIX):
            if now - st.st_mtime > _TMP_MAX_AGE_S:
                _unlink(p)
        elif p.suffix == _SUFFIX or p.suffix in _OLD_SUFFIXES:
            out.append((st.st_mtime, st.st_size, [p]))
    xla = root / "xla"
    for p in _listdir(xla):
        if p.name.endswith("-cache"):
            st = _stat(p)
            if st is None:
                continue
            atime = xla / (p.name[: -len("-cache")] + "-atime")
            ast = _stat(atime)
            files = [p] + ([atime] if ast is not None else [])
            out.append((st.st_mtime, st.st_size + (ast.st_size if ast else 0), files))
    return out


def _listdir(folder: Path) -> list[Path]:
    try:
        return [folder / n for n in os.listdir(folder)]
    except OSError:
        return []


def _stat(p: Path):
    try:
        return p.stat()
    except OSError:
        return None


def _unlink(p: Path) -> bool:
    try:
        p.unlink()
        return True
    except FileNotFoundError:
        return False
    except OSError:
        return False


def _trim(root: Path, bound: int, keep: Path | None = None) -> None:
    """Delete least recently used entries until both parts together hold at most `bound` bytes."""
    entries = sorted(_entries(root), key=lambda e: e[0])
    total = sum(e[1] for e in entries)
    for _, size, files in entries:
        if total <= bound:
            break
        if keep is not None and keep in files:
            continue
        if _unlink(files[0]):
            _count("evictions")
        for f in files[1:]:
            _unlink(f)
        total -= size


def info() -> CacheInfo:
    """The cache folder, whether caching is on, entries and bytes of each part, and the size bound."""
    cfg = _config.config()
    arrays = compiled = (0, 0)
    for _, size, files in _entries(cfg.cache_dir) if cfg.cache_dir.is_dir() else []:
        if files[0].parent.name == "arrays":
            arrays = (arrays[0] + 1, arrays[1] + size)
        else:
            compiled = (compiled[0] + 1, compiled[1] + size)
    xla_bytes = sum(st.st_size for top, _, files in os.walk(cfg.cache_dir / "xla") for n in files
                    if (st := _stat(Path(top) / n)) is not None)
    return CacheInfo(dir=cfg.cache_dir, enabled=cfg.cache, array_entries=arrays[0], array_bytes=arrays[1],
                     compiled_entries=compiled[0], compiled_bytes=max(compiled[1], xla_bytes), bound=cfg.cache_size)


def clear() -> int:
    """Delete every entry of both parts (and leftover temporary files); returns the bytes freed.

    Everything under ``xla/`` is JAX's (its entries, and on a GPU XLA's autotuning results) and goes;
    under ``arrays/`` only entry and temporary files go. Works with JAXRT_CACHE=off too. Files that
    cannot be deleted are skipped.
    """
    root = _config.config().cache_dir
    freed = 0
    for p in _listdir(root / "arrays"):
        st = _stat(p)
        if st is not None and p.is_file() and (p.suffix == _SUFFIX or p.suffix in _OLD_SUFFIXES or p.name.startswith(_TMP_PREFIX)) and _unlink(p):
            freed += st.st_size
    for top, dirs, files in os.walk(root / "xla", topdown=False):
        for n in files:
            p = Path(top) / n
            st = _stat(p)
            if st is not None and _unlink(p):
                freed += st.st_size
        for n in dirs:
            try:
                (Path(top) / n).rmdir()
            except OSError:
                pass
    return freed


# ---------------------------------------------------------------------------------------------
# meshes and BVHs through the array cache


def _source_hash(*modules) -> str:
    h = hashlib.sha256()
    for m in modules:
        h.update(Path(m.__file__).read_bytes())
    return h.hexdigest()[:32]


def _version(dist: str) -> str:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "unknown"


def _array_hash(a: np.ndarray) -> str:
    return _digest({"a": a})


def _json_array(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj).encode(), np.uint8)


def _from_json_array(a: np.ndarray):
    return json.loads(a.tobytes().decode())


_SOURCE = "\0source\0"  # stands for the file's path in stored warning messages


def load_mesh(path: str | os.PathLike, flat: bool = False, *, name: str | None = None) -> Mesh:
    """`jaxrt.geometry.mesh.load(path, flat=flat, name=name)` through the array cache (bit-identical result).

    Key: the file's sha256 and name, flat, name, the source of `jaxrt.geometry.mesh` and the numpy and
    trimesh versions. Warnings the load gave (zero-area triangles removed) are given again on a
    cache hit, naming `path`. An uncached ``.gltf`` (its buffers are separate files the key would
    not cover) and a path that is not a file go straight to `jaxrt.geometry.mesh.load`, which reports errors.
    """
    from jaxrt.geometry import data as _data
    from jaxrt.geometry import mesh as _mesh

    path = Path(path)
    if not path.is_file() or path.name.lower().endswith(".gltf"):
        return _mesh.load(path, flat=flat, name=name)
    key = {"file_sha256": _data.sha256_of(path), "file_name": path.name, "flat": bool(flat), "name": name,
           "code": _source_hash(_mesh), "numpy": np.__version__, "trimesh": _version("trimesh")}
    src = str(path)

    def build():
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            m = _mesh.load(path, flat=flat, name=name)
        said = [(w.category.__name__, str(w.message).replace(src, _SOURCE)) for w in caught]
        out = dict(vertices=m.vertices, faces=m.faces, normals=m.normals, tangents=m.tangents,
                   object_id=m.object_id, names=_json_array(list(m.names)), warnings=_json_array(said))
        if m.uvs is not None:
            out["uvs"] = m.uvs
        return out

    a = cached_arrays("mesh", key, build)
    for category, message in _from_json_array(a["warnings"]):
        cat = getattr(builtins, category, None)
        cat = cat if isinstance(cat, type) and issubclass(cat, Warning) else UserWarning
        warnings.warn(message.replace(_SOURCE, src), cat, stacklevel=2)
    return _mesh.Mesh(vertices=a["vertices"], faces=a["faces"], normals=a["normals"], uvs=a.get("uvs"),
                      tangents=a["tangents"], object_id=a["object_id"], names=tuple(_from_json_array(a["names"])))


def cached_meshes(kind: str, key: Mapping, build: Callable[[], list[tuple[Any, Mesh]]],
                  sources: tuple = ()) -> list[tuple[Any, Mesh]]:
    """[(label, Mesh)] from `build()` through the array cache (bit-identical meshes; a label is any
    JSON value).

    For derived geometry (e.g. a scene object's transformed meshes): `key` must hold everything the
    result depends on besides code; the source of `jaxrt.geometry.mesh` and of `sources` (modules),
    numpy's and trimesh's versions are added. Warnings `build()` gave are given again on a hit, with
    every path in `key["files"]` (a list of str) restored.
    """
    from jaxrt.geometry import mesh as _mesh

    files = [str(f) for f in key.get("files", ())]
    key = {**key, "files": [Path(f).name for f in files],
           "sha256": [_file_sha256(f) for f in files], "code": _source_hash(_mesh, *sources),
           "numpy": np.__version__, "trimesh": _version("trimesh")}
    fields = ("vertices", "faces", "normals", "tangents", "object_id", "uvs")

    def store():
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            pieces = build()
        said = []
        for w in caught:
            msg = str(w.message)
            for i, f in enumerate(files):
                msg = msg.replace(f, f"\0file{i}\0")
            said.append((w.category.__name__, msg))
        out = {"labels": _json_array([lab for lab, _ in pieces]), "warnings": _json_array(said),
               "names": _json_array([list(m.names) for _, m in pieces])}
        for i, (_, m) in enumerate(pieces):
            out.update({f"m{i}_{k}": getattr(m, k) for k in fields if getattr(m, k) is not None})
        return out

    a = cached_arrays(kind, key, store)
    for category, message in _from_json_array(a["warnings"]):
        for i, f in enumerate(files):
            message = message.replace(f"\0file{i}\0", f)
        cat = getattr(builtins, category, None)
        warnings.warn(message, cat if isinstance(cat, type) and issubclass(cat, Warning) else UserWarning,
                      stacklevel=2)
    names = _from_json_array(a["names"])
    return [(lab, _mesh.Mesh(**{k: a.get(f"m{i}_{k}") for k in fields}, names=tuple(names[i])))
            for i, lab in enumerate(_from_json_array(a["labels"]))]


def _file_sha256(path: str) -> str:
    from jaxrt.geometry import data as _data

    return _data.sha256_of(path)


_shared_trees: dict[str, BVH] | None = None  # while `sharing_trees` is active: key -> tree
_shared_depth = 0
_shared_lock = threading.Lock()


@contextlib.contextmanager
def sharing_trees():
    """Within this block, `build_bvh` calls with the same arrays and settings return the tree the
    first one built or read (one read of the entry, one transfer to the device), e.g. the two builds
    of one geometry a fit's preparation makes (the scene as given, and with the fitted material). A
    tree is a pure function of its key, so sharing it changes nothing; the block bounds how long the
    trees are held (a resident worker's later jobs do not keep them)."""
    global _shared_trees, _shared_depth
    with _shared_lock:
        _shared_depth += 1
        if _shared_trees is None:
            _shared_trees = {}
    try:
        yield
    finally:
        with _shared_lock:
            _shared_depth -= 1
            if _shared_depth == 0:
                _shared_trees = None


def build_bvh(vertices, faces, *, leaf_size: int = 1, builder: str = "lbvh", layout: str = "bfs",
              sah_settings: SahSettings | None = None) -> BVH:
    """`jaxrt.accel.build(vertices, faces, leaf_size=..., builder=..., layout=..., sah_settings=...)`
    through the array cache (bit-identical result; arguments and errors as there).

    Key: sha256 of the vertex and face arrays (dtype, shape, bytes), leaf_size, builder, layout, the
    SAH builder's settings (`jaxrt.accel.sah.SahSettings`), the source of the modules that build
    and pack the tree, numpy's version and the default backend (a GPU build also stores the GPU
    kernel's node tables, and then keys on JAX's version too).
    """
    import jax

    from jaxrt.accel import builder as _builder
    from jaxrt.accel import bvh as _bvh
    from jaxrt.accel import morton, sah, traverse_pallas

    sah_settings = sah.DEFAULT if sah_settings is None else sah_settings

    v = np.asarray(vertices)
    f = np.asarray(faces)
    backend = jax.default_backend()
    key = {"vertices": _array_hash(v), "faces": _array_hash(f), "leaf_size": leaf_size, "builder": builder,
           "layout": layout, "code": _source_hash(_bvh, _builder, sah, morton, traverse_pallas), "numpy": np.__version__,
           "backend": backend, "jax": jax.__version__ if backend == "gpu" else None,
           "sah": dataclasses.asdict(sah_settings) if builder == "sah" else None}
    shared = _shared_trees
    memo = _canonical(key) if shared is not None else None
    if memo is not None and memo in shared:
        return shared[memo]
    fields = dataclasses.fields(_bvh.BVH)
    built = []

    def build():
        tree = _bvh.build(v, f, leaf_size=leaf_size, builder=builder, layout=layout, sah_settings=sah_settings)
        built.append(tree)
        out = {x.name: np.asarray(getattr(tree, x.name)) for x in fields
               if not x.metadata.get("static") and getattr(tree, x.name) is not None}
        out["static"] = _json_array({x.name: getattr(tree, x.name) for x in fields if x.metadata.get("static")})
        return out

    a = cached_arrays("bvh", key, build)
    if built:
        tree = built[0]
    else:
        static = _from_json_array(a["static"])
        kw = {x.name: (jax.device_put(a[x.name]) if x.name in a else None) for x in fields
              if not x.metadata.get("static")}
        tree = _bvh.BVH(**kw, **static)
    if memo is not None:
        shared[memo] = tree
    return tree
