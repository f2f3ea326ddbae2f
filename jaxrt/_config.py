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
| JAXRT_TRAVERSAL | BVH traversal when a call passes none (`jaxrt.accel.bvh.intersect`) | auto, xla, cpu, embree, pallas, pallas-interpret (auto) |
| JAXRT_CACHE_DIR | the per-user cache folder (compiled programs, meshes, BVHs) | a path ($XDG_CACHE_HOME/jaxrt, else ~/.cache/jaxrt) |
| JAXRT_CACHE | whether the on-disk caches are used | on, off (on) |
| JAXRT_CACHE_SIZE | the cache folder's size bound; least recently used entries go first | bytes, or a number with K/M/G/T (binary units) (2G) |
| JAXRT_MEMORY | the memory budget of `jaxrt render` and `jaxrt.render(memory="auto")` (`jaxrt.render_tiles`) | bytes, or a number with K/M/G/T (unset: derived from the device) |
| JAXRT_CONFINE | refuse scene paths (meshes, textures, environment maps) outside the scene's folder and the data folder (`jaxrt.scene.parse`; the CLI's `--confine`) | as JAXRT_DEBUG (off) |
| JAXRT_COORDINATOR | several hosts: the address of process 0's coordination service, host:port (`jax.distributed.initialize`, called by `jaxrt._devices.initialize` and the CLI) | host:port (unset: one process) |
| JAXRT_PROCESS_COUNT | several hosts: how many processes take part, one per host | an integer ≥ 1 (required with JAXRT_COORDINATOR) |
| JAXRT_PROCESS_ID | several hosts: this process's index; only process 0 writes output files (`jaxrt.fsutil`) | 0 .. JAXRT_PROCESS_COUNT − 1 (required with JAXRT_COORDINATOR) |
| JAXRT_WORKER | whether the `jaxrt` command hands its job to a resident worker (`jaxrt serve`, `jaxrt.serve`): use one that is running and start one for a command typed at a terminal (auto), use one that is running, start one when none is, or never | auto, use, start, off (auto) |

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

__all__ = ["DEFAULT_CACHE_SIZE", "MAX_CPU_DEVICES", "RUNTIME_DEFAULTS", "TRAVERSALS", "VARIABLES", "WORKER_KEY_PREFIXES", "WORKER_KEY_VARIABLES", "WORKER_MODES",
           "Config", "apply_runtime_defaults", "command_defaults", "config", "cores", "default_cache_dir",
           "parse_size"]

#: The traversal implementations `JAXRT_TRAVERSAL` may name (`jaxrt.accel.bvh.IMPLS` holds the same tuple).
TRAVERSALS = ("auto", "xla", "cpu", "embree", "pallas", "pallas-interpret")

#: The default bound of the cache folder, in bytes (2 GiB).
DEFAULT_CACHE_SIZE = 2 << 30

#: Every variable this module reads, in the order of the table above.
VARIABLES = ("JAXRT_DATA", "JAXRT_DEBUG", "JAXRT_TRAVERSAL", "JAXRT_CACHE_DIR", "JAXRT_CACHE", "JAXRT_CACHE_SIZE",
             "JAXRT_MEMORY", "JAXRT_CONFINE", "JAXRT_COORDINATOR", "JAXRT_PROCESS_COUNT", "JAXRT_PROCESS_ID",
             "JAXRT_WORKER")

#: The values of JAXRT_WORKER: use a running worker and start one for a command typed at a terminal
#: (`jaxrt.serve.wants_worker`), use a running worker, start one when none is running, never use one.
WORKER_MODES = ("auto", "use", "start", "off")

#: Environment variables a running process cannot take from a job (JAX and the GPU runtime read
#: them when they start; jaxrt when it turns the compilation cache on and picks a traversal): a
#: resident worker serves only clients whose values equal its own (`jaxrt.serve.worker_key`), every
#: variable starting with one of `WORKER_KEY_PREFIXES` included. Every other JAXRT_* variable
#: travels with each job.
WORKER_KEY_VARIABLES = ("JAXRT_CACHE_DIR", "JAXRT_CACHE", "JAXRT_TRAVERSAL", "XDG_CACHE_HOME", "HOME",
                        "CUDA_VISIBLE_DEVICES", "HIP_VISIBLE_DEVICES", "ROCR_VISIBLE_DEVICES", "TPU_VISIBLE_CHIPS",
                        "NVIDIA_TF32_OVERRIDE", "OMP_NUM_THREADS", "PYTHONPATH", "PYTHONHASHSEED", "LD_LIBRARY_PATH")
WORKER_KEY_PREFIXES = ("JAX_", "XLA_", "TF_", "NCCL_")

#: Defaults jaxrt gives JAX's runtime variables when the environment does not set them (set just before
#: the first JAX-using jaxrt module loads, `apply_runtime_defaults`; an explicit value always wins).
#: XLA_PYTHON_CLIENT_PREALLOCATE=false: JAX's GPU client otherwise reserves 75 % of the GPU's memory at
#: its first allocation, which costs 1.6-1.8 s on a 141 GB H200 in every process (a third of a warm
#: `jaxrt render dragon`) and holds the memory whether a job needs it or not; the allocator still
#: keeps and reuses what it has grown to, so frames after the first run at the same speed.
RUNTIME_DEFAULTS = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}

#: The most CPU devices a `jaxrt` command asks JAX for (`command_defaults`). Every device holds its
#: own copy of the scene (`jaxrt._devices`: BVH, materials, textures) and the render's memory budget
#: is split between them, and at 8 devices a frame's tiles stop having the same shape for every
#: device count (`jaxrt._devices.MIN_TILES` / `TILES_PER_DEVICE`).
MAX_CPU_DEVICES = 8

_CPU_DEVICE_FLAG = "--xla_force_host_platform_device_count"

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
    coordinator: JAXRT_COORDINATOR ("host:port"), or None for a single process
    process_count, process_id: JAXRT_PROCESS_COUNT and JAXRT_PROCESS_ID (1 and 0 without a coordinator)
    worker:      JAXRT_WORKER, one of `WORKER_MODES`
    """

    data: Path | None
    debug: bool
    traversal: str
    cache_dir: Path
    cache: bool
    cache_size: int
    memory: int | None
    confine: bool
    coordinator: str | None = None
    process_count: int = 1
    process_id: int = 0
    worker: str = "auto"


def apply_runtime_defaults(environ: dict | None = None) -> dict:
    """Set each of `RUNTIME_DEFAULTS` that `environ` (default: ``os.environ``) lacks; returns `environ`.

    Takes effect when JAX creates its backend (the first device query or array), so call it before
    that; a process whose backend already started keeps what it started with."""
    env = os.environ if environ is None else environ
    for name, value in RUNTIME_DEFAULTS.items():
        env.setdefault(name, value)
    return env


def cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the platform has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - platforms without affinity masks
        return max(1, os.cpu_count() or 1)


def command_defaults(environ: dict | None = None) -> dict:
    """`apply_runtime_defaults`, and for a `jaxrt` command one device per core (at most
    `MAX_CPU_DEVICES`) on JAX's CPU backend, JAX_NUM_CPU_DEVICES, unless the environment already sets
    it or XLA_FLAGS sets --xla_force_host_platform_device_count. Returns `environ` (default
    ``os.environ``).

    Why: XLA:CPU runs one program's fused loops on one thread (only library calls such as jaxrt's
    traversal kernels spread over the cores), so a progressive render whose tiles are spread over one
    device per core keeps every core busy: path tracing 512², 16 spp on 2 cores took 0.69-0.75 of the
    one-device time (BENCHMARKS.md, "CPU path tracing on one device per core"). A GPU render is not
    affected (only the CPU backend's device count changes). Fits do not spread over CPU devices by
    default (`jaxrt._devices.solver_devices`). Only the command line does this: the Python API keeps
    JAX's default of one CPU device, as a program that imports jaxrt expects."""
    env = apply_runtime_defaults(environ)
    if "JAX_NUM_CPU_DEVICES" not in env and _CPU_DEVICE_FLAG not in env.get("XLA_FLAGS", ""):
        env["JAX_NUM_CPU_DEVICES"] = str(min(cores(), MAX_CPU_DEVICES))
    return env


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


_ADDRESS = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*):(\d{1,5})$")


def _processes(env: Mapping[str, str]) -> tuple[str | None, int, int]:
    """(coordinator, process count, process id) of a run over several hosts, or (None, 1, 0)."""
    raw = env.get("JAXRT_COORDINATOR", "")
    count_raw, id_raw = env.get("JAXRT_PROCESS_COUNT", ""), env.get("JAXRT_PROCESS_ID", "")
    if not raw.strip():
        for name, value in (("JAXRT_PROCESS_COUNT", count_raw), ("JAXRT_PROCESS_ID", id_raw)):
            if value.strip():
                raise InputError(f"{name}={value!r}: needs JAXRT_COORDINATOR (host:port of process 0) as well")
        return None, 1, 0
    addr = raw.strip()
    m = _ADDRESS.match(addr)
    if not m or not 0 < int(m.group(2)) < 65536:
        raise InputError(f"JAXRT_COORDINATOR={raw!r}: must be host:port of process 0 (e.g. 10.0.0.1:1234), "
                         f"a port from 1 to 65535")
    try:
        count = int(count_raw.strip())
    except ValueError:
        count = 0
    if count < 1:
        raise InputError(f"JAXRT_PROCESS_COUNT={count_raw!r}: with JAXRT_COORDINATOR, must be the number of "
                         f"processes (one per host), 1 or more")
    try:
        pid = int(id_raw.strip())
    except ValueError:
        pid = -1
    if not 0 <= pid < count:
        raise InputError(f"JAXRT_PROCESS_ID={id_raw!r}: with JAXRT_COORDINATOR, must be this process's index, "
                         f"0 to {count - 1}")
    return addr, count, pid


def config(environ: Mapping[str, str] | None = None) -> Config:
    """Read and validate every JAXRT_* variable of `environ` (default: os.environ) now.

    Raises InputError (one line naming the variable, its value and what is allowed) for: a
    JAXRT_DEBUG/JAXRT_CONFINE that is not a yes/no word, a JAXRT_TRAVERSAL not in `TRAVERSALS`,
    a JAXRT_CACHE other than on/off, a JAXRT_WORKER not in `WORKER_MODES`, a JAXRT_CACHE_SIZE/JAXRT_MEMORY that is not a size, a
    JAXRT_CACHE_DIR that names an existing non-folder, a JAXRT_COORDINATOR that is not host:port, a
    JAXRT_PROCESS_COUNT/JAXRT_PROCESS_ID missing or out of range with it, or either without it. JAXRT_DATA is not checked for existence here:
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

    worker_raw = env.get("JAXRT_WORKER", "")
    worker = worker_raw.strip().lower() or "auto"
    if worker not in WORKER_MODES:
        raise InputError(f"JAXRT_WORKER={worker_raw!r}: must be one of {', '.join(WORKER_MODES)}")

    coordinator, count, pid = _processes(env)
    return Config(
        worker=worker,
        coordinator=coordinator,
        process_count=count,
        process_id=pid,
        data=_path(env, "JAXRT_DATA"),
        debug=_flag(env, "JAXRT_DEBUG"),
        traversal=traversal,
        cache_dir=cache_dir,
        cache=cache_word == "on",
        cache_size=cache_size,
        memory=memory,
        confine=_flag(env, "JAXRT_CONFINE"),
    )
