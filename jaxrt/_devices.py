"""Several devices, and several hosts, for one job: the device choice, the mesh, the sharded tile
programs of renders and progressive passes, batches of fits split over devices, and joining hosts.

`jaxrt.render_tiles` renders an image as independent tiles (`camera.Window`: a rectangle of pixels
and a run of their samples, its origin traced, its extents static). On a mesh of D devices the same
tile program runs under `shard_map`: the scene pytree is replicated (every device holds the BVH,
materials, textures and lights), each call gives every device the origin of its own tile, and each
device runs its own traversal loop on its tile. Nothing in the body communicates: there is no
collective, so no device waits for another inside a loop, which is what auto-sharding a
`while_loop` over a sharded ray batch would do (one device's early exit is held back by the
longest-running device at every iteration, with an all-reduce of the loop condition in between).

Equality with one device
------------------------
A tile's random numbers and per-ray work do not depend on the device that runs it, so the sharded
render computes the same arithmetic as the one-device tiled render. It is still a different XLA
module: a program partitioned over D > 1 devices goes through the SPMD pipeline, after which XLA
simplifies and fuses it differently (in the optimized XLA:CPU modules, for instance, a division by
a square root stays a division where the one-device module turns it into a product with rsqrt,
and a few adds and multiplies are fused differently; `jax.pmap`, itself a `shard_map` now, gives
the same). So against one device the pixels differ by a few ulps per ray, as tiled and untiled
renders do (`jaxrt.render_tiles` gives the measurements), and that remains with the XLA flags
that make tiled renders exact (no FMA contraction, no YNNPACK fusions). The partitioned program
does not depend on D, so renders on any D ≥ 2 devices are equal to each other bit for bit
wherever the tile shape is the same, which it is up to MIN_TILES / TILES_PER_DEVICE = 8 devices
unless the memory budget shrinks the tiles (on a CPU the budget is split between the devices).
A mesh of one device compiles the one-device module and equals `integrators.tile` bit for bit.
Progressive path-tracing passes (`jaxrt.render_tiles.accumulate`) are the same tiles with the pass
index a traced, replicated scalar: on one host a first pass runs them as one-device programs, one
dispatched to each device, and later passes through `queue_program` (below); across hosts through
`pass_program`.

Cost-based schedule of progressive passes
-----------------------------------------
A call of `program` or `pass_program` lasts as long as its slowest tile, so tiles of unequal cost
(glass, sky) leave devices idle however they are interleaved. The passes of a progressive render
trace the same tiles again and again, so the first passes measure each tile's device time: they run
each device's interleaved tiles as a one-device program dispatched to that device
(`tile_pass_program`, `views` of the replicated scene, `timed`: a device gets its next tile when
its previous output is ready, which the host notes; a `shard_map` call's outputs become ready
together on XLA:CPU, so they cannot time one device; `jaxrt.render_tiles.TIMED_PASSES` passes, each
tile's least time kept). The later passes give each device a list of
tiles chosen by longest processing time first (`lpt`; Graham 1969: the largest device load is at
most 4/3 − 1/(3D) of the optimum) and run each device's whole list in one call (`queue_program`: a
while loop over the device's own tiles, so a device that finishes early waits only at the end of
the pass, not after every tile). Which device renders a tile does not change its arithmetic: the
loop's body is the same program on every device and for every assignment, so any two schedules give
the same pixels bit for bit; against one device, and against `pass_program`, these are other
compiled modules, within the few ulps per ray described above. Several hosts keep the interleaved
tiles (a device's time is only seen by its own process).

Fits
----
A batch of independent least-squares problems (the starts of one fit, one model's fits to several
targets, the study's materials) is split by rows over the devices (`batched`): each device runs the
one-device, vmapped program on its rows, with its own while loops, and nothing is exchanged until
the rows are gathered. This is `shard_map`'s model without `shard_map`, which optimistix's solvers
do not survive in this JAX (see `batched`). One fit's residual nodes can be split the other way
round (`fitting.compact.split_shader`): only the shading runs inside a `shard_map`, ending in a
`psum` of the partial images, and the solver runs outside it on the replicated residuals,
differentiating through the collective.

Photon passes
-------------
A pass of stochastic progressive photon mapping needs every visible point to meet every photon, so
it is split by photons, not by tiles (`sppm_program`): the scene and the per-pixel statistics are
replicated, every device computes the pass's visible points from the pass's keys (the same on every
device), traces its share of the photons (photon i keeps the random numbers of photon i of the
one-device pass; the count is padded to a multiple of D with photons of zero power), builds its own
hash grid and gathers at every visible point; one `psum` adds the per-pixel photon counts and
fluxes, and every device applies the same progressive update. Against one device: the same photon
counts and the fluxes up to the summation order, as long as no grid bucket of the one-device pass
is subsampled (more than `integrators.sppm.CELL_PHOTONS` deposits; each device then subsamples its
own, another unbiased estimate).

Several hosts
-------------
With JAXRT_COORDINATOR, JAXRT_PROCESS_COUNT and JAXRT_PROCESS_ID (`jaxrt._config`), `initialize`
joins the processes (one per host) through `jax.distributed`; `jax.devices()` then lists every
host's devices and the code above runs unchanged: host arrays are placed with
`jax.make_array_from_callback` (each process its own devices' rows, `put_rows`, `replicate`),
results are gathered to every process (`gather`, and `batched` gathers its rows with
`process_allgather`), and `jaxrt.fsutil` lets process 0 alone write files.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Int

from jaxrt import _config, integrators
from jaxrt.camera import Window
from jaxrt.errors import InputError

__all__ = ["AXIS", "MIN_TILES", "TILES_PER_DEVICE", "batched", "concurrent", "gather", "initialize", "local", "lpt",
           "makespan", "mesh", "pad_rows", "padded", "parse", "pass_program", "program", "put_each", "put_rows",
           "queue_arrays", "queue_program", "replicate", "round_arrays", "select", "shard_map", "sharded",
           "solver_devices", "sppm_program", "tile_pass_program", "timed", "to_host", "views"]

AXIS = "devices"
# A render on several devices is split into at least max(MIN_TILES, TILES_PER_DEVICE·D) tiles, so
# that tiles of unequal cost (glass, sky) even out within each device's share; the first term keeps
# the tile shape (and so the compiled arithmetic) the same for every device count up to
# MIN_TILES / TILES_PER_DEVICE.
MIN_TILES = 32
TILES_PER_DEVICE = 4

try:  # jax >= 0.7
    _shard_map = jax.shard_map
    _UNCHECKED = {"check_vma": False}
except AttributeError:  # pragma: no cover - older JAX
    from jax.experimental.shard_map import shard_map as _shard_map

    _UNCHECKED = {"check_rep": False}


#: Arrays at least this large (bytes) on a GPU go to the host through page-locked memory (`to_host`).
PINNED_COPY_BYTES = 1 << 20


def to_host(x: jax.Array, pinned: bool | None = None) -> np.ndarray:
    """A device array as a NumPy array. On a GPU, arrays of at least `PINNED_COPY_BYTES` are first moved
    to page-locked host memory (memory kind "pinned_host", a DMA at the link's speed) and read from
    there: a 512² RGB float32 image took 0.34-0.42 ms that way against 0.9-1.3 ms for a direct copy
    into pageable memory (one NVIDIA H200, `benchmarks/pass_parts.py`). On a CPU the array is already
    in host memory (`np.asarray` does not copy). pinned: force (True) or skip (False) the pinned route."""
    if pinned is None:
        devs = x.devices() if isinstance(x, jax.Array) else ()
        pinned = (len(devs) == 1 and next(iter(devs)).platform == "gpu" and x.nbytes >= PINNED_COPY_BYTES)
    if not pinned:
        return np.asarray(x)
    dev = next(iter(x.devices()))
    return np.asarray(jax.device_put(x, jax.sharding.SingleDeviceSharding(dev, memory_kind="pinned_host")))


def shard_map(f, *, mesh: Mesh, in_specs, out_specs):
    """`jax.shard_map` of this JAX (the experimental one of older versions), without the replication
    check (bodies here either use no collective or end in a `psum`)."""
    return _shard_map(f, mesh=mesh, in_specs=in_specs, out_specs=out_specs, **_UNCHECKED)


def _what(label: str, value: Any) -> str:
    # "--devices 9" for a flag, "devices=9" for an argument
    return f"{label}{value!r}" if label.endswith("=") else f"{label} {value}"


def parse(text: str, label: str = "--devices") -> int | None:
    """A `--devices` value without asking JAX: "all" -> None, else a positive integer."""
    t = str(text).strip().lower()
    if t == "all":
        return None
    try:
        n = int(t)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(f"{_what(label, text)}: must be 'all' or a number of devices, 1 or more")
    return n


def _every(devices: Any) -> bool:
    # the default choice of `select`: None or "all" (any case, surrounding spaces)
    return devices is None or (isinstance(devices, str) and devices.strip().lower() == "all")


def select(devices: Any = None, label: str = "devices=") -> tuple[jax.Device, ...]:
    """The devices of a render: None or "all": every device of the default backend (`jax.devices()`);
    an int N: the first N of them; a sequence of those devices: these, in this order.

    Raises:
        InputError: one line naming `label` (the argument or the flag) and what is allowed.
    """
    avail = tuple(jax.devices())
    n = len(avail)
    allowed = (f"'all' or a number from 1 to {n} (this host has {n} {avail[0].platform} "
               f"device{'s' if n > 1 else ''})")
    if _every(devices):
        return avail
    if isinstance(devices, str):
        devices = parse(devices, label)
        return avail if devices is None else select(devices, label)
    if isinstance(devices, bool) or not isinstance(devices, (int, np.integer, Sequence)):
        raise InputError(f"{_what(label, devices)}: must be {allowed}, or a list of jax.devices()")
    if isinstance(devices, (int, np.integer)):
        if not 1 <= int(devices) <= n:
            raise InputError(f"{_what(label, devices)}: must be {allowed}")
        return avail[:int(devices)]
    chosen = tuple(devices)
    if not chosen or any(d not in avail for d in chosen) or len(set(chosen)) != len(chosen):
        raise InputError(f"{_what(label, list(devices))}: a list of devices must name distinct devices of "
                         f"jax.devices() ({', '.join(str(d) for d in avail)}), at least one")
    return chosen


def concurrent(devices: Sequence[jax.Device]) -> int:
    """How many of `devices` may run a solver's program at the same time in this process: all of
    them on a GPU; on a CPU, one fewer than the cores (at least one).

    Why: XLA:CPU runs each device's program on a worker of one intra-op thread pool with as many
    threads as cores, and some library kernels a solver's program calls fan their work out onto
    that same pool and block until it is done (jaxlib's LAPACK kernels: a batch of QR
    factorisations, `lapack_sgeqrf_ffi`, waits on the batch's tasks). With as many programs as
    threads each inside such a kernel, no thread is left to run the tasks they wait for: a 256²
    fit with its starts on 2 devices of a 2-core CPU stopped there, its threads idle (seen with
    gdb: both pool threads in `jax::ParallelBatchMap` waiting, the pool's queue holding their tasks).
    One free thread is enough for progress. Renders do not need this: their only library calls
    are jaxrt's traversal kernels, whose calling thread does the work itself and waits only for
    pieces other threads have started (`accel/native`)."""
    devices = list(devices)
    if devices and devices[0].platform == "cpu":
        return max(1, min(len(devices), _config.cores() - 1))
    return len(devices)


def solver_devices(devices: Any = None, label: str = "devices=") -> tuple[jax.Device, ...]:
    """`select` for fits and studies: the same, except that the default (None or "all") on a CPU
    is the first `concurrent` devices, so a command that sees one CPU device per core
    (`jaxrt._config.command_defaults`) does not split a fit it would run more slowly split (each
    device compiles the solver once, and at most `concurrent` of them run at once). An explicit
    number or list is kept."""
    devs = select(devices, label)
    return devs[:concurrent(devs)] if _every(devices) else devs


def initialize(environ=None) -> bool:
    """Join a run over several hosts when JAXRT_COORDINATOR is set (`jaxrt._config`): one process per
    host calls `jax.distributed.initialize` with the coordinator's host:port, the process count and
    this process's id, after which `jax.devices()` lists every host's devices and the same code
    splits its work over all of them (each process passes the same arguments; the results are
    gathered to every process, and only process 0 writes files, `jaxrt.fsutil`). Must run before
    anything else asks JAX for its devices; the CLI calls it first (in Python: `jaxrt.join_hosts`).
    Every process should drive the same number of devices (results are gathered with
    `process_allgather`, which needs equal shares). Returns whether it joined a run over several
    hosts; a second call is a no-op."""
    cfg = _config.config(environ)
    if cfg.coordinator is None:
        return False
    if not jax.distributed.is_initialized():
        jax.distributed.initialize(coordinator_address=cfg.coordinator, num_processes=cfg.process_count,
                                   process_id=cfg.process_id)
    return True


def local(devices: Sequence[jax.Device]) -> list[jax.Device]:
    """The devices of `devices` that this process drives (all of them on one host)."""
    me = jax.process_index()
    return [d for d in devices if d.process_index == me]


def put_rows(x: np.ndarray, devices: Sequence[jax.Device]) -> jax.Array:
    """A host array (the same on every process) split along its leading axis over a mesh of
    `devices`, each process placing only its own devices' rows (works across hosts)."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, NamedSharding(mesh(devices), PartitionSpec(AXIS)), lambda i: x[i])


def gather(tree):
    """Every leaf of `tree` (arrays split over a mesh, maybe over several hosts) as a whole numpy
    array on this process: a plain transfer on one host, `process_allgather` across hosts."""
    if jax.process_count() == 1:
        return jax.tree.map(np.asarray, tree)
    from jax.experimental import multihost_utils

    return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def sharded(devices: Sequence[jax.Device]) -> bool:
    """Whether a render on `devices` takes the sharded path: several devices, or one that is not the
    default device (the one-device renderer runs on the default device)."""
    return len(devices) > 1 or devices[0] != jax.devices()[0]


def mesh(devices: Sequence[jax.Device]) -> Mesh:
    """A one-axis mesh (`AXIS`) over `devices`."""
    return Mesh(np.array(list(devices), dtype=object), (AXIS,))


def replicate(tree, devices: Sequence[jax.Device]):
    """`tree` (a scene) with every array on every device of `devices` (across hosts, each process
    places its own devices' copies of its own, equal, values)."""
    sharding = NamedSharding(mesh(devices), PartitionSpec())
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)
    return jax.tree.map(lambda x: jax.make_array_from_callback(np.shape(x), sharding, lambda i: np.asarray(x)[i])
                        if isinstance(x, (jax.Array, np.ndarray)) else x, tree)


def _device_tile(scene, origin, samples, *, shape, aovs: bool):
    # one device's share of a call: its tile, its own traversal loop; the leading axis of length one
    # is the device axis that out_specs concatenates
    th, tw, sb = shape
    o, s = jax.lax.squeeze(origin, [0]), jax.lax.squeeze(samples, [0])
    window = Window(o[0], o[1], s[0], s[1], th, tw, sb)
    out = integrators.REGISTRY[scene.settings.integrator][0](scene, aovs=aovs, window=window)
    return jax.tree.map(lambda x: jax.lax.expand_dims(x, [0]), out)


def _device_pass(scene, origin, samples, pass_index, *, shape):
    # one device's tile of progressive path-tracing pass `pass_index` (jittered, as
    # `integrators.path.accumulate`): the pass's random stream, the tile's pixels and samples
    th, tw, sb = shape
    o, s = jax.lax.squeeze(origin, [0]), jax.lax.squeeze(samples, [0])
    window = Window(o[0], o[1], s[0], s[1], th, tw, sb)
    out = integrators.path.render(scene, pass_index, jitter=True, window=window)
    return jax.lax.expand_dims(out, [0])


@functools.lru_cache(maxsize=32)
def pass_program(devices: tuple[jax.Device, ...], shape: tuple[int, int, int]):
    """`program` for one pass of progressive path tracing: ``f(scene, origins, samples, pass_index)``,
    the pass index a replicated int32 scalar (traced: one compilation for every pass); returns each
    device's tile of that pass, (D, th, tw, 3), Σ over the tile's samples / spp."""
    m = mesh(devices)
    rows, rep = PartitionSpec(AXIS), PartitionSpec()
    body = functools.partial(_device_pass, shape=shape)
    smap = _shard_map(body, mesh=m, in_specs=(rep, rows, rows, rep), out_specs=rows, **_UNCHECKED)
    r, split = NamedSharding(m, rep), NamedSharding(m, rows)
    return jax.jit(smap, in_shardings=(r, split, split, r), out_shardings=split)


def _device_sppm(scene, state, passes, *, count: int):
    # one device's share of `passes` SPPM passes (a loop in the one call, as `integrators.sppm.steps`):
    # the same visible points everywhere, its own photons and grid, M and Φ summed over the mesh (the
    # one collective), the same update on every device
    sources = integrators.sppm.photon_sources(scene)  # once, outside the loop
    return jax.lax.fori_loop(0, passes, lambda i, st: integrators.sppm.pass_share(scene, st, AXIS, count, sources),
                             state)


@functools.lru_cache(maxsize=32)
def sppm_program(devices: tuple[jax.Device, ...]):
    """Passes of stochastic progressive photon mapping over a mesh of `devices`: ``f(scene, state,
    count)`` -> the `integrators.sppm.SPPMState` after `count` passes (an int32 scalar,
    `integrators.sppm.pass_count`, traced), scene and state replicated
    (`replicate`); each device traces ceil(n/D) of the pass's n photons (the last padded with photons
    of zero power), gathers from its own hash grid at every visible point, and a `psum` adds the
    per-pixel photon counts and fluxes before the progressive update (`integrators.sppm.pass_share`).
    The pass index is the state's and the count traced: one compilation for every pass and count."""
    m = mesh(devices)
    rep = PartitionSpec()
    body = functools.partial(_device_sppm, count=len(devices))
    smap = _shard_map(body, mesh=m, in_specs=(rep, rep, rep), out_specs=rep, **_UNCHECKED)
    r = NamedSharding(m, rep)
    return jax.jit(smap, in_shardings=(r, r, r), out_shardings=r)


@functools.lru_cache(maxsize=32)
def program(devices: tuple[jax.Device, ...], shape: tuple[int, int, int], aovs: bool = False):
    """The compiled-on-first-call tile program of a mesh: ``f(scene, origins, samples)`` with the
    scene replicated (`replicate`), origins (D, 2) int32 (row, column) and samples (D, 2) int32
    (first sample, count), one row per device; returns each device's tile, (D, th, tw, 3) (and with
    `aovs` the AOV dict, each (D, th, tw, ...)), sharded over the devices.

    One function object per (devices, tile shape, aovs), so `jax.jit` compiles it once per render
    plan. (`jaxrt.programs.cached_jit` does not store programs on several devices; this one is
    traced in each process.)
    """
    m = mesh(devices)
    rows = PartitionSpec(AXIS)
    body = functools.partial(_device_tile, shape=shape, aovs=aovs)
    smap = _shard_map(body, mesh=m, in_specs=(PartitionSpec(), rows, rows), out_specs=rows, **_UNCHECKED)
    rep, split = NamedSharding(m, PartitionSpec()), NamedSharding(m, rows)
    return jax.jit(smap, in_shardings=(rep, split, split), out_shardings=split)


@functools.lru_cache(maxsize=32)
def queue_program(devices: tuple[jax.Device, ...], shape: tuple[int, int, int], k: int):
    """One progressive path-tracing pass over a list of up to `k` tiles per device, in one call:
    ``f(scene, origins, samples, counts, pass_index)`` with origins and samples (D, k, 2) int32 (each
    device's tiles, `queue_arrays`), counts (D,) int32 (how many of its k rows a device renders) and
    the pass index a replicated scalar; returns (D, k, th, tw, 3), row j of device d its j-th tile
    (rows past its count are zeros). Each device loops over its own tiles (`lax.while_loop`, its own
    trip count), with no collective, so devices with shorter lists are not held back."""
    m = mesh(devices)
    rows, rep = PartitionSpec(AXIS), PartitionSpec()
    body = functools.partial(_device_queue, shape=shape, k=k)
    smap = _shard_map(body, mesh=m, in_specs=(rep, rows, rows, rows, rep), out_specs=rows, **_UNCHECKED)
    r, split = NamedSharding(m, rep), NamedSharding(m, rows)
    return jax.jit(smap, in_shardings=(r, split, split, split, r), out_shardings=split)


def _device_queue(scene, origins, samples, counts, pass_index, *, shape, k):
    # one device's list of tiles of one pass, rendered one after another into its rows of the output
    th, tw, sb = shape
    o, s, n = origins[0], samples[0], counts[0]

    def body(carry):
        i, out = carry
        window = Window(o[i, 0], o[i, 1], s[i, 0], s[i, 1], th, tw, sb)
        tile = integrators.path.render(scene, pass_index, jitter=True, window=window)
        return i + 1, jax.lax.dynamic_update_index_in_dim(out, tile.astype(out.dtype), i, 0)

    out = jnp.zeros((k, th, tw, 3), jnp.float32)
    _, out = jax.lax.while_loop(lambda c: c[0] < n, body, (jnp.int32(0), out))
    return jax.lax.expand_dims(out, [0])


def lpt(costs: Sequence[float], n: int) -> tuple[tuple[int, ...], ...]:
    """Longest processing time first (Graham 1969): the indices of `costs` split into `n` lists, each
    cost in decreasing order (ties: the lower index first) going to the list with the least total so
    far (ties: the lower list). The largest total is at most (4/3 − 1/(3n)) times the least possible.
    Each list is returned in increasing index order."""
    if n < 1:
        raise ValueError(f"lpt: {n} lists; give 1 or more")
    c = np.asarray(costs, np.float64)
    if c.ndim != 1 or not np.isfinite(c).all() or (c < 0).any():
        raise ValueError("lpt: costs must be a list of finite numbers >= 0")
    load = np.zeros(n)
    out: list[list[int]] = [[] for _ in range(n)]
    for i in sorted(range(len(c)), key=lambda i: (-c[i], i)):
        d = int(np.argmin(load))  # the first of the least loaded
        out[d].append(i)
        load[d] += c[i]
    return tuple(tuple(sorted(x)) for x in out)


def makespan(costs: Sequence[float], lists: Sequence[Sequence[int]]) -> float:
    """The largest total cost of `lists` (index lists into `costs`, one per device)."""
    c = np.asarray(costs, np.float64)
    return max((float(c[list(x)].sum()) for x in lists), default=0.0)


def queue_arrays(steps: Sequence, lists: Sequence[Sequence[int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(origins (D, k, 2), samples (D, k, 2), counts (D,), k) of `queue_program` for the device lists
    `lists` of indices into `steps` (`Plan.steps`); k is the longest list, shorter ones padded with
    zero-sample copies of a tile that are never rendered (the device's loop stops at its count)."""
    k = max(1, max(len(x) for x in lists))
    origins = np.zeros((len(lists), k, 2), np.int32)
    samples = np.zeros((len(lists), k, 2), np.int32)
    for d, x in enumerate(lists):
        for j, i in enumerate(x):
            origins[d, j], samples[d, j] = steps[i][1], steps[i][2]
    counts = np.array([len(x) for x in lists], np.int32)
    return origins, samples, counts, k


@functools.lru_cache(maxsize=32)
def tile_pass_program(shape: tuple[int, int, int]):
    """One device's tile of a progressive path-tracing pass as a one-device program,
    ``f(scene, origin, samples, pass_index)`` (origin and samples (2,) int32), dispatched to each
    device by its arguments (`views`) for `timed`; returns (th, tw, 3)."""
    def one(scene, origin, samples, pass_index):
        th, tw, sb = shape
        window = Window(origin[0], origin[1], samples[0], samples[1], th, tw, sb)
        return integrators.path.render(scene, pass_index, jitter=True, window=window)

    return jax.jit(one)


def views(tree, devices: Sequence[jax.Device]) -> list:
    """For each of `devices` (all driven by this process), `tree` (replicated over them, `replicate`)
    as that device's own copy: every array leaf's shard on the device, nothing copied."""
    def on(d):
        def leaf(x):
            if isinstance(x, jax.Array) and len(x.sharding.device_set) > 1:
                return next(sh.data for sh in x.addressable_shards if sh.device == d)
            return x
        return jax.tree.map(leaf, tree)

    return [on(d) for d in devices]


def timed(calls: Sequence[Sequence], depth: int = 2, poll: float = 2e-4) -> list[list[tuple[np.ndarray, float]]]:
    """Run every device's list of calls (``calls[d][j]()`` dispatches one computation on device d and
    returns its array), each device at most `depth` calls ahead, and time them: returns, per device,
    (output as numpy, seconds) for each call, the seconds from the end of the device's previous call
    (or the first dispatch) to this one's output being ready (`jax.Array.is_ready`, polled): the
    call's device time, plus with ``depth=1`` the host's dispatch and polling delay (about a tenth
    of a millisecond). On one host; a device's calls run one after another, the devices at once."""
    n = len(calls)
    out: list[list[tuple[np.ndarray, float]]] = [[] for _ in range(n)]
    nxt = [0] * n
    flight: list[list] = [[] for _ in range(n)]

    def dispatch(d):
        while nxt[d] < len(calls[d]) and len(flight[d]) < depth:
            flight[d].append(calls[d][nxt[d]]())
            nxt[d] += 1

    start = time.perf_counter()
    last = [start] * n
    for d in range(n):
        dispatch(d)
    while any(flight):
        moved = False
        for d in range(n):
            if flight[d] and flight[d][0].is_ready():
                now = time.perf_counter()
                x = flight[d].pop(0)
                out[d].append((np.asarray(x), now - last[d]))
                last[d] = now
                dispatch(d)
                moved = True
        if not moved:
            time.sleep(poll)
    return out


def round_arrays(steps: Sequence, n: int) -> tuple[Int[np.ndarray, "D 2"], Int[np.ndarray, "D 2"]]:
    """(origins, samples) of one call: the windows of `steps` (at most `n`, `Plan.steps` entries),
    padded to `n` rows with the last window at a sample count of 0 (its rays start inactive, so a
    device without a tile in the last call exits its loops at once; its output is dropped)."""
    pad = n - len(steps)
    origins = np.array([s[1] for s in steps] + [steps[-1][1]] * pad, np.int32)
    samples = np.array([s[2] for s in steps] + [(steps[-1][2][0], 0)] * pad, np.int32)
    return origins, samples


# ---- whole independent problems (fits) split over the devices -------------------------------------------


def padded(n: int, devices: Sequence[jax.Device]) -> int:
    """`n` rounded up to a multiple of the device count: the batch length a sharded call takes."""
    d = max(1, len(devices))
    return -(-int(n) // d) * d


def pad_rows(tree, n: int):
    """Every leaf of `tree` (leading axis m ≤ n) padded to n rows with copies of its last row, so that a
    batch split over devices has one shape on every call; the caller drops the padded rows' results."""
    def pad(x):
        x = np.asarray(x)
        m = x.shape[0]
        return x if m == n else np.concatenate([x, np.repeat(x[-1:], n - m, axis=0)])

    return jax.tree.map(pad, tree)


def put_each(tree, devices: Sequence[jax.Device]) -> list:
    """One copy of `tree` on each of `devices` that this process drives (the replicated arguments of
    `batched`), in device order."""
    return [jax.device_put(tree, d) for d in local(devices)]


@functools.lru_cache(maxsize=64)
def _jitted(fn):
    return jax.jit(fn)


def batched(fn, devices: Sequence[jax.Device], split: tuple[bool, ...], *args, replicated: Sequence | None = None):
    """``fn(*args)`` for a batch of independent problems (`fn` vmapped over the leading axis, e.g. a
    batch of least-squares solves), the batch split over `devices`: positional argument i is split
    along its leading axis where ``split[i]`` (every leaf of that pytree), else the same for every
    device. Returns the outputs as numpy arrays, the devices' rows concatenated back in order.

    Each device runs the one-device program (`jax.jit(fn)`) on its own rows, dispatched
    asynchronously one device after another, so the devices run at once, each with its own while
    loops that stop when its own lanes have converged, and nothing communicates. (A `shard_map` of
    an optimistix solve does not trace in this JAX: lineax compares the shapes of a linear
    operator's input and output, and inside a manual mesh one side carries the mesh's sharding and
    the other not, "Incompatible linear operator structures"; with the replication check on,
    linearize meets tangents that are not marked as varying over the mesh.) The leading axis must be
    a multiple of the device count (`padded`, `pad_rows`). `replicated`: `put_each` of the
    non-split arguments (in order), to move them once for many calls.
    """
    n = len(devices)
    run = _jitted(fn)
    rows = {i: jax.tree.leaves(a)[0].shape[0] for i, a in enumerate(args) if split[i]}
    total = next(iter(rows.values()))
    if any(r != total for r in rows.values()) or total % n:
        raise ValueError(f"split arguments of {total} rows for {n} devices: give a multiple of the device count")
    k = total // n
    mine = [j for j, d in enumerate(devices) if d.process_index == jax.process_index()]
    shared = [a for i, a in enumerate(args) if not split[i]]
    copies = replicated if replicated is not None else put_each(shared, [devices[j] for j in mine])
    outs = []
    at_once = concurrent([devices[j] for j in mine])
    for c, j in enumerate(mine):
        if c >= at_once:  # at most `concurrent` programs at once (on a CPU: see there)
            jax.block_until_ready(outs[c - at_once])
        it = iter(copies[c])
        call = [jax.device_put(jax.tree.map(lambda x: np.asarray(x)[j * k:(j + 1) * k], a), devices[j]) if split[i]
                else next(it) for i, a in enumerate(args)]
        outs.append(run(*call))  # asynchronous: the next device starts while this one computes
    out = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *outs)
    if jax.process_count() == 1:
        return out
    # several hosts: every process computed its own devices' rows; each gets all of them, in device order
    from jax.experimental import multihost_utils

    every = multihost_utils.process_allgather(out)  # (processes, own rows, ...)
    owner = [[j for j, d in enumerate(devices) if d.process_index == p] for p in range(jax.process_count())]
    order = np.argsort([j for js in owner for j in js], kind="stable")

    def place(x):
        parts = [x[p, c * k:(c + 1) * k] for p, js in enumerate(owner) for c in range(len(js))]
        return np.concatenate([parts[i] for i in order])

    return jax.tree.map(lambda x: place(np.asarray(x)), every)
