"""Unidirectional path tracing with next-event estimation and multiple importance sampling.

`integrator = "path"`. Every pixel sample is one path; the B = H·W·spp paths advance together
(wavefront style), one bounce per iteration of a `lax.fori_loop` (a scan: BVH traversal is compiled
once, not once per bounce, and the loop is reverse-differentiable), then, unless the rays are traced
ahead (below), one last ray query that only collects the emission found after max_depth vertices (no
light sample or next direction there; with a few emissive triangles, an any-hit query to the nearest
one a ray meets, `LAST_RAYS_EMITTERS`). Each
bounce runs on the live paths only, compacted into chunks (`_compacted`: the dead ones cost neither
memory traffic nor traversal lanes), so short paths cost little whatever max_depth is; on a GPU only
in scenes of at least `GPU_COMPACT_MIN_TRIANGLES` triangles, where traversal outweighs moving the
paths' state. On the CPU the paths go in batches of a few chunks, one after another (`_batch_sizes`).
Where `CPU_TRACE_AHEAD` or `GPU_TRACE_AHEAD` holds (both on), a bounce traces the rays it makes
(the camera rays are traced before the first), adds the emission they find (environment or emissive
triangle) and finishes the paths whose ray escapes at once, so the next bounce's chunks hold only
paths with a surface to shade and no bounce after the last is needed.

Estimator (pbrt-v4's PathIntegrator, power heuristic with β = 2). At each path vertex:

* Emission reached by the previous BSDF-sampled ray (emissive triangle or environment) is added
  with MIS weight p_bsdf² / (p_bsdf² + p_light²); camera rays and delta bounces get weight 1.
* Next-event estimation at non-delta vertices: every point light, deterministically (delta
  lights: no MIS, and no selection noise), plus one sample of the "continuous" lights: choose the
  emissive triangles or the environment (probability 1/2 each when both exist), then a triangle by
  area·luminance(emission) and a uniform point on it (pdf converted to solid angle,
  d²/|cos θ_light|), or a direction from the environment's luminance distribution. Each gets one
  shadow ray (`bvh.occluded`) and the weight p_light² / (p_light² + p_bsdf²).
* The next direction is sampled from the material: the mirror coefficient δ is a delta lobe
  chosen with probability δ (the opaque BRDF part with 1 − δ, sampled with the model's
  `sample`/`pdf`); the NEE term above is weighted by (1 − δ) deterministically, so with point
  lights only and max_depth 1 the estimate equals the Whitted image exactly. Glass chooses
  reflection with probability R (Fresnel) and transmission otherwise, inside/outside decided by
  the geometric normal as in Whitted (no nested media; glass casts opaque shadows for NEE but
  transmits BSDF-sampled paths, so light through glass arrives by path sampling).
* Russian roulette from vertex RR_DEPTH on: survival probability max(throughput) clamped to
  [0.05, 0.95].

max_depth counts scattering vertices (as pbrt's maxDepth): 1 is direct lighting (NEE plus the
MIS-weighted emission found by the BSDF-sampled ray); Mitsuba's `max_depth` is ours + 1.

Emitters are one-sided (they emit on the side the triangle winding's normal points to);
surfaces are two-sided for reflection. No NaN/Inf reaches the image: zero pdfs and degenerate
directions end the path, and non-finite samples are replaced by 0.

Random numbers are counter-based: the path of pixel i, sample j in pass P has the key
`fold_in(fold_in(key(seed), P), i·spp + j)`, and its 8 uniforms at bounce k (light class, triangle,
2 for the light point, lobe/mirror/Fresnel choice, 2 for the BSDF direction, roulette) are the words
of Threefry-2x32-13 blocks of that key with counters (k, 0..3) (`common.counter_uniforms`). A path's
numbers therefore do not depend on the batch around it. Camera
jitter and lens samples come from `camera.generate_rays` with a per-pass seed. A tile of tiled
rendering (`camera.Window`) computes its paths' global i·spp + j, so its paths are the whole
image's, bit for bit; where i·spp + j ≥ 2³² (only tiled renders reach it) the high word is folded
in after the low one, so streams stay distinct instead of wrapping.

Gradients. `jax.grad` of an image w.r.t. material parameters, emission, environment texels and
light intensities is an unbiased estimate of the gradient of the expected image (away from
visibility changes, which material parameters never move): every sampling decision (directions,
lobe/mirror/Fresnel choices, light selection, MIS weights, roulette) is computed from
stop_gradient'ed values, while the path weights f(params)·cosθ/pdf, δ/q, R/R̂ are not. For fixed
sampling densities the estimator is an unbiased estimate of I(θ) for every θ, so its derivative
at the current θ is an unbiased estimate of dI/dθ (the densities only have to be positive where
f is). Geometry and the camera are stop_gradient'ed (edge terms are not modelled).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

import brdfs
from jaxrt import _random, accel, camera, envmap
from jaxrt import lights as _lights
from jaxrt.integrators.common import (counter_uniforms, emitter_table, intersect_active, intersect_surface_active,
                                      live_first, power_heuristic, sample_area_light)
from jaxrt.integrators.common import on_cpu as _on_cpu  # a name of this module's: tests patch it
from jaxrt.shading.aovs import build_aovs
from jaxrt.shading.material import at_hits, hit_params, glass_split, is_glass
from jaxrt.shading.surface import dot, from_local, local_frame, mirror_dir, normalize, offset_scale, oriented, to_local

RR_DEPTH = 3
_NU = 8  # uniforms per path and bounce (see module docstring)
CPU_CHUNK = 16384  # live paths per chunk of a bounce on the CPU (`_batch_sizes`)
CPU_BATCH_CHUNKS = 8  # chunks per batch of paths on the CPU (`_batch_sizes`)
CPU_DENSE_AT = 0.8  # live share of a batch from which the CPU's bounce runs uncompacted (`_compacted`)
# (the Cornell box, whose second bounce starts 93 % alive: 1.0 spent 4-5.5 % less CPU time a pass at
# 256² on one device but ~7 % more wall time at 512² on two (`benchmarks/peers.py`); 0.5: +6 % at 256²)
# Chunks per pass on a GPU (`_batch_sizes`): with a skipped chunk costing nothing, fewer and larger
# chunks move less state (each live chunk's conditional copies the state arrays) against more dead
# paths in the last live chunk of a bounce. One NVIDIA H200, the environment-lit dragon at 512², 16
# spp: 3 chunks 19.1 ms a pass, 4 chunks 19.9, 6 21.6, 8 22.6 (BENCHMARKS.md, "Path tracing: vector
# loads in the traversal, and skipped chunks").
GPU_CHUNKS = 3
# Whether a GPU's first bounce runs on the whole batch (its paths all start alive), outside the loop
# of compacted bounces: that spares its gathers, scatters and per-chunk conditionals (one NVIDIA
# H200, 512², 16 spp: 0.9-1.2 ms of a 13-22 ms pass) but the program then holds the bounce three
# times, a longer first compilation (+1.3 s for the Cornell box, +4.6 s for the environment-lit
# dragon): off, as a render would need over a thousand such passes to win the wait back. On the
# CPU chunks keep the state in cache, so the first bounce is compacted there regardless.
GPU_WHOLE_FIRST_BOUNCE = False
# The GPU compacts the bounces of scenes with at least this many triangles, and runs every bounce of
# smaller ones on the whole batch: compaction moves each live path's state twice a bounce (gather,
# scatter) to spare dead paths' traversal and shading, which pays only where traversal is dear. One
# NVIDIA H200, 512², 16 spp, depth 4, pass medians (BENCHMARKS.md, "Path tracing: ray order, ..."):
# the Cornell box (32 triangles; paths live long) 13.9 ms compacted against 12.0-12.5 ms whole; the
# environment-lit bunny (69k) 15.0 against 15.3-15.4; the dragon (871k) 22.9 against 23.0-23.2.
# The crossover between 32 and 69k triangles is not measured.
GPU_COMPACT_MIN_TRIANGLES = 10_000
# Where a compacted bounce's chunk is skipped (past the live count), whether its gathers and scatters
# are skipped with it (inside the chunk's conditional) rather than run on nothing but dropped rows.
COMPACT_IN_COND = True
# Where a GPU compacts its bounces, whether each bounce traces the rays it makes (the next bounce's
# closest hits), adds the emission they find and finishes at once the paths whose ray escapes, instead
# of the next bounce tracing them first: the next bounce's chunks then hold only paths with a surface
# to shade. A chunk's shading costs its whole size whatever share of it lives (one NVIDIA H200, the
# environment-lit dragon: ~1 ms a chunk of 1.4M paths), so a path that only escapes costs a full slot;
# and the emission-only bounce after the last is not needed. The
# camera rays are traced before the first bounce. One NVIDIA H200, the environment-lit dragon at 512²
# (16 spp, depth 4, `benchmarks/path_chunks.py`, medians of 9 passes, two alternations in one process):
# 19.4 -> 16.3 ms a pass, pixels equal, first call 8.9 -> 8.5 s (the last bounce's body goes away).
GPU_TRACE_AHEAD = True
# The same on the CPU (every CPU pass compacts; its surfaces come from the traversal, so a bounce carries
# each hit's surface too). One CPU device of a 2-core VM, `benchmarks/path_ab.py` at 256² (16 spp, depth
# 4, medians of 5-7 alternating with the pass without it): the environment-lit dragon -14.6 % wall time
# (-12.4 % CPU time), the Cornell box -1.1 % (its paths seldom escape); compile time unchanged. The
# emissive triangles' light collected where the rays are traced too (no bounce after the last): the
# Cornell box a further +3.9, -7.1, -5.7 % wall time in three such A/Bs (medians of 9, 9, 21 passes).
CPU_TRACE_AHEAD = True
# Where the rays made at the last vertex (max_depth) are traced on their own (not ahead: a GPU's
# whole-batch bounces, as in the Cornell box) they only bring back the emission they reach, so with
# at most this many emissive triangles they are not traced among all the scene's triangles:
# each is tested against every emitter (`accel.intersect_few`, fused into the glue), and the nearest
# emitter hit's visibility, or for a ray that meets none the escape to an environment, is an any-hit
# query, which ends at the first occluder (`last_rays` in `samples`). A closest hit walks on to the nearest
# surface, and rays that meet no emitter (most, in a room lit by a small lamp) are no query at all
# where no environment shines. 0 traces them as the other bounces' rays. One NVIDIA H200, the Cornell
# box at 512², 16 spp, depth 4 (`benchmarks/path_chunks.py`, medians of 9, alternating in one
# process): 11.31 / 11.36 ms a pass against 11.70 / 11.63 with their closest hits, pixels within 1.2e-7.
LAST_RAYS_EMITTERS = 16
# Whether that emitter test takes exact edge signs and a double-float t (`accel.intersect_few`): a ray
# within rounding of an emitter's edge counts as hitting it either way, and the emission's MIS weight
# needs no more than float32's t. The exact test lengthened the pass's first compilation on an H200
# (fresh processes, medians of 3: 8.36 against 8.00 s with closest hits, then 8.97 against 8.43); this
# one does not (7.42 against 8.43), and the pass is no slower.
LAST_RAYS_EXACT = False
# Whether a GPU's whole-batch bounces (scenes under GPU_COMPACT_MIN_TRIANGLES) have the traversal
# kernel take each ray query's live rays first (`common.live_first`, the queries' `order`): a dead path's
# slot or an unlit light sample's leaves the kernel at its tree's root, but a warp costs as long as its
# slowest lane, and in the Cornell box's later bounces a third to a half of the slots are dead,
# scattered over nearly every warp. It costs a prefix sum and a scatter of indices a query; the rays,
# their results and the paths' state stay where they are. One NVIDIA H200, the Cornell box at 512²,
# 16 spp, depth 4: closest hits 2.78 -> 2.42 ms a pass, any hits 2.02 -> 1.43 ms, the orders 0.3-0.4 ms;
# the pass 11.61 / 11.44 -> 11.27 / 11.28 ms (`path_chunks.py`, alternating, pixels equal). Gathering
# the live rays into a packed batch instead (and the results back) cost more than it saved (+0.35 ms).
# In the compacted bounces too (the environment-lit dragon: its chunks' dead tails, unlit light
# samples) the pass was slower, 16.86 / 16.73 against 15.99 / 16.10 ms, and its first call took 66 s.
GPU_PACK_RAYS = True
_sg = lax.stop_gradient


def _light_classes(scene):
    """Static probabilities of sampling (emissive triangles, environment) for the one NEE sample."""
    has_tri = scene.area_lights is not None and scene.area_lights.count > 0
    has_env = getattr(scene, "environment", None) is not None
    n = int(has_tri) + int(has_env)
    return (1.0 / n if has_tri else 0.0), (1.0 / n if has_env else 0.0)


def _params(mats, s, k: int) -> dict:
    # textured parameters are looked up at the hit's uv where the Surface carries one
    uv = getattr(s, "uv", None)
    return hit_params(mats, s.material, k) if uv is None else hit_params(mats, s.material, k, uv)


def _bsdf_models(mats):
    return [(k, brdfs.get(name)) for k, name in enumerate(mats.models) if not brdfs.get(name).delta]


def _path_keys(kpath, window: camera.Window, spp: int, width: int):
    """The key of every path of a window: fold_in(kpath, i·spp + j) for global pixel i = row·width +
    column and sample j, with i·spp + j computed in two 32-bit words (it reaches 2⁴⁰: 16384² pixels
    by 4096 samples) and the high word folded in second where it is not 0."""
    u32 = jnp.uint32
    rows = (window.row0 + jnp.arange(window.height)).astype(u32)
    cols = (window.col0 + jnp.arange(window.width)).astype(u32)
    pix = (rows[:, None] * u32(width) + cols[None, :]).reshape(-1, 1)  # < 2^28
    j = (window.sample0 + jnp.arange(window.spp)).astype(u32)[None, :]
    hi16, lo16 = pix >> u32(16), pix & u32(0xFFFF)  # pix·spp = hi16·spp·2^16 + lo16·spp (exact: spp < 2^16)
    a = (hi16 * u32(spp)) << u32(16)
    b = lo16 * u32(spp) + j
    lo = a + b
    hi = ((hi16 * u32(spp)) >> u32(16)) + (lo < a).astype(u32)
    lo, hi = lo.reshape(-1), hi.reshape(-1)
    k_lo = _random.fold_in(kpath, lo)
    k_hi = _random.fold_in(k_lo, hi)
    data = jnp.where((hi == 0)[:, None], jax.random.key_data(k_lo), jax.random.key_data(k_hi))
    return jax.random.wrap_key_data(data, impl=jax.random.key_impl(kpath))


def _stored(tree, alive):
    """`tree`, computed once and kept in memory, on the CPU. XLA fuses an elementwise producer into
    each of its consumers and recomputes it there: in the environment-lit dragon's bounce
    (`benchmarks/path.py`) each sampled direction's sines and cosines were made three times (the
    traced program had 7 sines, the compiled one 22; 1.9x the traced program's elementwise
    operations in all, 1.4x with the stores). An optimisation barrier does not stop that on the CPU
    (XLA:CPU removes barriers before fusing); a conditional's operands and results are buffers. Its
    predicate (some path of the batch alive) always holds where this runs, which the compiler cannot
    know. On GPUs recomputing is cheap and a conditional costs a wait for the device: no-op there.
    (Kept in memory behind an optimization barrier on an H200, the random numbers made the Cornell
    box's pass 5 % slower and the environment-lit dragon's 2-4 %; all of these values 11-13 % and
    3-6 %: BENCHMARKS.md, "Path tracing: the last rays go to the emitters".)"""
    if jax.default_backend() != "cpu":
        return tree
    return lax.cond(jnp.any(alive), lambda t: t, lambda t: jax.tree.map(jnp.zeros_like, t), tree)


def _where_present(present, fn, *args):
    """fn(*args) where `present` (some path of the chunk continues on a surface of the model fn
    evaluates), zeros otherwise, on the CPU. A scene with several BSDF models evaluates each on
    every path and selects per path; where a chunk's paths all meet one model, the others' work is
    skipped (zeros are never selected: they belong to paths that do not continue). On GPUs a
    conditional waits for the device: fn(*args) there, as where `present` is None (one model)."""
    if present is None or jax.default_backend() != "cpu":
        return fn(*args)
    return lax.cond(present, fn, lambda *a: jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(fn, *a)),
                    *args)


def _keyed(geo):
    """The geometry with Embree's key of its triangle table where its rays go through Embree on the
    CPU (`accel.with_table_key`; made here, from the triangles this pass traces), and whether it is
    keyed. A keyed Embree call does not hash the table, so chunks need not amortise that."""
    tree = getattr(geo, "tree", None)
    if jax.default_backend() != "cpu" or not isinstance(tree, accel.BVH):
        return geo, False
    tree = accel.with_table_key(tree)
    if tree.table_key is None:
        return geo, False
    return eqx.tree_at(lambda g: g.tree, geo, tree), True


def _batch_sizes(n: int, triangles: int) -> tuple[int, int]:
    """(batch, chunk): the paths of a pass of n paths traced together (one `lax.map` step), and the
    live paths of a batch that one bounce handles at a time (`_compacted`).

    GPU: one batch of every path, in GPU_CHUNKS chunks. CPU: a bounce is ~50 XLA ops that each stream
    every path's state through memory: in chunks of CPU_CHUNK paths that state stays in cache (the
    Cornell box at 256², 16 spp: ~20 % less CPU time per pass; BENCHMARKS.md, "Path tracing on the
    CPU: chunks and stored samples"), and a batch is CPU_BATCH_CHUNKS chunks (its state, ~150 bytes a
    path, is what the gathers and scatters of `_compacted` walk). A traversal call that hashes its
    triangle table (Embree without a key, `_keyed`) keeps a chunk at least `triangles` paths (the
    871k-triangle dragon's 31 MB take 2-4 ms a call: chunks of 4096 made its pass 2.3x slower); pass 0
    where the calls are keyed. Chunks and batches are equal in size, the fewest that respect the bounds."""
    if jax.default_backend() != "cpu":
        return n, -(-n // GPU_CHUNKS)
    m = max(1, n // max(CPU_CHUNK, triangles))
    chunk = -(-n // m)
    batches = -(-m // CPU_BATCH_CHUNKS)
    return -(-m // batches) * chunk, chunk


def _compacted(fn, carry, chunk: int, dense_at: float | None = None):
    """One bounce (`fn` over a path-state tuple whose third entry is `alive` and whose last, the
    paths' keys, fn does not change) over the live paths of `carry` only: their indices are gathered
    in order (a prefix sum, so neighbouring paths stay neighbours), then fn runs on `chunk` of them at
    a time and its results are scattered back; chunks past the live count are skipped (`lax.cond`).

    Why (Laine, Karras and Aila 2013, "Megakernels considered harmful: wavefront path tracing on
    GPUs"): a wavefront bounce costs every path of the batch its state's memory traffic, dead or
    alive, and a traversal warp costs as much for one live lane as for 32. In the environment-lit
    dragon (`benchmarks/path.py`, 16 spp, max_depth 4) 63 %, 19 %, 8 % and 0.3 % of the paths are
    alive at bounces 1-4, scattered over 65 %, 44 %, 35 % and 7 % of 32-path groups: compacted, the
    pass handles ~1.9 batches of paths instead of 5. The results are the uncompacted ones: a path's
    arithmetic and random numbers (`counter_uniforms`, by key and bounce) never depend on the paths
    beside it. The loops are a scan (reverse-differentiable); a skipped chunk's results are zeros
    that the scatter drops. Each leaf moves by its own gather and scatter: packing the ~15 leaves
    into one matrix first (one gather, one scatter) cost more than it saved on both platforms (one
    NVIDIA H200, 512², 16 spp: the dragon's pass 25.5 ms packed against 22.3 ms per leaf, the Cornell
    box 18.6 against 13.7; the 2-core CPU, Cornell box at 256²: +17 % CPU time against +5 %, both
    against no compaction).

    dense_at (the CPU's `CPU_DENSE_AT`): where at least this share of the batch is alive, the chunks
    are the batch's own consecutive rows, sliced and written back in place, their dead paths masked
    (a chunk with none alive still skipped): on the CPU a gather and a scatter move element by
    element, which costs a bounce whose paths nearly all live more than the dead ones' work (the
    Cornell box at 256²: +6.6 % wall time compacted at every bounce against uncompacted chunks).
    Needs chunk to divide the batch."""
    alive = carry[2]
    n_all = alive.shape[0]
    m = -(-n_all // chunk)
    n = jnp.sum(alive, dtype=jnp.int32)
    pos = jnp.cumsum(alive, dtype=jnp.int32) - 1
    idx = jnp.zeros(m * chunk, jnp.int32).at[jnp.where(alive, pos, m * chunk)].set(
        jnp.arange(n_all, dtype=jnp.int32), mode="drop", unique_indices=True)
    state, keys = carry[:-1], carry[-1]
    lane = jnp.arange(chunk, dtype=jnp.int32)
    if dense_at is not None:
        assert n_all % chunk == 0, (n_all, chunk)
        dense = n >= jnp.int32(math.ceil(dense_at * n_all))

    def run(rows, valid, sub):
        sub = sub[:2] + (sub[2] & valid,) + sub[3:]
        return fn(sub + (keys[rows],))[:-1]

    def skip(rows, valid, sub):
        return jax.tree.map(lambda x: jnp.zeros((chunk,) + x.shape[1:], x.dtype), sub)

    def sparse_rows(start):
        return lax.dynamic_slice(idx, (start,), (chunk,)), start + lane < n

    def gather(state, rows):
        return jax.tree.map(lambda x: x[rows], state)

    def scatter(state, rows, valid, out):
        dest = jnp.where(valid, rows, n_all)  # (dead lanes' rows dropped)
        return jax.tree.map(lambda x, y: x.at[dest].set(y, mode="drop", unique_indices=True), state, out)

    def live_chunk(c, state):
        # gather, bounce and scatter of one chunk, all inside the conditional: a chunk past the live
        # count then costs no launch at all (its gathers and scatters of nothing included)
        rows, valid = sparse_rows(c * chunk)
        return scatter(state, rows, valid, run(rows, valid, gather(state, rows)))

    def step(c, state):
        start = c * chunk
        if dense_at is None and COMPACT_IN_COND:
            # (XLA then copies the state arrays through the conditional, ~5 copies a live chunk: 0.8 ms
            # of the dragon's pass; still 0.8-1.1 ms faster than running the skipped chunks' gathers
            # and scatters on dropped rows, one NVIDIA H200, BENCHMARKS.md)
            return lax.cond(start < n, live_chunk, lambda c, state: state, c, state)
        if dense_at is None:
            rows, valid = sparse_rows(start)
            sub = gather(state, rows)
            some = start < n
        else:
            rows, valid = lax.cond(dense, lambda: (start + lane, lax.dynamic_slice(alive, (start,), (chunk,))),
                                   lambda: sparse_rows(start))
            sub = lax.cond(dense, lambda: jax.tree.map(lambda x: lax.dynamic_slice_in_dim(x, start, chunk), state),
                           lambda: gather(state, rows))
            some = jnp.any(valid)
        out = lax.cond(some, run, skip, rows, valid, sub)
        if dense_at is None:
            return scatter(state, rows, valid, out)
        # (dense: the chunk's dead paths come back as fn left them, as in an uncompacted pass)
        return lax.cond(dense, lambda: jax.tree.map(lambda x, y: lax.dynamic_update_slice_in_dim(x, y, start, 0),
                                                    state, out), lambda: scatter(state, rows, valid, out))

    state = step(0, state) if m == 1 else lax.fori_loop(0, m, step, state)
    return state + (keys,)


def _in_chunks(fn, xs, n: int, chunk: int):
    """fn over the leading axis of the pytree xs (n rows) in chunks of `chunk` rows, one after another
    (`lax.map`); the last chunk is padded with zeros and its padding dropped."""
    if chunk >= n:
        return fn(xs)
    m = -(-n // chunk)
    def pad(x):
        x = jnp.pad(x, [(0, m * chunk - n)] + [(0, 0)] * (x.ndim - 1))
        return x.reshape((m, chunk) + x.shape[1:])

    out = lax.map(fn, jax.tree.map(pad, xs))
    return jax.tree.map(lambda y: y.reshape((m * chunk,) + y.shape[2:])[:n], out)


def samples(scene, pass_index: Int[Array, ""] | int = 0, *, jitter: bool | None = None, aovs: bool = False,
            window: camera.Window | None = None):
    """Radiance of every path of one pass.

    Args:
        scene: a `jaxrt.scene.Scene` (settings.spp paths per pixel, settings.max_depth bounces).
        pass_index: which pass (a different random stream per pass; traced, no recompile).
        jitter: jitter samples inside the pixel (default: spp > 1, as Whitted); progressive
            accumulation always jitters.
        aovs: also return the first-hit records (prim, u, v, t, direction) of every path.
        window: None for every pixel and sample, else one tile (`camera.Window`): its pixels and
            run of samples, each path with the random numbers of the same path of the whole image;
            samples past the window's `count` are not traced (radiance 0).

    Returns:
        (H·W, spp, 3) float32 linear radiance per path [W/(m²·sr)], finite (the window's pixels and
        samples with a window); with `aovs` a pair (radiance, first-hit dict).
    """
    st, cam, mats = scene.settings, _sg(scene.camera), scene.materials
    geo, keyed = _keyed(_sg(scene.geometry))
    D = st.max_depth
    spp = st.spp
    npix, nsamp = (cam.num_pixels, spp) if window is None else (window.num_pixels, window.spp)
    B = npix * nsamp
    p_tri, p_env = _light_classes(scene)
    env = scene.environment if p_env > 0 else None
    table = emitter_table(scene) if p_tri > 0 else None
    al = scene.area_lights
    nl = scene.lights.count
    models = _bsdf_models(mats)
    on_cpu = _on_cpu()
    # (each bounce on the whole batch: see GPU_COMPACT_MIN_TRIANGLES, GPU_PACK_RAYS)
    compact = on_cpu or geo.triangle_count >= GPU_COMPACT_MIN_TRIANGLES
    pack = GPU_PACK_RAYS and not compact

    key = jax.random.fold_in(jax.random.key(jnp.asarray(st.seed, jnp.uint32)), jnp.asarray(pass_index, jnp.uint32))
    kcam, kpath = jax.random.split(key)
    cam_seed = jax.random.bits(kcam, (), jnp.uint32)
    o0, d0 = camera.generate_rays(cam, spp, cam_seed, jitter, window=window)
    d0 = normalize(d0)
    if window is None:
        path_keys = _random.fold_in(kpath, jnp.arange(B, dtype=jnp.uint32))
        alive0 = jnp.ones(B, bool)
    else:
        path_keys = _path_keys(kpath, window, spp, cam.width)
        alive0 = jnp.broadcast_to(jnp.arange(nsamp) < window.count, (npix, nsamp)).reshape(-1)

    def uniforms(keys, k):
        return counter_uniforms(keys, k, _NU)

    def env_emission(L, alive, found, d, tput, specular, pdf_prev):
        # radiance of the environment reached by rays d that found no surface (MIS-weighted)
        le = envmap.radiance(env, d)
        w = jnp.where(specular, 1.0, power_heuristic(pdf_prev, p_env * _sg(envmap.pdf(env, d))))
        return L + jnp.where((alive & ~found)[:, None], tput * w[:, None] * le, 0.0)

    def tri_emission(L, found, prim, t, material, ng, d, tput, specular, pdf_prev):
        # radiance of the emissive triangles that rays d found (MIS-weighted against the light sample
        # that could have picked the same point: area pdf to solid angle, t² / cos at the light;
        # ng the triangles' winding normals)
        le = al.emission[material]
        cos_l = -dot(d, ng)
        t = jnp.where(found, t, 0.0)
        p_l = p_tri * table.face_pdf[jnp.maximum(prim, 0)] * t * t / jnp.where(cos_l > 0, cos_l, 1.0)
        w = jnp.where(specular, 1.0, power_heuristic(pdf_prev, p_l))
        return L + jnp.where((found & (cos_l > 0))[:, None], tput * w[:, None] * le, 0.0)

    def closest_hits(o, d, alive):
        # (hits, surfaces there or None). On the CPU the hit point and geometric normal come with the
        # hit (Embree computes them from the triangle it holds, on both cores;
        # `geometry.intersect_surface`), so the glue gathers no corners: the geometry is under
        # stop_gradient here, so nothing differentiates them. A GPU pass gathers them (`geo.surface`).
        if on_cpu:
            return intersect_surface_active(geo, o, d, alive)
        return intersect_active(geo, o, d, alive, ordered=pack), None

    def occluded(o, d, tmax):
        # any hits with t in [0, tmax] (rays with tmax <= 0 find none)
        return geo.occluded(o, d, tmax, order=live_first(tmax > 0) if pack else None)

    def work(k, carry, last: bool = False):
        # One bounce of a chunk of paths. With `ahead` (not None: the carry's hits, an `accel.Hit`, and
        # on the CPU the surfaces there; see GPU_TRACE_AHEAD, CPU_TRACE_AHEAD) each path's ray was
        # traced where it was made and the paths whose ray escaped were finished there; else the
        # bounce traces its paths' rays first.
        o, d, alive, tput, specular, pdf_prev, L, first, ahead, keys = carry
        B = o.shape[0]  # the paths of one chunk
        # the bounce's random numbers, by key and bounce: on the CPU made once into a buffer
        # (`_stored`: XLA would otherwise remake the Threefry blocks in each consuming loop), on a GPU
        # remade where used (cheap there); neither stores them in the paths' state, which every
        # bounce would read, gather and scatter
        u = _stored(uniforms(keys, k), alive)
        hit, s = ahead if ahead is not None else closest_hits(o, d, alive)
        prim = jnp.where(alive, hit.prim, -1)
        found = prim >= 0
        if first is not None and ahead is None:
            first = jax.tree.map(lambda a, b: jnp.where(k == 0, b, a), first,
                                 dict(prim=prim, u=hit.u, v=hit.v, t=jnp.where(found, hit.t, 0.0), d=d))
        if not on_cpu:
            s = geo.surface(prim, hit.u, hit.v)
        s = eqx.tree_at(lambda x: x.material, s, jnp.where(found, s.material, 0))

        # ---- emission found by the previous ray
        if env is not None and ahead is None:
            L = env_emission(L, alive, found, d, tput, specular, pdf_prev)
        if table is not None and ahead is None:
            L = tri_emission(L, found, prim, hit.t, s.material, s.ng, d, tput, specular, pdf_prev)

        if last:
            # vertex max_depth + 1 only collects the emission its ray found: no light sample, no
            # next direction (in the loop they would all be masked off by k < D)
            return (o, d, jnp.zeros_like(alive), tput, specular, pdf_prev, L, first, ahead, keys)
        cont = found & (k < D)
        ng, ns, _ = oriented(s, d)
        frame = local_frame(ns, s.tangent)
        wo = to_local(-d, frame)
        # stored: the shading frame (a cross product), the light sample and the BSDF sample each
        # have several consumers, which would recompute them (see `_stored`)
        frame, wo = _stored((frame, wo), alive)
        eps = offset_scale(s.p)
        glass = cont & is_glass(mats, s.material)
        opaque = cont & ~glass
        delta = jnp.where(opaque, mats.delta[s.material], 0.0)
        q = _sg(delta)
        params = {kk: _params(mats, s, kk) for kk, _ in models}
        sel = {kk: mats.model_id[s.material] == kk for kk, _ in models}
        present = {kk: jnp.any(sel[kk] & cont) if len(models) > 1 else None for kk, _ in models}

        def eval_f(wi_l, wo_l, extra_dims=0):
            f = jnp.zeros(wi_l.shape)
            pdf = jnp.zeros(wi_l.shape[:-1])
            for kk, model in models:
                fk, pk = _where_present(
                    present[kk], lambda p, wi_l, wo_l, model=model: at_hits(
                        p, lambda p: (model.eval(p, wi_l, wo_l), model.pdf(_sg(p), wo_l, wi_l)), extra_dims),
                    params[kk], wi_l, wo_l)
                m = sel[kk].reshape((-1,) + (1,) * extra_dims)
                f = jnp.where(m[..., None], fk, f)
                pdf = jnp.where(m, pk, pdf)
            return f, pdf

        # ---- next-event estimation: every point light, one continuous-light sample
        origin = s.p + ng * eps
        rays_o, rays_d, rays_t = [], [], []
        if nl > 0:
            wi_p, dist_p, scale_p = _lights.incident(scene.lights, s.p)  # (B, L, 3), (B, L), (B, L, 3)
            lit_p = opaque[:, None] & (dot(wi_p, ng[:, None, :]) > 0)
            wi_pl = to_local(wi_p, tuple(x[:, None, :] for x in frame))
            f_p, _ = eval_f(wi_pl, wo[:, None, :], extra_dims=1)
            c_p = f_p * jnp.maximum(wi_pl[..., 2], 0.0)[..., None] * scale_p  # (B, L, 3)
            rays_o.append(jnp.broadcast_to(origin[:, None, :], wi_p.shape).reshape(-1, 3))
            rays_d.append(wi_p.reshape(-1, 3))
            rays_t.append(jnp.where(lit_p, dist_p - 2.0 * eps, -1.0).reshape(-1))
        if table is not None or env is not None:
            wi_c = jnp.zeros((B, 3))
            le_c = jnp.zeros((B, 3))
            p_c = jnp.zeros(B)
            dist_c = jnp.full(B, jnp.inf)
            pick_tri = u[:, 0] < p_tri
            if table is not None:
                wi_t, le_t, p_t, dist = sample_area_light(geo, al, table, origin, u[:, 1:4], p_tri)
                wi_c = jnp.where(pick_tri[:, None], wi_t, wi_c)
                le_c = jnp.where(pick_tri[:, None], le_t, le_c)
                p_c = jnp.where(pick_tri, p_t, p_c)
                dist_c = jnp.where(pick_tri, dist, dist_c)
            if env is not None:
                wi_e, le_e, pdf_e = envmap.sample(env, u[:, 2:4])
                wi_c = jnp.where(pick_tri[:, None], wi_c, wi_e)
                le_c = jnp.where(pick_tri[:, None], le_c, le_e)
                p_c = jnp.where(pick_tri, p_c, p_env * _sg(pdf_e))
            wi_c, le_c, p_c, dist_c = _stored((wi_c, le_c, p_c, dist_c), alive)
            wi_cl = to_local(wi_c, frame)
            f_c, pb = eval_f(wi_cl, wo)
            lit_c = opaque & (dot(wi_c, ng) > 0) & (p_c > 0)
            w_c = power_heuristic(p_c, (1.0 - q) * pb)
            c_c = f_c * (jnp.maximum(wi_cl[:, 2], 0.0) * w_c / jnp.where(p_c > 0, p_c, 1.0))[:, None] * le_c
            rays_o.append(origin)
            rays_d.append(wi_c)
            rays_t.append(jnp.where(lit_c, dist_c - 2.0 * eps[:, 0], -1.0))
        if rays_o:
            tmax = jnp.concatenate(rays_t)
            occ = occluded(jnp.concatenate(rays_o), jnp.concatenate(rays_d), tmax)
            vis = (tmax > 0) & ~occ
            direct = jnp.zeros((B, 3))
            if nl > 0:
                direct = direct + jnp.sum(jnp.where(vis[: B * nl].reshape(B, nl)[..., None], c_p, 0.0), axis=1)
            if table is not None or env is not None:
                direct = direct + jnp.where(vis[B * nl:][:, None], c_c, 0.0)
            L = L + tput * (1.0 - delta)[:, None] * direct

        # ---- next direction: opaque (mirror lobe δ or the model's sampler) ...
        wi_s = jnp.zeros((B, 3)).at[:, 2].set(1.0)
        pdf_s = jnp.zeros(B)
        for kk, model in models:
            wk, pk = _where_present(present[kk], lambda p, wo, u, model=model: at_hits(
                p, lambda p: model.sample(_sg(p), _sg(wo), u)[::2]), params[kk], wo, u[:, 5:7])
            wi_s = jnp.where(sel[kk][:, None], wk, wi_s)
            pdf_s = jnp.where(sel[kk], pk, pdf_s)
        wi_s, pdf_s = _stored((wi_s, pdf_s), alive)
        f_s, _ = eval_f(wi_s, wo)
        ok_s = pdf_s > 0
        # (q = 1 always takes the mirror; the guard keeps this unused branch finite for gradients)
        den = jnp.where(ok_s & (q < 1.0), pdf_s * (1.0 - q), 1.0)
        fac_b = f_s * (jnp.maximum(wi_s[:, 2], 0.0) * (1.0 - delta) / den)[:, None]
        mirror = u[:, 4] < q
        fac_m = jnp.broadcast_to((delta / jnp.where(q > 0, q, 1.0))[:, None], (B, 3))
        d_op = jnp.where(mirror[:, None], mirror_dir(d, ng, ns), from_local(wi_s, frame))
        ok_op = (mirror | ok_s) & (dot(d_op, ng) > 0)
        fac_op = jnp.where(mirror[:, None], fac_m, fac_b)
        new_d, new_o, fac, ok = d_op, origin, fac_op, ok_op
        new_spec = mirror
        new_pdf = (1.0 - q) * pdf_s
        # ... or glass: reflection with probability R, else transmission
        for kk, name in enumerate(mats.models):
            if not brdfs.get(name).delta:
                continue
            r, dr, dt, t_ok = glass_split(mats, s, d, kk)
            rq = _sg(r)
            pick_r = (u[:, 4] < rq) | ~t_ok
            fac_g = jnp.where(pick_r, r / jnp.where(rq > 0, rq, 1.0), (1.0 - r) / jnp.where(rq < 1, 1.0 - rq, 1.0))
            here = glass & (mats.model_id[s.material] == kk)
            new_d = jnp.where(here[:, None], jnp.where(pick_r[:, None], dr, dt), new_d)
            new_o = jnp.where(here[:, None], jnp.where(pick_r[:, None], origin, s.p - ng * eps), new_o)
            fac = jnp.where(here[:, None], fac_g[:, None], fac)
            ok = jnp.where(here, True, ok)
            new_spec = new_spec | here
        tput = tput * fac
        alive = cont & ok
        # ---- Russian roulette
        q_rr = jnp.clip(jnp.max(_sg(tput), axis=-1), 0.05, 0.95)
        rr = jnp.asarray(k >= RR_DEPTH)  # (a bool array also where k is a Python int: ~rr below)
        alive = alive & (~rr | (u[:, 7] < q_rr))
        tput = jnp.where(rr, tput / q_rr[:, None], tput)
        good = alive & jnp.all(jnp.isfinite(tput), axis=-1)
        tput = jnp.where(good[:, None], tput, 0.0)
        new_o, new_d, new_pdf = _sg(new_o), normalize(_sg(new_d)), _sg(new_pdf)
        if ahead is not None:
            # the next ray traced now; a path whose ray escapes is finished here (the environment's
            # emission), so the next bounce's chunks hold only paths with a surface to shade
            good, L, ahead = trace_ahead(new_o, new_d, good, tput, new_spec, new_pdf, L)
        return (new_o, new_d, good, tput, new_spec, new_pdf, L, first, ahead, keys)

    def trace_ahead(o, d, alive, tput, specular, pdf_prev, L):
        # (the paths still alive: those whose ray found a surface; the radiance with the emission the
        # rays found, environment and emissive triangles, so that no bounce after the last is needed;
        # their hits and, on the CPU, the surfaces there)
        hit, s = closest_hits(o, d, alive)
        found = alive & (hit.prim >= 0)
        prim = jnp.where(found, hit.prim, -1)
        if env is not None:
            L = env_emission(L, alive, found, d, tput, specular, pdf_prev)
        if table is not None:
            # (a GPU gathers the surfaces' material and normal here and again where the next bounce
            # shades them: XLA keeps only what each use reads)
            se = s if s is not None else geo.surface(prim, hit.u, hit.v)
            se = eqx.tree_at(lambda x: x.material, se, jnp.where(found, se.material, 0))
            L = tri_emission(L, found, prim, hit.t, se.material, se.ng, d, tput, specular, pdf_prev)
        return found, L, (hit._replace(prim=prim), s)

    def last_rays(carry):
        # the emission reached by the rays of vertex max_depth, without their closest hits (see
        # LAST_RAYS_EMITTERS): the nearest emitter each ray meets, if any, and one any-hit query, up
        # to that emitter (short by the 2·eps of a shadow ray to a light sample) or, for a ray that
        # meets none, to infinity where an environment shines (an unoccluded one escapes); the
        # emitter counts where nothing is nearer, as the closest hit would have found
        o, d, alive, tput, specular, pdf_prev, L, first, ahead, keys = carry
        tmax = jnp.where(alive, jnp.inf if env is not None else -1.0, -1.0)
        met = jnp.zeros_like(alive)
        if table is not None:
            v0, v1, v2 = geo.triangles(al.prims)
            h = accel.intersect_few(jnp.concatenate([v0, v1, v2], axis=-1), o, d, 0.0,
                                    jnp.where(alive, jnp.inf, -1.0), exact=LAST_RAYS_EXACT)
            met = h.prim >= 0
            j = jnp.maximum(h.prim, 0)
            t_e = jnp.where(met, h.t, 0.0)
            eps = offset_scale(o + t_e[:, None] * d)[:, 0]
            tmax = jnp.where(met, t_e - 2.0 * eps, tmax)
        occ = occluded(o, d, tmax)
        if env is not None:
            L = env_emission(L, alive, met | occ, d, tput, specular, pdf_prev)
        if table is not None:
            face = al.prims[j]
            ng_e = normalize(jnp.cross(v1 - v0, v2 - v0))[j]
            seen = met & ~occ
            L = tri_emission(L, seen, jnp.where(seen, face, -1), t_e, geo.face_material(face), ng_e, d, tput,
                             specular, pdf_prev)
        return (o, d, jnp.zeros_like(alive), tput, specular, pdf_prev, L, first, ahead, keys)

    def trace(o0, d0, alive0, key_data, chunk):
        # the paths of one batch, from their camera rays to their ends: (radiance, first hits); each
        # bounce runs on the batch's live paths only, in chunks of `chunk` (`_compacted`), except a
        # small scene's on a GPU, which run on the whole batch (GPU_COMPACT_MIN_TRIANGLES)
        B = o0.shape[0]
        keys = jax.random.wrap_key_data(key_data, impl=jax.random.key_impl(kpath))
        first = (dict(prim=jnp.full(B, -1, jnp.int32), u=jnp.zeros(B), v=jnp.zeros(B), t=jnp.zeros(B), d=d0)
                 if aovs else None)
        # the throughput's dtype follows the material values so float64 tests stay float64
        one = jnp.ones((B, 3), jnp.result_type(float))
        state = (o0, d0, alive0, one, jnp.ones(B, bool), jnp.zeros(B), jnp.zeros((B, 3)))
        ahead = None
        if CPU_TRACE_AHEAD if on_cpu else (GPU_TRACE_AHEAD and compact):
            # the camera rays traced before the first bounce (see GPU_TRACE_AHEAD)
            found, L0, ahead = trace_ahead(*state)
            if aovs:
                h = ahead[0]
                first = dict(prim=h.prim, u=h.u, v=h.v, t=jnp.where(found, h.t, 0.0), d=d0)
            state = (o0, d0, found) + state[3:6] + (L0,)
        carry = state + (first, ahead, keys)
        k0 = 0
        dense_at = CPU_DENSE_AT if on_cpu else None
        if compact:
            def bounce(fn, c):
                return _compacted(fn, c, chunk, dense_at)
        else:
            def bounce(fn, c):
                return fn(c)
        if GPU_WHOLE_FIRST_BOUNCE and not on_cpu and D > 0:
            # the paths start alive (a tile's padding samples excepted, masked): no compaction
            # (see GPU_WHOLE_FIRST_BOUNCE)
            carry, k0 = work(0, carry), 1
        carry = lax.fori_loop(k0, D, lambda k, c: bounce(lambda x: work(k, x), c), carry)
        if ahead is None and (D == 0 or table is not None or env is not None):
            # the emission found by the last rays (traced ahead, it was added where they were traced;
            # with point lights only there is none to find). With max_depth 0 the camera rays' first
            # hits are recorded there.
            few = LAST_RAYS_EMITTERS > 0 and (table is None or al.count <= LAST_RAYS_EMITTERS)
            carry = bounce(last_rays if D > 0 and few else lambda x: work(D, x, last=True), carry)
        return carry[6], carry[7]

    xs = (o0, d0, alive0, jax.random.key_data(path_keys))
    batch, chunk = _batch_sizes(B, 0 if keyed else geo.triangle_count)
    L, first = _in_chunks(lambda x: trace(*x, chunk), xs, B, batch)
    L = jnp.where(jnp.isfinite(L), L, 0.0).reshape(npix, nsamp, 3)
    if aovs:
        return L, first
    return L


def _aovs(scene, first: dict, window: camera.Window | None = None) -> dict:
    # paths are pixel-major (H·W·spp, the spp samples of a pixel together): the first sample of
    # pixel i is path i·spp
    cam, spp = scene.camera, scene.settings.spp
    shape, spp = ((cam.height, cam.width), spp) if window is None else ((window.height, window.width), window.spp)
    idx = jnp.arange(shape[0] * shape[1]) * spp
    return build_aovs(scene, *(first[k][idx] for k in ("prim", "u", "v", "t", "d")), shape=shape)


def render(scene, pass_index: Int[Array, ""] | int = 0, *, aovs: bool = False, jitter: bool | None = None,
           window: camera.Window | None = None):
    """One pass of `settings.spp` paths per pixel averaged into an (H, W, 3) image; with `aovs` a pair
    (image, dict) with depth, normal, albedo and object_id of each pixel's first sample (as Whitted).

    With a `window` (`camera.Window`, one tile of tiled rendering) only its pixels and samples are
    traced: the window's share of the pass, Σ over its samples / spp, (window height, width, 3); the
    AOVs are those of the window's first sample."""
    cam = scene.camera
    out = samples(scene, pass_index, jitter=jitter, aovs=aovs, window=window)
    L, first = out if aovs else (out, None)
    # On a GPU the barrier keeps XLA from fusing the average into the last bounce's output: fused,
    # XLA:GPU emitted it as one elementwise loop over the (pixels, spp, 3) radiance that took 0.67 ms
    # of a 12.9 ms Cornell box pass on an H200 (512², 16 spp); apart, the pass takes 12.3 ms
    # (`benchmarks/pass_parts.py`, "mean barrier"). On the CPU the fused average is the faster (the
    # barrier's pass was 3-6 % slower, Cornell box 256², one device).
    if jax.default_backend() != "cpu":
        L = lax.optimization_barrier(L)
    if window is None:
        img = jnp.mean(L, axis=1).reshape(cam.height, cam.width, 3)
    else:
        img = (jnp.sum(L, axis=1) / scene.settings.spp).reshape(window.height, window.width, 3)
    if not aovs:
        return img
    return img, _aovs(scene, first, window)


class Accumulation(eqx.Module):
    """Running sum of progressive passes: total (H, W, 3) Σ over samples; count () samples per pixel."""

    total: Float[Array, "H W 3"]
    count: Int[Array, ""]
    passes: Int[Array, ""]

    @property
    def image(self) -> Float[Array, "H W 3"]:
        return self.total / jnp.maximum(self.count, 1)


def accumulate(scene, state: Accumulation | None = None) -> Accumulation:
    """Add one pass of `scene.settings.spp` jittered samples per pixel to `state` (None: start).

    Pass P uses random stream P, so N calls give the same image as one render of N·spp samples
    would with those streams; the compiled pass is reused across calls (the pass index is traced).
    """
    cam = scene.camera
    if state is None:
        state = Accumulation(jnp.zeros((cam.height, cam.width, 3)), jnp.asarray(0), jnp.asarray(0))
    img = jnp.mean(samples_jit(scene, state.passes, jitter=True), axis=1).reshape(cam.height, cam.width, 3)
    spp = scene.settings.spp
    return Accumulation(state.total + img * spp, state.count + spp, state.passes + 1)


samples_jit = jax.jit(samples, static_argnames=("jitter", "aovs"))
render_jit = jax.jit(render, static_argnames=("aovs", "jitter"))


@functools.lru_cache(maxsize=8)
def _render_to_host(device, jitter: bool | None):
    # the jitted pass whose image XLA writes to the device's page-locked host memory (one per device,
    # as jit keeps one compiled program per input placement)
    return jax.jit(functools.partial(render, jitter=jitter),
                   out_shardings=jax.sharding.SingleDeviceSharding(device, memory_kind="pinned_host"))


def render_host(scene, pass_index: Int[Array, ""] | int = 0, *, jitter: bool | None = None) -> np.ndarray:
    """`render`'s image as a NumPy array (H, W, 3). On a GPU the pass's program copies its image to
    page-locked host memory itself, at the end, so reading it costs next to nothing: on an H200 a
    512² Cornell box pass read to the host this way took 12.9 ms against 13.5-13.9 ms for
    `np.asarray(render_jit(...))`, whose copy goes to pageable memory after the program
    (`benchmarks/pass_parts.py`). Elsewhere `np.asarray(render_jit(...))`. The scene's arrays are on
    one device (the default device where they are not placed)."""
    leaf = jax.tree.leaves(scene)[0]
    devs = leaf.devices() if isinstance(leaf, jax.Array) else {jax.devices()[0]}
    device = next(iter(devs))
    if len(devs) != 1 or device.platform != "gpu":
        return np.asarray(render_jit(scene, pass_index, jitter=jitter))
    return np.asarray(_render_to_host(device, jitter)(scene, pass_index))
