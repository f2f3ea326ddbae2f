"""Finding measured materials: names like "merl/alum-bronze" -> a checked member of a zip archive.

The neural BRDFs of Sztrajman, Rainer, Ritschel & Weyrich ("Neural BRDF Representation and Importance
Sampling", Computer Graphics Forum 40(6), 2021) come as three zip archives, one per measured database:

    collection  archive                   folder in the archive   materials  measured by
    merl        merl_nbrdf.zip            merl_nbrdf/             100        Matusik et al. 2003 (MERL 100)
    rgl         rgl-isotropic_nbrdf.zip   rgl-isotropic_nbrdf/    51         Dupuy & Jakob 2018 (RGL-EPFL, isotropic)
    nielsen     nielsen_nbrdf.zip         nielsen_nbrdf/          8          Nielsen, Jensen & Ramamoorthi 2015

Each material is `FOLDER/NAME.h5` (the network's weights) beside `FOLDER/NAME.json` (a Keras model
description whose last layer is marshalled Python bytecode; nothing here reads the .json files). A
material's name is "COLLECTION/NAME", NAME being the .h5 file's stem.

The archives are read in place (zipfile), never extracted. `find_material` looks for the archive in, in
this order,

  1. the environment variable ``JAXRT_DATA``: the data root (archives in ``$JAXRT_DATA/brdfs/``), or any
     folder beside ``brdfs/`` such as the mesh folder ``$JAXRT_DATA = .../data/meshes`` (archives in
     ``$JAXRT_DATA/../brdfs/``), or the archives' own folder;
  2. the user cache: ``$XDG_CACHE_HOME/jaxrt/brdfs`` if XDG_CACHE_HOME is set, else ``~/.cache/jaxrt/brdfs``,

and checks each archive's sha256 against `ARCHIVES` before the first use. jaxrt never downloads
anything: a missing or corrupt archive is a one-line `InputError` saying where it was looked for and
where to get it. The lookups take `dirs=` to search other folders instead. (The BRDF library
depends on nothing else of the project, so it reads the two variables itself, with the meaning
jaxrt's configuration gives them: unset or empty means not given.)
"""

from __future__ import annotations

import difflib
import hashlib
import os
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from brdfs.errors import InputError


class Archive(NamedTuple):
    """One archive of neural BRDFs: file name, sha256 (hex), folder inside the zip, material count."""

    filename: str
    sha256: str
    folder: str
    count: int


_SOURCE = ("GitHub asztr/Neural-BRDF, folder data/, commit e229dda3308c78f05e57dbc9455326884f766301 "
           "(Sztrajman et al. 2021, MIT licence)")

#: collection -> archive; the checksums are those of the published archives.
ARCHIVES: dict[str, Archive] = {
    "merl": Archive("merl_nbrdf.zip", "d1678c0cc5059f315d3d3284f36f3082787474106d72e3cae41fbad76d8f271a",
                    "merl_nbrdf", 100),
    "rgl": Archive("rgl-isotropic_nbrdf.zip", "401f588f08a66714ebd9d1355298f85e4d2f3782c9a87f370538dc8657cf5389",
                   "rgl-isotropic_nbrdf", 51),
    "nielsen": Archive("nielsen_nbrdf.zip", "fd034c57b2cbe0e976b088ea4bb7ccbdda3782dad90946243124e07316442166",
                       "nielsen_nbrdf", 8),
}

#: Checked archives: (path, size, mtime_ns) -> sha256, so repeated lookups do not rehash.
_verified: dict[tuple[str, int, int], str] = {}
#: Member listings of checked archives: (path, size, mtime_ns) -> sorted material stems.
_listings: dict[tuple[str, int, int], tuple[str, ...]] = {}


class Material(NamedTuple):
    """A located measured material: `name` ("merl/alum-bronze"), the checked `archive` and the zip
    `member` holding its weights ("merl_nbrdf/alum-bronze.h5")."""

    name: str
    archive: Path
    member: str

    def read_bytes(self) -> bytes:
        """The member's bytes (the .h5 file), read from the archive in place."""
        with zipfile.ZipFile(self.archive) as zf:
            return zf.read(self.member)


def search_dirs() -> list[Path]:
    """Folders searched for the archives, in order (see the module docstring); duplicates removed."""
    dirs: list[Path] = []
    env = os.environ.get("JAXRT_DATA")
    if env:
        root = Path(env).expanduser()
        dirs += [root / "brdfs", root.parent / "brdfs", root]
    xdg = os.environ.get("XDG_CACHE_HOME")
    dirs.append((Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "jaxrt" / "brdfs")
    out: list[Path] = []
    for d in dirs:
        if d not in out:
            out.append(d)
    return out


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _key(path: Path) -> tuple[str, int, int]:
    st = path.stat()
    return (str(path.resolve()), st.st_size, st.st_mtime_ns)


def find_archive(collection: str, dirs: Sequence[Path] | None = None) -> Path:
    """Path of the checked archive of `collection` ("merl", "rgl" or "nielsen"), searched in `dirs`
    (default `search_dirs()`).

    Raises InputError for an unknown collection, an archive found nowhere, or one whose sha256 differs.
    """
    if collection not in ARCHIVES:
        raise InputError(f"unknown measured-material collection {collection!r}; known: {', '.join(ARCHIVES)}")
    a = ARCHIVES[collection]
    dirs = search_dirs() if dirs is None else [Path(d) for d in dirs]
    for d in dirs:
        path = d / a.filename
        if not path.is_file():
            continue
        key = _key(path)
        digest = _verified.get(key) or _sha256(path)
        if digest != a.sha256:
            raise InputError(f"{path}: corrupt or wrong archive for {collection!r}: sha256 {digest}, expected "
                             f"{a.sha256}; replace it with {a.filename} from {_SOURCE}")
        _verified[key] = digest
        return path
    hint = "" if os.environ.get("JAXRT_DATA") else " (JAXRT_DATA is not set)"
    raise InputError(f"measured-material archive {a.filename!r} not found in {', '.join(map(str, dirs))}{hint}; "
                     f"get it from {_SOURCE} and put it in $JAXRT_DATA/brdfs or the user cache")


def _listing(collection: str, dirs=None) -> tuple[Path, tuple[str, ...]]:
    """(archive path, sorted material stems) of a collection; the count is checked against `ARCHIVES`."""
    path = find_archive(collection, dirs)
    key = _key(path)
    if key not in _listings:
        a = ARCHIVES[collection]
        prefix = a.folder + "/"
        with zipfile.ZipFile(path) as zf:
            stems = sorted(n[len(prefix):-3] for n in zf.namelist()
                           if n.startswith(prefix) and n.endswith(".h5") and "/" not in n[len(prefix):])
        if len(stems) != a.count:
            raise InputError(f"{path}: expected {a.count} materials ({prefix}*.h5), found {len(stems)}")
        _listings[key] = tuple(stems)
    return path, _listings[key]


def material_names(collection: str | None = None, dirs: Sequence[Path] | None = None) -> tuple[str, ...]:
    """Every measured material's name ("merl/alum-bronze", ...), collection by collection (all 159 when
    `collection` is None); needs the archives (InputError naming what is missing otherwise)."""
    cols = ARCHIVES if collection is None else [collection]
    return tuple(f"{c}/{s}" for c in cols for s in _listing(c, dirs)[1])


def find_material(name: str, dirs: Sequence[Path] | None = None) -> Material:
    """ "COLLECTION/NAME" -> the located, checked `Material`.

    Raises InputError for a malformed name, an unknown collection or material (listing close matches),
    or a missing/corrupt archive.
    """
    if not isinstance(name, str) or name.count("/") != 1:
        raise InputError(f"measured material {name!r}: expected 'COLLECTION/NAME' with COLLECTION one of "
                         f"{', '.join(ARCHIVES)} (e.g. 'merl/alum-bronze')")
    collection, stem = name.split("/")
    path, stems = _listing(collection, dirs)
    if stem not in stems:
        close = difflib.get_close_matches(stem, stems, n=5, cutoff=0.5)
        hint = (f"; close matches: {', '.join(f'{collection}/{c}' for c in close)}" if close
                else f"; {len(stems)} materials, e.g. {collection}/{stems[0]}")
        raise InputError(f"unknown measured material {name!r}{hint}")
    return Material(name, path, f"{ARCHIVES[collection].folder}/{stem}.h5")
