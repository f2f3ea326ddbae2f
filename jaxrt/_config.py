"""Every ``JAXRT_*`` environment variable, read and validated in one place.

`config()` reads the environment each time it is called and returns an immutable `Config`; there is
no module-level state to reset (tests set variables with ``monkeypatch.setenv`` or pass a mapping as
``config(environ)``). Reading is cheap (a dozen dictionary look-ups), so callers read it where they
need a value rather than keeping a copy. A bad value raises `jaxrt.errors.InputError` with one line
that names the variable, the value and what is allowed. This module imports nothing beyond the
standard library and `jaxrt.errors`, so anything may import it without pulling in JAX.

| variable | meaning | allowed (default) |
|---|---|---|
| JAXRT_DATA | a folder searched first for the registry's data files (`jaxrt.geometry.data`) | a path (unset: only the user cache) |
| JAXRT_DEBUG | the CLI prints tracebacks instead of one-line errors | 1/true/yes/on, 0/false/no/off ("" = off) |
| JAXRT_TRAVERSAL | BVH traversal when a call passes none (`jaxrt.accel.bvh.intersect`) | auto, xla, cpu, pallas, pallas-interpret (auto) |
| JAXRT_CACHE_DIR | the per-user cache folder (compiled programs, meshes, BVHs) | a path ($XDG_CACHE_HOME/jaxrt, else ~/.cache/jaxrt) |
| JAXRT_CACHE | whether the on-disk caches are used | on, off (on) |
| JAXRT_CACHE_SIZE | the cache folder's size bound; least recently used entries go first | bytes, or a number with K/M/G/T (binary units) (2G) |
| JAXRT_MEMORY | the memory budget of `jaxrt render` and `jaxrt.render(memory="auto")` (`jaxrt.render_tiles`) | bytes, or a number with K/M/G/T (unset: derived from the device) |
| JAXRT_CONFINE | refuse scene paths (meshes, textures, environment maps) outside the scene's folder and the data folder (`jaxrt.scene.parse`; the CLI's `--confine`) | as JAXRT_DEBUG (off) |

Relative paths are taken relative to the current directory at the time of the call and returned
absolute, so a value read once means the same folder after a ``chdir``.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping
from pathlib import Path

from jaxrt.errors import InputError

__all__ = ["DEFAULT_CACHE_SIZE", "TRAVERSALS", "VARIABLES", "Config", "config", "default_cache_dir", "parse_size"]

#: The traversal implementations `JAXRT_TRAVERSAL` may name (`jaxrt.accel.bvh.IMPLS` holds the same tuple).
TRAVERSALS = ("auto", "xla", "cpu", "pallas", "pallas-interpret")

#: The default bound of the cache folder, in bytes (2 GiB).
DEFAULT_CACHE_SIZE = 2 << 30

#: Every variable this module reads, in the order of the table above.
VARIABLES = ("JAXRT_DATA", "JAXRT_DEBUG", "JAXRT_TRAVERSAL", "JAXRT_CACHE_DIR", "JAXRT_CACHE", "JAXRT_CACHE_SIZE",
             "JAXRT_MEMORY", "JAXRT_CONFINE")

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("", "0", "false", "no", "off")
_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}
_SIZE = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*([kmgt]?)(?:i?b)?\s*$", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class Config:
    """The validated environment (see the module docstring for each variable).

    data:        JAXRT_DATA as an absolute path, or None when unset or empty
    debug:       JAXRT_DEBUG
    traversal:   JAXRT_TRAVERSAL, one of `TRAVERSALS`
    cache_dir:   the cache folder: JAXRT_CACHE_DIR, else `default_cache_dir()`; absolute
    cache:       JAXRT_CACHE is on
    cache_size:  JAXRT_CACHE_SIZE in bytes (0 stores nothing)
    memory:      JAXRT_MEMORY in bytes, or None (the renderer's memory budget, `jaxrt.render_tiles`)
    confine:     JAXRT_CONFINE
    """

    data: Path | None
    debug: bool
    traversal: str
    cache_dir: Path
    cache: bool
    cache_size: int
    memory: int | None
    confine: bool


def default_cache_dir(environ: Mapping[str, str] | None = None) -> Path:
    """``$XDG_CACHE_HOME/jaxrt`` where XDG_CACHE_HOME is set and not empty, else ``~/.cache/jaxrt``
    (the folder `jaxrt.geometry.data` and `jaxrt.accel.traverse_cpu` use today)."""
    env = os.environ if environ is None else environ
    xdg = env.get("XDG_CACHE_HOME", "")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "jaxrt"


def parse_size(text: str, variable: str = "size") -> int:
    """Bytes from "1073741824", "512M", "2G", "1.5GiB", "64k" (binary units, case-insensitive).

    Raises InputError naming `variable` for anything else or a negative value.
    """
    m = _SIZE.match(text)
    if not m:
        raise InputError(f"{variable}={text!r}: must be a number of bytes, optionally followed by K, M, G or T "
                         f"(binary units), e.g. 2G or 500M")
    return int(float(m.group(1)) * _UNITS[m.group(2).lower()])


def _flag(env: Mapping[str, str], name: str) -> bool:
    raw = env.get(name, "")
    v = raw.strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    raise InputError(f"{name}={raw!r}: must be one of {', '.join(_TRUE)} (on) or {', '.join(_FALSE[1:])} (off)")


def _path(env: Mapping[str, str], name: str) -> Path | None:
    raw = env.get(name, "")
    if not raw.strip():
        return None
    if "\0" in raw:
        raise InputError(f"{name}={raw!r}: must be a path (it contains a NUL character)")
    return Path(os.path.abspath(Path(raw).expanduser()))


def config(environ: Mapping[str, str] | None = None) -> Config:
    """Read and validate every JAXRT_* variable of `environ` (default: os.environ) now.

    Raises InputError (one line naming the variable, its value and what is allowed) for: a
    JAXRT_DEBUG/JAXRT_CONFINE that is not a yes/no word, a JAXRT_TRAVERSAL not in `TRAVERSALS`,
    a JAXRT_CACHE other than on/off, a JAXRT_CACHE_SIZE/JAXRT_MEMORY that is not a size, and a
    JAXRT_CACHE_DIR that names an existing non-folder. JAXRT_DATA is not checked for existence here:
    `jaxrt.geometry.data.find` names it when a file is missing.
    """
    env = os.environ if environ is None else environ

    traversal = env.get("JAXRT_TRAVERSAL", "").strip() or "auto"
    if traversal not in TRAVERSALS:
        raise InputError(f"JAXRT_TRAVERSAL={env['JAXRT_TRAVERSAL']!r}: must be one of {', '.join(TRAVERSALS)}")

    cache_raw = env.get("JAXRT_CACHE", "")
    cache_word = cache_raw.strip().lower() or "on"
    if cache_word not in ("on", "off"):
        raise InputError(f"JAXRT_CACHE={cache_raw!r}: must be on or off")

    cache_dir = _path(env, "JAXRT_CACHE_DIR")
    if cache_dir is None:
        cache_dir = Path(os.path.abspath(default_cache_dir(env)))
    elif cache_dir.exists() and not cache_dir.is_dir():
        raise InputError(f"JAXRT_CACHE_DIR={env['JAXRT_CACHE_DIR']!r}: exists and is not a folder; "
                         f"name a folder (created when missing)")

    size_raw = env.get("JAXRT_CACHE_SIZE", "")
    cache_size = parse_size(size_raw, "JAXRT_CACHE_SIZE") if size_raw.strip() else DEFAULT_CACHE_SIZE

    mem_raw = env.get("JAXRT_MEMORY", "")
    memory = parse_size(mem_raw, "JAXRT_MEMORY") if mem_raw.strip() else None
    if memory == 0:
        raise InputError(f"JAXRT_MEMORY={mem_raw!r}: must be a positive size, e.g. 8G")

    return Config(
        data=_path(env, "JAXRT_DATA"),
        debug=_flag(env, "JAXRT_DEBUG"),
        traversal=traversal,
        cache_dir=cache_dir,
        cache=cache_word == "on",
        cache_size=cache_size,
        memory=memory,
        confine=_flag(env, "JAXRT_CONFINE"),
    )
