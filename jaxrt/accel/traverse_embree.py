"""Ray queries through Embree 3 on the CPU: an XLA FFI custom call written in C++ (`native/embree.cc`).

Embree (Wald et al. 2014) builds a wide BVH of its own and traverses packets of rays with the SIMD
instructions of the CPU it runs on (chosen at run time); where the library is installed it is the
CPU traversal `jaxrt.accel.bvh` uses by default (`JAXRT_TRAVERSAL=auto`; `embree` asks for it, `cpu`
for jaxrt's own single-ray kernel, `jaxrt.accel.traverse_cpu`). BENCHMARKS.md ("jaxrt beside Mitsuba
3") has the measurements.

Results keep `traverse_cpu.traverse`'s contract: the triangle index in leaf order (Embree's scene is
built from the BVH's own triangle table, so its primID is that index), barycentrics of v1 and v2,
t in units of |direction| and, with `refine`, t of the chosen triangle recomputed in double; with
`points`, also each hit's point and unit geometric normal, computed in double from the triangle the
kernel has at hand (`bvh.intersect_points`). Embree's
triangle test rounds differently from the native kernel's, so t, u, v agree to a few ulps and of two
triangles at the same distance to within an ulp either may be chosen, and the ends of [tmin, tmax] are
decided with Embree's float32 t; its robust mode keeps the test watertight at edges, not exactly at
vertices (a ray through a vertex exactly slips through about 1 % of the time; `native/embree.cc`). Embree's tree is built on the first call that sees a triangle table and kept in the
process (a few tables, keyed by a hash of the table's bytes that every call computes): a frame never
rebuilds it, a changed mesh never reuses a stale one. A program that traces one table many times
(the path tracer: two calls per bounce and chunk) hashes it once instead: `table_key` makes the key
from the table inside the program and `traverse(key=...)` passes it beside the same table (the key
cannot go stale as long as both are made from the same traced value). A Whitted level on the CPU
makes one call for its rays' closest hits and their shadow rays to the point lights (`direct`: the
kernel makes each packet's shadow segments from the hits it has just found, with the float32
operations of the trace loop, and traces them at once). Instanced scenes (`jaxrt.accel.two_level`) keep
their own traversal.

No build step at install: `available()` compiles the shipped source as `traverse_cpu` does (cached,
keyed, atomic) and links it with -lembree3 (Debian: `apt-get install libembree-dev`). Where no Embree
library is found it returns False without a word and `bvh` uses the native kernel; where one is
found but compiling against it fails it warns once; `impl="embree"` (JAXRT_TRAVERSAL=embree) without
Embree warns once too.
"""

from __future__ import annotations

import ctypes.util
import os
import threading
import warnings
from importlib import resources

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt32

from jaxrt.accel import traverse_cpu

TARGET = "jaxrt_embree_trace"
_SYMBOL = "JaxrtEmbreeTrace"
# the keyed calls (`table_key`, `traverse(key=...)`): the same library, two more targets
KEY_TARGET, _KEY_SYMBOL = "jaxrt_embree_table_key", "JaxrtEmbreeTableKey"
KEYED_TARGET, _KEYED_SYMBOL = "jaxrt_embree_trace_keyed", "JaxrtEmbreeTraceKeyed"
# closest hits and their shadow rays to point lights in one call (`direct`)
DIRECT_TARGET, _DIRECT_SYMBOL = "jaxrt_embree_direct", "JaxrtEmbreeDirect"
#: every FFI target this module registers (`jaxrt.programs` registers them before compiling a stored
#: program that calls one)
TARGETS = (TARGET, KEY_TARGET, KEYED_TARGET, DIRECT_TARGET)
LIBS = ("-lembree3",)
# No errno from sqrt and no floating-point traps, so that the loops finishing the hits in double
# (`Finish` in embree.cc) have no branches and vectorise; neither changes a result.
FLAGS = ("-fno-math-errno", "-fno-trapping-math")
CHUNK = 256  # rays per work item handed to a thread (16 packets of 16)
# Embree's RTCBuildQuality: 0 low, 1 medium (its default: binned SAH), 2 high (spatial splits). The
# tree is built once per mesh and traced every frame.
QUALITY = 1

_compiler: str | None = None  # overrides $CXX / "c++" (tests)
_library: str | None = None  # overrides the library lookup (tests): a name that is not found
_lock = threading.Lock()
_state: dict = {}


def _source() -> bytes:
    return resources.files("jaxrt.accel").joinpath("native", "embree.cc").read_bytes()


def _load() -> bool:
    _state["missing"] = ctypes.util.find_library(_library or "embree3") is None
    if _state["missing"]:
        return False  # Embree is not installed: the native kernel, silently (unless asked for by name)
    compiler = _compiler or os.environ.get("CXX") or "c++"
    try:
        traverse_cpu.load_library("embree", _source(), compiler, TARGET, _SYMBOL, _state, LIBS, FLAGS)
        if not _state.get("keyed"):
            for target, symbol in ((KEY_TARGET, _KEY_SYMBOL), (KEYED_TARGET, _KEYED_SYMBOL),
                                   (DIRECT_TARGET, _DIRECT_SYMBOL)):
                jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(_state["lib"], symbol)), platform="cpu")
            _state["keyed"] = True
    except Exception as e:  # noqa: BLE001 -- any failure means: use the native kernel
        detail = getattr(e, "stderr", None) or str(e)
        warnings.warn(f"jaxrt: Embree is installed but the Embree traversal could not be built (compiler "
                      f"{compiler!r}: {detail.strip()[-500:]}); using jaxrt's own CPU kernel", RuntimeWarning,
                      stacklevel=3)
        return False
    return True


def available() -> bool:
    """Whether the Embree kernel is compiled, loaded and registered (compiling on first call)."""
    with _lock:
        if "ok" not in _state:
            _state["ok"] = _load()
        return _state["ok"]


def note_missing() -> None:
    """Warn once per process that Embree was asked for (JAXRT_TRAVERSAL=embree) but is not installed."""
    with _lock:
        if _state.get("noted") or not _state.get("missing"):
            return  # said already, or installed but not built (`available` warned)
        _state["noted"] = True
    warnings.warn("jaxrt: JAXRT_TRAVERSAL=embree, but no Embree 3 library was found (Debian: apt-get install "
                  "libembree-dev); using jaxrt's own CPU kernel", RuntimeWarning, stacklevel=4)


def _reset_for_tests() -> None:
    """Forget the load result so the next `available()` tries again (the FFI target stays registered)."""
    with _lock:
        _state.pop("ok", None)
        _state.pop("noted", None)


def traverse(triangles: Float[Array, "F 9"], origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
             tmin: Float[Array, " N"], tmax: Float[Array, " N"], *, any_hit: bool, refine: bool = False,
             coherent: str = "auto", packet: int = 16, threads: int = 0, points: bool = False,
             key: UInt32[Array, "2"] | None = None):
    """Trace N rays through Embree; returns (found, t, tri_index_in_leaf_order, u, v), each (N,), as
    `traverse_cpu.traverse`, and with `points` (closest hit only) also (p, ng), each (N, 3).

    triangles: the BVH's (F,9) float32 leaf-order table; origins, directions (N,3) float32; tmin,
    tmax (N,) float32. Rays with a NaN, an infinite origin or direction, a zero direction or
    tmin > tmax miss. refine: t of each hit in double (as `traverse_cpu`). coherent: Embree's mode
    for a packet, "yes" (traversed as one: camera rays, shadow rays to one light), "no" (split into
    single rays as they diverge: bounced rays) or "auto" (per packet: "yes" where its rays' directions
    share an octant); packet: 16 (packets of 16 rays) or 1 (one ray at a time); threads: worker
    threads (0: XLA's intra-op thread pool); these three only affect speed. Lowers for the CPU only; under vmap it runs once per batch
    element. key: `table_key(triangles)` of this same table, made in the same program (then the call
    does not hash the table; see the module docstring), or None. Raises RuntimeError where the kernel
    is not `available()`.

    points: also the hit point p = v0 + u·e1 + v·e2 and the unit geometric normal e1 × e2 / |e1 × e2|
    of each hit (e1 = v1 − v0, e2 = v2 − v0, the winding's normal), computed in double from the
    float32 corners and the double barycentrics of the refined hit and rounded once (the kernel has
    the triangle at hand; the caller then gathers no corners); zeros on a miss.
    """
    modes = {"no": 0, "yes": 1, "auto": 2}
    if packet not in (1, 16) or threads < 0 or coherent not in modes or (points and any_hit):
        raise ValueError(f"traverse_embree.traverse: packet must be 1 or 16, threads >= 0 and coherent one of "
                         f"{tuple(modes)}, and points only with closest hits; got {packet}, {threads}, "
                         f"{coherent!r}, points={points}, any_hit={any_hit}")
    if not available():
        raise RuntimeError("jaxrt.accel.traverse_embree: the Embree kernel is not available")
    n = origins.shape[0]
    f32 = jax.ShapeDtypeStruct((n,), jnp.float32)
    i32 = jax.ShapeDtypeStruct((n,), jnp.int32)
    # p and ng are empty (0, 3) unless asked for: the kernel writes them only then
    f3 = jax.ShapeDtypeStruct((n if points else 0, 3), jnp.float32)
    call = jax.ffi.ffi_call(TARGET if key is None else KEYED_TARGET, (f32, i32, f32, f32, f3, f3),
                            vmap_method="sequential")
    keys = () if key is None else (key,)
    t, best, u, v, p, ng = call(jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32),
                                jnp.asarray(tmin, jnp.float32), jnp.asarray(tmax, jnp.float32), triangles, *keys,
                                any_hit=bool(any_hit), refine=bool(refine), coherent=np.int64(modes[coherent]),
                                packet=np.int64(packet), quality=np.int64(QUALITY), chunk=np.int64(CHUNK),
                                threads=np.int64(threads))
    if points:
        return best >= 0, t, best, u, v, p, ng
    return best >= 0, t, best, u, v


def table_key(triangles: Float[Array, "F 9"]) -> UInt32[Array, "2"]:
    """The 64-bit content hash of a (F, 9) float32 triangle table as two uint32 words (low first),
    computed by the kernel in the running program, which also builds (or finds) Embree's scene of the
    table. Pass it to `traverse(key=...)` beside the same table: those calls then skip hashing the
    table. Raises RuntimeError where the kernel is not `available()`."""
    if not available():
        raise RuntimeError("jaxrt.accel.traverse_embree: the Embree kernel is not available")
    call = jax.ffi.ffi_call(KEY_TARGET, jax.ShapeDtypeStruct((2,), jnp.uint32), vmap_method="sequential")
    return call(triangles, quality=np.int64(QUALITY))


def direct(triangles: Float[Array, "F 9"], origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
           tmin: Float[Array, " N"], tmax: Float[Array, " N"], lights: Float[Array, "L 3"], *,
           coherent: str = "auto", threads: int = 0):
    """Closest hits and, in the same call, each hit's shadow rays to L point lights: returns
    (found, t, best, u, v, p, ng), as `traverse(points=True, refine=True)`, and occ (N, L) bool.

    The shadow ray of a hit and light is the segment the Whitted trace loop tests
    (`jaxrt.integrators.whitted.shadow_segments`), made in the kernel with the same float32
    operations from the hit's p and ng, the ray's direction and the light's position, and traced from
    the light's end (`bvh.occluded(from_end=True)`). occ is True where that segment is blocked, False
    on misses and where the light is behind the hit's geometric normal (not lit; the caller decides
    lit for itself and ANDs). The kernel writes the shadow rays of each packet of 16 hits right after
    tracing them, so no shadow-ray arrays are made and the table is hashed once. Lowers for the CPU
    only; raises RuntimeError where the kernel is not `available()`.
    """
    modes = {"no": 0, "yes": 1, "auto": 2}
    if threads < 0 or coherent not in modes:
        raise ValueError(f"traverse_embree.direct: threads must be >= 0 and coherent one of {tuple(modes)}; "
                         f"got {threads}, {coherent!r}")
    if not available():
        raise RuntimeError("jaxrt.accel.traverse_embree: the Embree kernel is not available")
    n = origins.shape[0]
    nl = lights.shape[0]
    f32 = jax.ShapeDtypeStruct((n,), jnp.float32)
    i32 = jax.ShapeDtypeStruct((n,), jnp.int32)
    f3 = jax.ShapeDtypeStruct((n, 3), jnp.float32)
    call = jax.ffi.ffi_call(DIRECT_TARGET, (f32, i32, f32, f32, f3, f3, jax.ShapeDtypeStruct((n, nl), jnp.bool_)),
                            vmap_method="sequential")
    t, best, u, v, p, ng, occ = call(
        jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32), jnp.asarray(tmin, jnp.float32),
        jnp.asarray(tmax, jnp.float32), triangles, jnp.asarray(lights, jnp.float32).reshape(nl, 3),
        coherent=np.int64(modes[coherent]), quality=np.int64(QUALITY), chunk=np.int64(CHUNK),
        threads=np.int64(threads))
    return best >= 0, t, best, u, v, p, ng, occ
