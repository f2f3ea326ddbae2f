"""BVH traversal as a native CPU kernel: an XLA FFI custom call written in C++ (`jaxrt/native/traverse.cc`).

The pure-XLA traversal (`jaxrt.accel.traverse_xla.traverse`) runs ~100 small XLA:CPU kernels per
traversal step; Pallas, which solves the same problem on the GPU (`jaxrt.accel.traverse_pallas`), has no CPU
backend. This module is the CPU analogue: one C++ function traces each ray to the end with its
state in registers, over threads (chunks of consecutive rays: image tiles, coherent).

Results are the XLA path's: the same ray classes and links, the same slab box test (with
`FAR_SCALE`), the same watertight triangle test and tie rule (strict <, the earlier
triangle on exact ties), any-hit early exit. Edge signs are exact (via double, see the C++ file).
The float32 hit distance may differ from the XLA path's in the last ulp where XLA contracts a
multiply-add into an FMA (the C++ is compiled with -ffp-contract=off), so triangles at the same
distance to within an ulp may be chosen differently; `bvh.intersect` refines t of the chosen
triangle in double-float for both paths.

No build step at install: the first call of `available()` compiles the shipped source with the
system C++ compiler ($CXX, else `c++`) into <cache folder>/native (`jaxrt.cache.cache_dir()`), keyed
by a hash of the source, compiler, flags and jaxlib version, written to a temporary file and
renamed into place (two processes compiling at once both succeed), loads it with ctypes and
registers the FFI target once per process. Where there is no compiler or compilation fails,
`available()` warns once and returns False, and `bvh` uses the XLA loop.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import tempfile
import threading
import warnings
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
from jaxtyping import Array, Float

from jaxrt import _config
from jaxrt.accel.predicates import FAR_SCALE

TARGET = "jaxrt_bvh_traverse"
#: every FFI target this module registers (see `jaxrt.accel.traverse_embree.TARGETS`)
TARGETS = (TARGET,)
_SYMBOL = "JaxrtBvhTraverse"
# -ffp-contract=off: every float32 product is rounded before it is added, as in the XLA path
# (results must not depend on the compiler's FMA contraction). No -march=native: the cached
# library may be shared between machines (a home directory on a network file system).
FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-ffp-contract=off", "-w")
CHUNK = 128  # rays per work item handed to a thread
LANES = 8  # rays in flight per thread (1..32), stepped round-robin to overlap cache misses

_compiler: str | None = None  # overrides $CXX / "c++" (tests)
_lock = threading.Lock()
_state: dict = {}


def _source() -> bytes:
    return resources.files("jaxrt.accel").joinpath("native", "traverse.cc").read_bytes()


def _cache_dir() -> Path:
    # compiled kernels live beside the other caches but are not subject to their size bound or to
    # JAXRT_CACHE=off: without them the CPU falls back to the much slower XLA loop
    return _config.config().cache_dir / "native"


def _compile(src: bytes, compiler: str) -> Path:
    """Path of the compiled library (compiled now unless cached). Raises OSError/CalledProcessError."""
    return compile_library("traverse", src, compiler)


def compile_library(stem: str, src: bytes, compiler: str, libs: tuple[str, ...] = (),
                    flags: tuple[str, ...] = ()) -> Path:
    """Path of the FFI library compiled from C++ `src` with `FLAGS` and `flags` (and linked with `libs`,
    e.g. ("-lembree3",)), compiled now unless cached under <cache folder>/native/<stem>-<key>.so, key a
    hash of the source, compiler, flags, libraries and jaxlib version. Raises OSError/CalledProcessError."""
    key = hashlib.sha256(b"\0".join([src, compiler.encode(), " ".join(FLAGS + flags + libs).encode(),
                                     jaxlib.__version__.encode(), os.uname().machine.encode()])).hexdigest()[:20]
    out = _cache_dir() / f"{stem}-{key}.so"
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="jaxrt-build-") as tmp:
        cc = Path(tmp) / f"{stem}.cc"
        cc.write_bytes(src)
        fd, part = tempfile.mkstemp(prefix=out.stem + ".", suffix=".so.part", dir=out.parent)
        os.close(fd)
        try:
            subprocess.run([compiler, *FLAGS, *flags, "-I", jax.ffi.include_dir(), str(cc), "-o", part, *libs],
                           check=True, capture_output=True, text=True, timeout=300)
            os.replace(part, out)  # atomic: a concurrent compile of the same key renames the same bytes
        finally:
            if os.path.exists(part):
                os.unlink(part)
    return out


def load_library(stem: str, src: bytes, compiler: str, target: str, symbol: str, state: dict,
                 libs: tuple[str, ...] = (), flags: tuple[str, ...] = ()) -> None:
    """Compile (unless cached, `compile_library`) and load the FFI library, registering its `symbol` as
    the CPU FFI target `target` once per process: `state["lib"]` keeps the registered library loaded,
    and a later load (after a test reset) reuses that registration. Raises on any failure."""
    lib = ctypes.CDLL(str(compile_library(stem, src, compiler, libs, flags)))
    if "lib" not in state:
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
        state["lib"] = lib


def _load() -> bool:
    compiler = _compiler or os.environ.get("CXX") or "c++"
    try:
        load_library("traverse", _source(), compiler, TARGET, _SYMBOL, _state)
    except Exception as e:  # noqa: BLE001 -- any failure means: use the XLA loop
        detail = getattr(e, "stderr", None) or str(e)
        warnings.warn(f"jaxrt: the native CPU traversal kernel is unavailable (compiler {compiler!r}: "
                      f"{detail.strip()[-500:]}); using the slower XLA traversal loop", RuntimeWarning, stacklevel=3)
        return False
    return True


def available() -> bool:
    """Whether the native kernel is compiled, loaded and registered (compiling on first call)."""
    with _lock:
        if "ok" not in _state:
            _state["ok"] = _load()
        return _state["ok"]


def _reset_for_tests() -> None:
    """Forget the load result so the next `available()` tries again (the FFI target stays registered)."""
    with _lock:
        _state.pop("ok", None)


def traverse(arrays: dict, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"], tmin: Float[Array, " N"],
             tmax: Float[Array, " N"], *, any_hit: bool, refine: bool = False, threads: int = 0,
             lanes: int = LANES):
    """Trace N rays on the CPU; returns (found, t, tri_index_in_leaf_order, u, v), each (N,), as
    `traverse_xla.traverse` (without the step counts).

    arrays: node_box (nn,6) float32, node_leaf (nn,2) int32, links (6nn,2) int32, triangles (F,9)
    float32 (see bvh.BVH; leaves of any size); origins, directions (N,3) float32; tmin, tmax (N,)
    float32; t is in units of |direction|. refine: t of each hit recomputed in double from its
    triangle's plane (what `traverse_xla.refine_t` does in double-float; `jaxrt.accel.intersect` asks for
    it). threads: worker threads (0: XLA's intra-op thread pool);
    lanes: rays in flight per thread, 1..32 (both only affect speed). Lowers for the CPU only.
    Under vmap the kernel runs once per batch element. Raises RuntimeError where the kernel is not
    `available()` (`bvh` checks first and uses the XLA loop).
    """
    if not 1 <= lanes <= 32 or threads < 0:
        raise ValueError(f"traverse_cpu.traverse: lanes must be in 1..32 and threads >= 0; got {lanes}, {threads}")
    if not available():
        raise RuntimeError("jaxrt.accel.traverse_cpu: the native kernel could not be built (see the warning)")
    n = origins.shape[0]
    f32 = jax.ShapeDtypeStruct((n,), jnp.float32)
    i32 = jax.ShapeDtypeStruct((n,), jnp.int32)
    call = jax.ffi.ffi_call(TARGET, (f32, i32, f32, f32), vmap_method="sequential")
    t, best, u, v = call(jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32),
                         jnp.asarray(tmin, jnp.float32), jnp.asarray(tmax, jnp.float32),
                         arrays["node_box"], arrays["node_leaf"], arrays["links"], arrays["triangles"],
                         any_hit=bool(any_hit), refine=bool(refine), far_scale=np.float32(FAR_SCALE),
                         chunk=np.int64(CHUNK), threads=np.int64(threads), lanes=np.int64(lanes))
    return best >= 0, t, best, u, v
