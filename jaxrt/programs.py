"""Traced programs kept across processes: `cached_jit`, a `jax.jit` whose tracing is done once per machine.

JAX's persistent compilation cache (`jaxrt.cache.enable_compilation_cache`) skips XLA compilation in
a new process, but not tracing and lowering: every process still runs the Python of the whole
integrator (a Whitted frame of the dragon traces and lowers for 5.5 s on an H200's host, most of a
warm `jaxrt render`). `cached_jit(fun)` removes that step for calls that repeat a program structure:

  1. The call's arguments are split into array leaves and their structure (the pytree definition,
     which holds every static field of a `Scene`: resolution, spp, integrator, model set, ...).
  2. The key is a hash of: `fun`'s name, the static arguments, the structure, every leaf's shape,
     dtype and weak type, the target platform and device kind, the JAX/jaxlib versions, the JAX
     options that change tracing (x64, promotion rules, matmul precision), the JAXRT_TRAVERSAL choice
     and the source of every module of the `jaxrt`, `brdfs` and `fitting` packages (and the native kernel).
  3. On a miss, `jax.export` traces and lowers `fun` for the concrete platform (so
     `lax.platform_dependent` keeps one branch) and the serialized program (StableHLO plus its
     calling convention) is stored as an array entry of `jaxrt.cache` (sha256-checked, atomic, under
     the cache's size bound).
  4. On a hit the program is deserialized (milliseconds) and called through `jax.jit`, whose small
     wrapper module lowers in ~0.1 s and whose compilation comes from the persistent cache.

Results are those of `jax.jit(fun)`: the same program runs (the tests compare bit for bit). Calls
that cannot use a stored program fall back to `jax.jit(fun)` with identical semantics: under a JAX
transformation (any argument is a tracer: `grad`, `vmap`, an outer `jit`), arguments on several
devices or on a platform other than the default one, JAXRT_CACHE=off, and programs `jax.export`
cannot serialize (host callbacks, outputs of unregistered pytree types). The exported program calls
custom targets that `jax.export` does not list as stable (the Pallas/Triton traversal, the native
CPU kernel); that is safe here because an entry is only ever read by the same JAX, jaxlib and jaxrt
on the same platform, which the key guarantees.

Within a process, each (key) keeps its compiled wrapper, so a repeated call costs a pytree flatten
and a dictionary lookup beyond `jax.jit`'s own dispatch.

Compiled programs and the kernel's mapping limit. XLA:CPU loads every compiled program's machine
code into memory mappings of its own (three per object file: code, constants, data; a small program
takes about a dozen, a frame of the path tracer hundreds), and JAX keeps every executable it compiled
for as long as the process lives. Linux allows a process `vm.max_map_count` mappings (65530 by
default); at the limit LLVM cannot map the next program and aborts the whole process ("Unable to
allocate section memory"). A long-lived process that compiles many distinct programs (the resident
worker, a notebook, a test run) reaches it. `mapped_regions()` reports (used, limit); `release()` drops
the compiled programs this process holds in memory (JAX's caches and the stored programs' executables;
the next call compiles again, from the persistent compilation cache where that is on); `relieve()`
releases when the used share passes `RELEASE_AT`. A stored program calls `relieve()` before it
compiles (once, with a warning, where it released anything), and `jaxrt serve` between jobs.
"""

from __future__ import annotations

import functools
import gc
import hashlib
import re
import threading
import warnings
import weakref
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxrt import _config

__all__ = ["RELEASE_AT", "ProgramStats", "cached_jit", "mapped_regions", "program_stats", "relieve", "release",
           "source_digest"]

# The Pallas GPU traversal's custom call (Triton), which `jax.export` does not list as stable; nor
# does it list the native CPU kernels' targets (`_native`).
_TRITON_TARGET = "__gpu$xla.gpu.triton"
# JAX options that change what tracing produces (or whether it raises).
_TRACE_OPTIONS = ("jax_enable_x64", "jax_numpy_rank_promotion", "jax_numpy_dtype_promotion",
                  "jax_default_matmul_precision", "jax_default_prng_impl", "jax_threefry_partitionable")
_PACKAGES = ("jaxrt", "brdfs", "fitting")
_CUSTOM_CALL = re.compile(r"custom_call @([\w$.\-]+)")
# The `jaxrt.accel` modules that build and register the native CPU kernels (each lists its FFI
# targets in `TARGETS`): a stored program lists the targets it calls, and a process registers those
# (only) before compiling it.
_NATIVE_MODULES = ("traverse_cpu", "traverse_embree")


@functools.cache
def _native() -> dict[str, str]:
    """FFI target -> the `jaxrt.accel` module that registers it, from the modules' own TARGETS (one
    source of truth: a target added to a module is stored, looked up and registered without an edit here)."""
    import importlib

    return {t: m for m in _NATIVE_MODULES for t in importlib.import_module(f"jaxrt.accel.{m}").TARGETS}

_lock = threading.Lock()
_counts = {"hits": 0, "misses": 0, "exports": 0, "fallbacks": 0}
# every `cached_jit` function of the process (weakly: a function that goes away is not kept alive),
# so that `release` can drop their executables
_functions: weakref.WeakSet = weakref.WeakSet()
_releasing = threading.Lock()
_released = {"warned": False}

#: the share of `vm.max_map_count` above which `relieve` releases the compiled programs (a program
#: compiled at 75 % still leaves room for a few hundred large ones before the limit)
RELEASE_AT = 0.75


def mapped_regions() -> tuple[int, int] | None:
    """(memory mappings this process holds, the most it may hold: Linux's ``vm.max_map_count``), or
    None where the kernel does not say (not Linux). Reading costs ~1 ms per 1,000 mappings."""
    try:
        with open("/proc/sys/vm/max_map_count", "rb") as f:
            limit = int(f.read())
        with open("/proc/self/maps", "rb") as f:
            used = sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))
    except (OSError, ValueError):
        return None
    return used, limit


def release() -> int:
    """Drop every compiled program this process holds in memory: JAX's caches (`jax.clear_caches`:
    every `jax.jit`'s executables and traces) and the executables of the `cached_jit` programs, whose
    traced programs are kept. Later calls compile again, from the persistent compilation cache where
    it is on (`jaxrt.cache`). Objects a caller still holds (a `lower(...).compile()` result) keep
    theirs. Returns how many stored programs' executables were dropped."""
    with _releasing:
        n = 0
        for fn in list(_functions):
            for stored in list(fn._programs.values()):
                if stored is not _UNSTORABLE and stored._executable is not None:
                    stored._executable = None  # a call compiling it meanwhile just sets it again
                    n += 1
        jax.clear_caches()
        gc.collect()
        return n


def relieve(fraction: float = RELEASE_AT) -> bool:
    """`release()` where this process holds more than `fraction` of the memory mappings it may hold
    (`mapped_regions`); True where it released."""
    m = mapped_regions()
    if m is None or m[0] <= fraction * m[1]:
        return False
    release()
    return True


class ProgramStats:
    """This process's `cached_jit` counters: `hits` (a stored program was used), `misses` (traced and
    stored), `fallbacks` (a call ran through plain `jax.jit`: under a transformation, on several
    devices, cache off, or a program export cannot serialize)."""

    __slots__ = ("hits", "misses", "fallbacks")

    def __init__(self, hits: int, misses: int, fallbacks: int):
        self.hits, self.misses, self.fallbacks = hits, misses, fallbacks

    def __repr__(self) -> str:
        return f"ProgramStats(hits={self.hits}, misses={self.misses}, fallbacks={self.fallbacks})"


def program_stats() -> ProgramStats:
    with _lock:
        return ProgramStats(_counts["hits"], _counts["misses"], _counts["fallbacks"])


def _count(name: str) -> None:
    with _lock:
        _counts[name] += 1


@functools.cache
def source_digest() -> str:
    """sha256 over the source files of the `jaxrt`, `brdfs` and `fitting` packages (once per process)."""
    import importlib.util

    h = hashlib.sha256()
    for pkg in _PACKAGES:
        spec = importlib.util.find_spec(pkg)  # located, not imported (fitting imports optimistix)
        if spec is None or not spec.submodule_search_locations:
            continue
        root = Path(next(iter(spec.submodule_search_locations)))
        for p in sorted(root.rglob("*")):
            if p.suffix in (".py", ".cc", ".h") and "__pycache__" not in p.parts:
                h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


@functools.cache
def _environment() -> dict:
    import jaxlib

    return {"jax": jax.__version__, "jaxlib": jaxlib.__version__, "source": source_digest()}


def _platform(leaves: Sequence[Any]) -> str | None:
    """The export platform of a call, or None where a stored program cannot serve it."""
    default = jax.default_backend()
    for x in leaves:
        if isinstance(x, jax.Array):
            devices = x.sharding.device_set
            if len(devices) != 1 or next(iter(devices)).platform != default:
                return None
    return jax.export.default_export_platform()


def _spec(x) -> tuple:
    """(shape, dtype, weak type) of a leaf as `jax.jit` would see it."""
    if hasattr(x, "dtype"):  # jax and numpy arrays, numpy scalars
        return (tuple(np.shape(x)), str(jax.dtypes.canonicalize_dtype(x.dtype)), bool(getattr(x, "weak_type", False)))
    # Python scalars are weakly typed
    return ((), str(jax.dtypes.canonicalize_dtype(jax.dtypes.result_type(x))), True)


@functools.cache
def _missing():
    """equinox's MISSING, the marker a Module's pytree node holds for fields it does not have: a
    singleton that Modules compare by identity, so a stored structure must unpickle to it."""
    import equinox as eqx

    class Probe(eqx.Module):
        pass

    return jax.tree_util.tree_structure(Probe()).node_data()[1][0]


def _dump_tree(tree) -> bytes:
    """An output's structure as bytes: pickle, with equinox's MISSING written as a reference to it.
    A structure that does not come back equal (a class pickle cannot name, such as one defined inside a
    function, or other data that does not survive a copy) raises: such a function runs through jax.jit."""
    import io
    import pickle

    missing = _missing()

    class Pickler(pickle.Pickler):
        def reducer_override(self, obj):
            return (_missing, ()) if obj is missing else NotImplemented

    buf = io.BytesIO()
    Pickler(buf, protocol=pickle.HIGHEST_PROTOCOL).dump(tree)
    data = buf.getvalue()
    if pickle.loads(data) != tree:
        raise ValueError(f"the output structure {str(tree)[:200]} does not survive pickling")
    return data


class _Stored:
    """One stored program of a `_CachedJit` in this process: the exported program (`jax.export`, which
    returns the flat output leaves) and the output's structure; compiled on first use, once, whichever
    thread gets there first (a compilation started ahead of time is waited for, not repeated)."""

    def __init__(self, exp, out_tree):
        self.exp, self.out_tree = exp, out_tree
        self._executable = None
        self._lock = threading.Lock()

    def executable(self, leaves):
        exe = self._executable
        if exe is not None:
            return exe
        _before_compiling()
        with self._lock:
            if self._executable is None:
                self._executable = jax.jit(self.exp.call).lower(*leaves).compile()
            return self._executable

    def __call__(self, leaves):
        return jax.tree_util.tree_unflatten(self.out_tree, self.executable(leaves)(*leaves))

    def out_info(self):
        avals = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in self.exp.out_avals]
        return jax.tree_util.tree_unflatten(self.out_tree, avals)


_UNSTORABLE = object()  # a program export could not store: calls with that key go through jax.jit


def _before_compiling() -> None:
    """`relieve()` before a stored program compiles; the first release of the process says so."""
    if relieve():
        used, limit = mapped_regions() or (0, 0)
        if not _released["warned"]:
            _released["warned"] = True
            warnings.warn(f"jaxrt: compiled programs filled more than {RELEASE_AT:.0%} of the {limit} memory "
                          f"mappings a process may have (vm.max_map_count; {used} after releasing them): "
                          "this process's compiled programs were dropped and compile again when used "
                          "(from the compilation cache where it is on)", RuntimeWarning, stacklevel=4)


class _CachedJit:
    def __init__(self, fun: Callable, name: str, static_argnames: tuple[str, ...]):
        self._fun = fun
        self._name = name
        self._static = static_argnames
        self._jit = jax.jit(fun, static_argnames=static_argnames)
        self._programs: dict[Any, _Stored] = {}
        # one load (read or export) at a time: a call that arrives while another thread loads the same
        # program (a compilation started ahead of time) waits for it instead of tracing it again
        self._loading = threading.RLock()
        functools.update_wrapper(self, fun)
        _functions.add(self)

    def _cache_size(self) -> int:
        """Distinct programs this function holds in this process (stored ones and `jax.jit`'s)."""
        return sum(p is not _UNSTORABLE for p in self._programs.values()) + self._jit._cache_size()

    def _program(self, args, kwargs):
        """(stored program, leaves) for a call that a stored program can serve, else (None, statics)."""
        statics = {k: kwargs.pop(k) for k in self._static if k in kwargs}
        leaves, tree = jax.tree_util.tree_flatten((args, kwargs))
        cfg = _config.config()
        platform = None
        if cfg.cache and not any(isinstance(x, jax.core.Tracer) for x in leaves):
            platform = _platform(leaves)
        if platform is None:
            return None, statics
        specs = tuple(_spec(x) for x in leaves)
        memo = (tree, specs, tuple(sorted(statics.items())), platform, cfg.traversal)
        try:
            stored = self._programs.get(memo)
        except TypeError:  # an unhashable static argument: jax.jit refuses it with its own message
            return None, statics
        if stored is None:
            with self._loading:
                stored = self._programs.get(memo)
                if stored is None:
                    stored = self._load(tree, specs, statics, platform, cfg) or _UNSTORABLE
                    self._programs[memo] = stored
        if stored is _UNSTORABLE:
            return None, statics
        return stored, leaves

    def __call__(self, *args, **kwargs):
        stored, rest = self._program(args, kwargs)
        if stored is None:
            _count("fallbacks")
            return self._jit(*args, **kwargs, **rest)
        return stored(rest)

    def lower(self, *args, **kwargs):
        """`jax.jit(fun).lower(...)`, through the stored program where there is one (arguments may be
        `jax.ShapeDtypeStruct`s): its `compile()` compiles the program later calls run (so compiling
        ahead of time, in another thread too, never compiles twice), and its `out_info` is the
        output's structure of `jax.ShapeDtypeStruct`s, known without tracing on a stored program."""
        stored, rest = self._program(args, kwargs)
        if stored is None:
            return self._jit.lower(*args, **kwargs, **rest)
        return _Lowered(stored, rest, self._static)

    def _load(self, tree, specs, statics, platform, cfg) -> _Stored | None:
        import pickle

        from jax import export

        from jaxrt import cache

        device = jax.devices()[0]
        key = {
            "function": self._name, "statics": repr(sorted(statics.items())), "tree": str(tree),
            "leaves": [list(s) for s in specs], "platform": platform, "device": device.device_kind,
            "traversal": cfg.traversal, "options": {o: str(getattr(jax.config, o, None)) for o in _TRACE_OPTIONS},
            **_environment(),
        }
        fun = self._fun
        out_trees: list = []

        def flat(*xs):
            # the program returns the output's leaves: `jax.export` serializes only the pytree types
            # registered with it, and a GBuffer or a FitBuffer is not; the structure is kept beside it
            a, k = jax.tree_util.tree_unflatten(tree, xs)
            leaves, out_tree = jax.tree_util.tree_flatten(fun(*a, **k, **statics))
            out_trees.append(out_tree)
            return leaves

        exported: list = []

        def build():
            avals = [jax.ShapeDtypeStruct(s[0], s[1], weak_type=s[2]) for s in specs]
            jitted = jax.jit(flat)
            targets = {_TRITON_TARGET, *_native()}
            for _ in range(2):
                checks = [export.DisabledSafetyCheck.custom_call(t) for t in sorted(targets)]
                try:
                    exp = export.export(jitted, platforms=[platform], disabled_checks=checks)(*avals)
                    break
                except ValueError as e:
                    if "custom calls" not in str(e):
                        raise
                    # other unlisted targets (LAPACK/cuSOLVER kernels of a linear solve, say): the
                    # program's own list, from its lowering (the trace itself is cached by jax.jit)
                    text = jitted.trace(*avals).lower(lowering_platforms=(platform,)).as_text()
                    targets |= set(_CUSTOM_CALL.findall(text))
            else:
                raise RuntimeError("custom-call targets could not be listed")
            # The structure by pickle: the types it names are this source's (the key holds its digest),
            # and the folder is the user's own, as trusted as the compiled programs read from it. A type
            # pickle cannot name (a class defined inside a function) makes this raise: jax.jit serves.
            out_tree = _dump_tree(out_trees[-1])
            # the native kernels it calls (their targets were registered while it was traced)
            native = sorted(set(_CUSTOM_CALL.findall(exp.mlir_module())) & set(_native())) if platform == "cpu" else []
            exported.append((exp, out_trees[-1]))
            return {"program": np.frombuffer(exp.serialize(), np.uint8), "tree": np.frombuffer(out_tree, np.uint8),
                    "native": np.frombuffer(" ".join(native).encode(), np.uint8)}

        try:
            arrays = cache.cached_arrays("program", key, build)
            if exported:
                exp, out_tree = exported[0]
                _count("misses")
            else:
                exp = export.deserialize(bytearray(arrays["program"].tobytes()))
                out_tree = pickle.loads(arrays["tree"].tobytes())
                # a stored program calling a native kernel: register its FFI target before the
                # program compiles or its executable is read from the compilation cache (building the
                # kernel where this cache folder has none yet); the other kernel is not built
                import importlib

                for target in arrays["native"].tobytes().decode().split():
                    if target not in _native():
                        raise RuntimeError(f"no jaxrt.accel module registers {target}")
                    if not importlib.import_module(f"jaxrt.accel.{_native()[target]}").available():
                        raise RuntimeError(f"the native kernel of {target} is not available")
                _count("hits")
        except Exception as e:  # noqa: BLE001 -- anything export cannot do runs through jax.jit
            if cfg.debug:
                import warnings

                warnings.warn(f"jaxrt: {self._name[:80]}: program not stored ({type(e).__name__}: {str(e)[:400]})",
                              RuntimeWarning, stacklevel=3)
            return None
        return _Stored(exp, out_tree)


class _Lowered:
    """What `_CachedJit.lower` returns for a stored program: `compile()` gives the program calls use,
    called with the original (unflattened) arguments; `out_info` the output's shapes and types."""

    def __init__(self, stored: _Stored, leaves, static: tuple[str, ...]):
        self._stored, self._leaves, self._static = stored, leaves, static

    @property
    def out_info(self):
        return self._stored.out_info()

    def compile(self):
        return _Compiled(self._stored, self._static, self._stored.executable(self._leaves))


class _Compiled:
    """A stored program's compiled executable taking the function's own arguments (static ones are
    accepted and ignored: they are part of the program); other attributes (`memory_analysis`,
    `cost_analysis`, ...) are the executable's."""

    def __init__(self, stored: _Stored, static: tuple[str, ...], executable):
        # the executable is held here too: `release` may drop the stored program's, not this one's
        self._stored, self._static, self._executable = stored, static, executable

    def __call__(self, *args, **kwargs):
        for k in self._static:
            kwargs.pop(k, None)
        leaves = jax.tree_util.tree_leaves((args, kwargs))
        return jax.tree_util.tree_unflatten(self._stored.out_tree, self._executable(*leaves))

    def __getattr__(self, name):
        return getattr(self._executable, name)


def cached_jit(fun: Callable | None = None, *, name: str | None = None,
               static_argnames: Sequence[str] = ()) -> Callable:
    """`jax.jit(fun, static_argnames=...)` whose traced program is stored in the on-disk cache.

    Static arguments must be passed by keyword. `name` (default: the function's module and
    qualified name) joins the key. Use it as a decorator or call it on a function.
    """
    if fun is None:
        return functools.partial(cached_jit, name=name, static_argnames=static_argnames)
    label = name or f"{fun.__module__}.{fun.__qualname__}"
    return _CachedJit(fun, label, tuple(static_argnames))
