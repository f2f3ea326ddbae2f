"""What every integrator shares and no integrator owns: camera-ray order, ray queries with inactive
slots, the multiple-importance-sampling heuristic, the sampling table of the emissive triangles, and
per-path uniforms drawn with an unrolled Threefry. Integrators import this module, never each other.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int, Key

from jaxrt import envmap
from jaxrt._random import threefry2x32, unit_float
from jaxrt.accel import Hit
from jaxrt.shading.surface import dot, normalize


def on_cpu() -> bool:
    """Whether the integrators' programs are made for the CPU: there a conditional that skips dead
    work pays off and loops keep XLA:CPU from fusing a chain into each consumer; on a GPU each
    conditional or loop step is a host round trip, so the integrators take branch-free forms (the path
    tracer's live-path chunks are the exception: `path._compacted`'s conditionals skip more work than
    they cost there)."""
    return jax.default_backend() == "cpu"


def live_first(active: Bool[Array, " B"]) -> Int[Array, " B"]:
    """The permutation of a batch's ray slots that puts the `active` ones first and the others after
    them, each group in its order (a stable partition by one prefix sum): a ray query's `order`, so that
    a GPU kernel's warps hold live rays together (a warp runs as long as its slowest lane)."""
    n = active.shape[0]
    i = jnp.arange(n, dtype=jnp.int32)
    if n == 0:
        return i
    before = jnp.cumsum(active, dtype=jnp.int32) - active  # active slots before each slot
    slot = jnp.where(active, before, before[-1] + active[-1] + i - before)
    return jnp.zeros(n, jnp.int32).at[slot].set(i, unique_indices=True)


def intersect_active(geometry, origins: Float[Array, "B 3"], directions: Float[Array, "B 3"],
                     active: Bool[Array, " B"], *, ordered: bool = False) -> Hit:
    """Closest hits of a batch of ray slots of which only `active` ones exist: inactive slots get an
    empty interval, so traversal rejects them at the root. ordered: the kernel takes the active slots
    first (`live_first`; the same hits)."""
    return geometry.intersect(origins, directions, 0.0, jnp.where(active, jnp.inf, -1.0),
                              order=live_first(active) if ordered else None)


def intersect_surface_active(geometry, origins: Float[Array, "B 3"], directions: Float[Array, "B 3"],
                             active: Bool[Array, " B"]):
    """`intersect_active` and the surface at the hits (`geometry.intersect_surface`: not
    differentiable; for the passes under stop_gradient)."""
    return geometry.intersect_surface(origins, directions, 0.0, jnp.where(active, jnp.inf, -1.0))


#: rounds of Threefry-2x32 behind `counter_uniforms`: the fewest Salmon et al. (2011) found
#: "Crush-resistant" (every test of TestU01's BigCrush passed) for Threefry-2x32; 20 (JAX's) adds
#: a safety margin against cryptanalysis that a Monte Carlo estimate does not need
COUNTER_ROUNDS = 13


def counter_uniforms(keys: Key[Array, " B"], k: int | Array, n: int) -> Float[Array, "B n"]:
    """n uniforms in [0, 1) for each of B typed keys and a counter k (a path's bounce), counter-based:
    the words of Threefry-2x32-13 blocks (`COUNTER_ROUNDS`) keyed by the key's two words with
    counters (k, 0), (k, 1), ..., both words of a block used, each word's top 23 bits the mantissa
    of a float in [1, 2), minus 1. A path's numbers depend on its key and k only, never on the batch
    around it.

    Why not `fold_in_uniforms` (JAX's fold_in then uniform, 9 blocks of 20 rounds for 8 numbers):
    these 8 numbers cost 4 blocks of 13 rounds, about a quarter of the integer work (on a CPU the
    difference is 5-10 % of a path-tracing pass: BENCHMARKS.md, "Path tracing: cheaper random
    numbers"). Other key types than Threefry's go through `fold_in_uniforms`. The floats have the
    default float type's width (float64 under x64: the float32 values, widened)."""
    if str(jax.random.key_impl(keys)) != "threefry2x32":
        return fold_in_uniforms(keys, k, n)
    key_data = jax.random.key_data(keys)
    k1, k2 = key_data[:, 0], key_data[:, 1]
    words = []
    for j in range(-(-n // 2)):  # block by block over the batch: XLA:CPU vectorises along the batch
        words += threefry2x32(k1, k2, jnp.asarray(k, jnp.uint32), np.uint32(j), rounds=COUNTER_ROUNDS)
    return unit_float(jnp.stack(words[:n], axis=-1)).astype(jnp.result_type(float))


def fold_in_uniforms(keys: Key[Array, " B"], k: int | Array, n: int) -> Float[Array, "B n"]:
    """``jax.random.uniform(jax.random.fold_in(key, k), (n,))`` for each of B typed keys, bit for
    bit; for Threefry keys and float32 (JAX's defaults) from an unrolled hash (`jaxrt._random`).

    fold_in hashes the counter (0, k) with the key; element j of the uniform draw hashes (0, j) with
    the folded key and takes the XOR of the two output words (JAX's default
    ``jax_threefry_partitionable`` layout), whose top 23 bits become the mantissa of a float in
    [1, 2), minus 1.

    XLA fuses the hash into every consumer of the result (each column's use recomputes the
    row's hashes; XLA:CPU drops optimisation barriers before fusing), so callers that use the
    numbers more than once should store them first, e.g. as a loop-carried value."""
    if (str(jax.random.key_impl(keys)) != "threefry2x32" or not jax.config.jax_threefry_partitionable
            or jnp.result_type(float) != jnp.float32):  # another PRNG, layout or float width: JAX's own
        return jax.vmap(lambda pk: jax.random.uniform(jax.random.fold_in(pk, k), (n,)))(keys)
    key_data = jax.random.key_data(keys)
    k1, k2 = key_data[:, 0:1], key_data[:, 1:2]
    zero = jnp.zeros((), jnp.uint32)
    f1, f2 = threefry2x32(k1, k2, zero, jnp.asarray(k, jnp.uint32))
    b1, b2 = threefry2x32(f1, f2, zero, jnp.arange(n, dtype=jnp.uint32)[None, :])
    return unit_float(b1 ^ b2)


#: `jnp.searchsorted`'s method for the integrators' table look-ups (light CDFs, the photon grid's
#: buckets): the binary search written out step by step. Its default ("scan") is a loop, and on a GPU
#: each loop iteration is a round trip to the host for the loop's condition; unrolled, a look-up is
#: one fused kernel of log2(n) gathers. The result is the same index either way.
SEARCH = "scan_unrolled"

_UNSIGNED = True  # `sample_order_arrays` (False: signed on every backend, for A/B)
BLOCK = (8, 4)  # pixels (wide, high) per block of level-0 slots: one GPU warp's 32 rays



def sample_order(height: int, width: int, spp: int) -> tuple[np.ndarray, np.ndarray]:
    """Level-0 ray order: (sample index, in `camera.generate_rays` order, of each level-0 slot (n,);
    level-0 slot of each pixel's first sample (npix,)), static numpy.

    Pixels go in 8x4 blocks, blocks row by row, the spp samples of a pixel together: the 32 rays of a
    GPU warp then cover a block rather than a 32-pixel strip of a row, and stay more alike down the
    tree (children keep their parents' order). Simulated on the dragon at 512²: 18 % fewer steps for
    a warp's slowest ray.
    """
    y, x = np.divmod(np.arange(height * width), width)
    bw, bh = BLOCK
    key = ((y // bh) * (-(-width // bw)) + x // bw) * (bw * bh) + (y % bh) * bw + x % bw
    pixels = np.argsort(key, kind="stable")
    samples = (pixels[:, None] * spp + np.arange(spp)[None, :]).reshape(-1)
    first = np.empty(height * width, np.int64)
    first[pixels] = np.arange(height * width) * spp
    return samples.astype(np.int32), first.astype(np.int32)


def sample_order_arrays(height: int, width: int, spp: int) -> tuple[Int[Array, " n"], Int[Array, " npix"]]:
    """`sample_order` as int32 arrays of a program, made there from indices when the image is whole
    8x4 blocks (then a slot's pixel follows from its block and place in the block), else
    `sample_order`'s tables as constants. Why: a 1024² frame's two tables are 8 MB of constants,
    and every constant a program holds is stored with it and read again by each process that loads
    it (`jaxrt.programs`); the arithmetic costs a few integer operations per ray."""
    bw, bh = BLOCK
    if width % bw or height % bh:
        order, first = sample_order(height, width, spp)
        return jnp.asarray(order), jnp.asarray(first)
    nbx = width // bw
    # unsigned on the CPU: XLA:CPU writes a signed // and % by a constant with sign fix-ups (about 50
    # integer operations for `first`), which it recomputed for every element of the gather into pixel
    # order that consumes them; unsigned they are multiplies and shifts. Same indices.
    dt = jnp.uint32 if _UNSIGNED and on_cpu() else jnp.int32
    s = jnp.arange(height * width * spp, dtype=dt)
    p, j = s // spp, s % spp  # pixel rank, sample
    b, q = p // (bw * bh), p % (bw * bh)  # block, place in the block
    order = (((b // nbx) * bh + q // bw) * width + (b % nbx) * bw + q % bw) * spp + j
    i = jnp.arange(height * width, dtype=dt)
    y, x = i // width, i % width
    first = (((y // bh) * nbx + x // bw) * (bw * bh) + (y % bh) * bw + x % bw) * spp
    return order.astype(jnp.int32), first.astype(jnp.int32)


def power_heuristic(a, b):
    """Power heuristic a² / (a² + b²) in a form that neither overflows nor divides by 0."""
    a = jnp.minimum(a, 1e30)
    b = jnp.minimum(b, 1e30)
    r = b / jnp.where(a > 0, a, 1.0)
    return jnp.where(a > 0, 1.0 / (1.0 + r * r), 0.0)


class EmitterTable(eqx.Module):
    """Sampling table of the emissive triangles (derived from current values, never stored).

    cdf: (E + 1,) over emitters by area·luminance(emission); face_pdf: (F,) probability density per
    unit area of choosing a point on each face (0 for non-emitters); total: () Σ area·luminance;
    area: (E,) each emitter's area (in the order of `AreaLights.prims`).
    """

    cdf: Float[Array, " E1"]
    face_pdf: Float[Array, " F"]
    total: Float[Array, ""]
    area: Float[Array, " E"]


def emitter_table(scene) -> EmitterTable:
    """Areas and selection probabilities of the scene's emissive triangles (detached values)."""
    geo = lax.stop_gradient(scene.geometry)
    al = lax.stop_gradient(scene.area_lights)
    v0, v1, v2 = geo.triangles(al.prims)
    area = 0.5 * jnp.linalg.norm(jnp.cross(v1 - v0, v2 - v0), axis=-1)
    power = area * envmap.luminance(al.emission[geo.face_material(al.prims)])
    total = jnp.sum(power)
    norm = jnp.where(total > 0, total, 1.0)
    cdf = jnp.concatenate([jnp.zeros(1), jnp.cumsum(power) / norm])
    pdf_area = jnp.where(area > 0, power / norm / jnp.where(area > 0, area, 1.0), 0.0)
    face_pdf = jnp.zeros(geo.face_count).at[al.prims].set(pdf_area)
    return EmitterTable(cdf, face_pdf, total, area)


def sample_emitter_point(geo, al, table: EmitterTable, u: Float[Array, "B 3"]):
    """A point on the emissive triangles, chosen by `table` (u[:, 0]) and uniform over the chosen
    triangle's area (u[:, 1:3], the square-root warp of Shirley & Chiu): (face, its vertices
    (v0, v1, v2), point y, geometric normal n of the triangle's winding). Shared by next-event
    estimation and photon emission."""
    j = jnp.clip(jnp.searchsorted(table.cdf, u[:, 0], side="right", method=SEARCH) - 1, 0, al.count - 1)
    face = al.prims[j]
    v0, v1, v2 = geo.triangles(face)
    su = jnp.sqrt(u[:, 1])
    b1, b2 = 1.0 - su, u[:, 2] * su
    y = (1.0 - b1 - b2)[:, None] * v0 + b1[:, None] * v1 + b2[:, None] * v2
    n_l = normalize(jnp.cross(v1 - v0, v2 - v0))
    return face, (v0, v1, v2), y, n_l


def sample_area_light(geo, al, table: EmitterTable, origin: Float[Array, "B 3"], u: Float[Array, "B 3"],
                      p_select: float):
    """One next-event-estimation sample of the emissive triangles seen from `origin` (a point
    already offset off its surface): a point y of `sample_emitter_point` (u), the direction wi
    towards it, the emitted radiance L_e of its face, the solid-angle pdf p_select·p_A·d²/cos θ_l
    (p_A the table's area density, θ_l the angle at y between -wi and the face's winding normal; pbrt's
    area-light `SampleLi`) and the distance to y. A point seen from behind the face, one at the
    origin, or an empty table (no emitted power) gives pdf 0 and L_e 0. Returns (wi, L_e, pdf, dist).

    wi aims from the offset origin: a ray parallel to y − p from the unoffset point would meet the
    light's plane eps/cos θ early, short of a shadow ray's end, and count as occluded."""
    face, _, y, n_l = sample_emitter_point(geo, al, table, u)
    to = y - origin
    d2 = dot(to, to)
    dist = jnp.sqrt(jnp.maximum(d2, 1e-30))
    wi = to / dist[:, None]
    cos_l = -dot(wi, n_l)
    ok = (cos_l > 0) & (d2 > 1e-20) & (table.total > 0)
    pdf = jnp.where(ok, p_select * table.face_pdf[face] * d2 / jnp.where(ok, cos_l, 1.0), 0.0)
    le = jnp.where(ok[:, None], al.emission[geo.face_material(face)], 0.0)
    return wi, le, pdf, dist

