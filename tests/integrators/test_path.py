"""The path tracer (`jaxrt.integrators.path`), environment maps (`jaxrt.envmap`) and emissive surfaces.

References are independent of the code under test: exact values (white furnace), the Whitted
integrator (a different algorithm on the same scene), closed-form form factors, numerical
quadrature written here, Mitsuba 3's path tracer, and finite differences. Monte Carlo checks
compare against standard errors computed from the per-sample (or per-pass) values; the bounds
are k = 4.5 standard errors (two-sided, p ≈ 7e-6 per value) so a test with a few dozen values
fails by chance about once in 10^4 runs while a 1-2 % bias in a region mean is still caught.

Compile budget: each distinct scene structure costs one jit of the path tracer (two BVH
traversals, ~10 s on CPU). Tests that can share a structure do (module-scoped scenes whose
materials/emission/environment values are swapped as traced arrays).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import accel, envmap, scene
from jaxrt.integrators import common, path
from jaxrt.errors import InputError
from jaxrt.shading import direct

K = 4.5  # standard errors allowed per compared value (see module docstring)


def _with_material(sc, name):
    """The furnace sphere re-assigned to material `name` (a traced array: no recompile)."""
    i = sc.materials.index(name)
    return eqx.tree_at(lambda s: s.geometry.material, sc, jnp.full_like(sc.geometry.material, i))


def _pixel_stats(L):
    """Per-pixel mean and standard error from (P, S, 3) per-sample values, float64."""
    L = np.asarray(L, np.float64)
    return L.mean(1), L.std(1, ddof=1) / math.sqrt(L.shape[1])


# --------------------------------------------------------------------------- white furnace


@pytest.fixture(scope="module")
def furnace():
    return scene.load("furnace", overrides={"camera.width": 16, "camera.height": 16, "render.spp": 64})


def test_furnace_lambert_is_one(furnace):
    # A convex object inside a uniform environment: every ray leaving the surface escapes, so
    # L = ∫ f cosθ L_env dω = albedo · 1 exactly at the first bounce and the estimator needs no
    # deeper paths (max_depth is 10 here only because the glass test shares the compile).
    L = path.samples_jit(_with_material(furnace, "white"), 0, jitter=True)
    m, se = _pixel_stats(L)
    assert np.all(np.isfinite(m))
    miss = se == 0  # background pixels see the environment directly: exactly 1
    assert np.allclose(m[miss], 1.0, atol=1e-6)
    assert (~miss).sum() > 100
    z = (m - 1.0) / np.where(miss, 1.0, se)
    assert np.max(np.abs(z)) < K, f"max |z| = {np.max(np.abs(z)):.2f}"
    assert abs(m[~miss].mean() - 1.0) < K * math.sqrt(np.mean(se[~miss] ** 2) / (~miss).sum())


def test_furnace_energy_conserving_glossy_at_most_one(furnace):
    # cook_torrance with rho_d + rho_s = 1 conserves energy (README table); V-cavity shadowing
    # loses some, so the sphere must be darker than 1 (never brighter beyond the noise).
    L = path.samples_jit(_with_material(furnace, "glossy"), 1, jitter=True)
    m, se = _pixel_stats(L)
    hit = se > 0
    assert np.all(m[hit] <= 1.0 + K * se[hit])
    assert m[hit].mean() < 0.95  # and it is visibly below 1: the check could fail


def test_furnace_closed_glass_sphere_is_one(furnace):
    # Glass neither absorbs nor emits: every path that enters the sphere leaves it again (no TIR
    # traps light in a sphere) and sees radiance 1; depth 10 loses < R^9 ~ 1e-12 of the energy.
    L = path.samples_jit(_with_material(furnace, "glass"), 2, jitter=True)
    m, se = _pixel_stats(L)
    hit = se > 0
    assert hit.sum() > 100
    z = (m[hit] - 1.0) / se[hit]
    assert np.max(np.abs(z)) < K, f"max |z| = {np.max(np.abs(z)):.2f}"
    assert np.allclose(m[~hit], 1.0, atol=1e-6)


def test_progressive_accumulation_matches_passes(furnace):
    sc = _with_material(furnace, "white")
    state = path.accumulate(sc)
    state = path.accumulate(sc, state)
    assert int(state.count) == 2 * sc.settings.spp and int(state.passes) == 2
    passes = [np.asarray(path.samples_jit(sc, i, jitter=True)).mean(1).reshape(16, 16, 3) for i in (0, 1)]
    np.testing.assert_allclose(np.asarray(state.image), (passes[0] + passes[1]) / 2, rtol=1e-5, atol=1e-6)
    assert not np.allclose(passes[0], passes[1])  # different passes use different random streams


def test_pass_image_on_the_host_is_the_mean_of_its_samples(furnace):
    """`render`'s image (on a GPU its samples averaged behind an optimisation barrier), `render_host` and the
    program that writes the image to page-locked host memory (the GPU's route, built here for the
    CPU device) all give the mean of the pass's per-sample radiance; `_devices.to_host` through
    pinned memory gives the array's values."""
    from jaxrt import _devices

    sc = _with_material(furnace, "glossy")
    want = np.asarray(path.samples_jit(sc, 3, jitter=True)).mean(1).reshape(16, 16, 3)
    img = path.render_jit(sc, 3, jitter=True)
    np.testing.assert_allclose(np.asarray(img), want, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(path.render_host(sc, 3, jitter=True), np.asarray(img))
    pinned = path._render_to_host(jax.devices()[0], True)(sc, 3)
    assert pinned.sharding.memory_kind == "pinned_host"
    np.testing.assert_array_equal(np.asarray(pinned), np.asarray(img))
    np.testing.assert_array_equal(_devices.to_host(img, pinned=True), np.asarray(img))
    assert isinstance(_devices.to_host(img), np.ndarray) and isinstance(_devices.to_host(want), np.ndarray)
    assert not np.allclose(want, np.asarray(path.render_jit(sc, 4, jitter=True)))  # another pass, another image


def test_chunks_trace_the_paths_of_the_whole_batch(furnace, monkeypatch):
    # On the CPU a pass's paths go in batches (`lax.map`), each bounce over a batch's live paths in
    # chunks (`path._batch_sizes`, `path._compacted`); each path keeps its own random numbers, so the
    # radiance and first hits equal those of one batch whose every bounce runs on every path. A
    # small CPU_CHUNK gives three chunks (one per sphere triangle at least, 5120), two to a batch:
    # two batches that do not divide the 16·16·64 paths (the last one's padding is dropped), and
    # chunks of dead paths in the later bounces (the furnace's sphere is convex) that are skipped.
    sc = _with_material(furnace, "glossy")
    n = 16 * 16 * sc.settings.spp
    monkeypatch.setattr(path, "_compacted", lambda fn, carry, *args: fn(carry))
    whole = jax.jit(lambda s: path.samples(s, 3, jitter=True, aovs=True))(sc)
    monkeypatch.undo()
    monkeypatch.setattr(path, "CPU_CHUNK", 1500)
    monkeypatch.setattr(path, "CPU_BATCH_CHUNKS", 2)
    batch, chunk = path._batch_sizes(n, sc.geometry.triangle_count)
    assert jax.default_backend() != "cpu" or (chunk < batch < n and n % batch)
    chunked = jax.jit(lambda s: path.samples(s, 3, jitter=True, aovs=True))(sc)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(chunked), strict=True):
        if np.issubdtype(np.asarray(a).dtype, np.integer):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        else:  # the same arithmetic, up to the rounding of differently fused programs
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-6, atol=1e-7)
    assert float(jnp.mean(whole[0])) > 0


@pytest.mark.parametrize("live, dense_at, calls", [(13, None, 2), (13, 0.8, 2), (36, 0.8, 5), (40, 1.0, 5),
                                                   (36, 1.0, 5)])
def test_compacted_bounce_runs_live_paths_in_order_and_differentiates(live, dense_at, calls):
    # `path._compacted` against what it stands for, an elementwise bounce over the live paths only:
    # 40 paths in chunks of 8. 13 live: fn runs twice (the chunks past the live count are
    # skipped), on the live paths in their order; 36 live with dense_at 0.8 (the CPU's dense mode):
    # on the batch's own five blocks of rows, the dead masked. Either way dead paths keep their
    # state, and the gradient through the gathers or slices, the skipped chunks' conditionals and
    # the scatters is the closed form. 36 live with dense_at 1.0: compacted (five chunks, as 36 > 32);
    # all 40 live: dense.
    rng = np.random.default_rng(0)
    n, chunk = 40, 8
    alive = np.zeros(n, bool)
    alive[rng.choice(n, live, replace=False)] = True
    x = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    ids = jnp.arange(n, dtype=jnp.int32)
    keys = jax.random.split(jax.random.key(1), n)
    seen = []

    def fn(p):
        def bounce(carry):
            x, ids, live, keys = carry
            jax.debug.callback(lambda i, a: seen.append((np.asarray(i), np.asarray(a))), ids, live)
            k = jax.random.key_data(keys)[:, 0].astype(jnp.float32)[:, None]
            return jnp.where(live[:, None], x * p + k, x), ids, live, keys
        return bounce

    def compacted(p):
        return path._compacted(fn(p), (x, ids, jnp.asarray(alive), keys), chunk, dense_at)

    out = compacted(jnp.float32(2.0))
    k = np.asarray(jax.random.key_data(keys))[:, 0].astype(np.float32)[:, None]
    want = np.where(alive[:, None], np.asarray(x) * 2.0 + k, np.asarray(x))
    np.testing.assert_array_equal(np.asarray(out[0]), want)
    np.testing.assert_array_equal(np.asarray(out[1]), np.arange(n))
    np.testing.assert_array_equal(np.asarray(out[2]), alive)
    assert len(seen) == calls
    live_rows = np.flatnonzero(alive)
    np.testing.assert_array_equal(np.concatenate([i[a] for i, a in seen]), live_rows)
    rows = np.concatenate([i for i, _ in seen])
    if dense_at is not None and live >= dense_at * n:  # dense: the batch's rows in order, dead ones among them
        np.testing.assert_array_equal(rows, np.arange(n))
    else:  # compacted: the live rows first in each chunk
        assert not np.array_equal(rows[:live], np.arange(live))
    seen.clear()
    g = jax.grad(lambda p: jnp.sum(compacted(p)[0]))(jnp.float32(2.0))
    np.testing.assert_allclose(float(g), float(np.asarray(x)[alive].sum()), rtol=1e-5)


def test_live_first_is_a_stable_partition():
    rng = np.random.default_rng(4)
    for p in (0.0, 0.3, 1.0):
        active = rng.random(257) < p
        active[-1] = p > 0.5  # (the last ray's own slot is where the two groups meet)
        order = np.asarray(common.live_first(jnp.asarray(active)))
        np.testing.assert_array_equal(order, np.concatenate([np.flatnonzero(active), np.flatnonzero(~active)]))


@pytest.mark.slow  # ~75 s on 2 cores (six programs with the XLA traversal, a scene)
@pytest.mark.parametrize("name", ["furnace", pytest.param("cornell_area", marks=pytest.mark.data)])
def test_gpu_bounce_layouts_trace_the_same_paths(name, monkeypatch, request):
    # The GPU's layouts of a pass, made here by telling the path tracer it is not on the CPU: every
    # bounce compacted (scenes of at least GPU_COMPACT_MIN_TRIANGLES) with each bounce tracing the
    # rays it makes (GPU_TRACE_AHEAD) or tracing its own first, and every bounce on the whole batch
    # (smaller scenes: `_compacted` is not called). A path's arithmetic and random numbers never
    # depend on its neighbours, so radiance, first hits and the gradient agree to the rounding of
    # differently fused programs. The furnace's glossy sphere in its environment and the Cornell
    # box with its emissive ceiling, 8x8 pixels at 16 spp, depth 4 (paths die at different bounces).
    if name == "cornell_area":
        request.getfixturevalue("data_dir")
    sc = scene.load(name, overrides={"camera.width": 8, "camera.height": 8, "render.spp": 16, "render.max_depth": 4})
    if name == "furnace":
        sc = _with_material(sc, "glossy")
    monkeypatch.setattr(path, "_on_cpu", lambda: False)
    calls = []
    orig = path._compacted
    monkeypatch.setattr(path, "_compacted", lambda fn, carry, *a: calls.append(a) or orig(fn, carry, *a))
    k = int(sc.materials.model_id[int(sc.geometry.material[0])])

    def scaled(s_, x):  # the parameters of the first triangle's model scaled by x
        params = list(s_.materials.params)
        params[k] = jax.tree.map(lambda p: p * x, params[k])
        return eqx.tree_at(lambda y: y.materials.params, s_, tuple(params))

    def run(**knobs):
        for name_, v in knobs.items():
            monkeypatch.setattr(path, name_, v)
        calls.clear()
        out = jax.jit(lambda s: path.samples(s, 2, jitter=True, aovs=True))(sc)
        n = len(calls)
        g = jax.jit(jax.grad(lambda x: jnp.mean(path.samples(scaled(sc, x), 2, jitter=True))))(jnp.float32(0.9))
        return out, n, g

    n_tri = sc.geometry.triangle_count
    ahead, c0, g0 = run(GPU_COMPACT_MIN_TRIANGLES=n_tri, GPU_TRACE_AHEAD=True)
    own, c1, g1 = run(GPU_COMPACT_MIN_TRIANGLES=n_tri, GPU_TRACE_AHEAD=False)
    whole, c2, g2 = run(GPU_COMPACT_MIN_TRIANGLES=n_tri + 1, GPU_TRACE_AHEAD=True)  # (not compacted: no ahead)
    # the skipped chunks' gathers and scatters run on dropped rows instead of inside the conditional
    outside, c3, g3 = run(GPU_COMPACT_MIN_TRIANGLES=n_tri, COMPACT_IN_COND=False, GPU_TRACE_AHEAD=True)
    # every bounce on the whole batch, each ray query's live rays packed at the front (GPU_PACK_RAYS)
    packed, c4, g4 = run(GPU_COMPACT_MIN_TRIANGLES=n_tri + 1, GPU_PACK_RAYS=True)
    # (the loop's body is traced once, then, where each bounce traces its own rays, the last bounce
    # that collects the emission its rays find: traced ahead, the emission is added where they are traced)
    assert (c0, c1, c2, c3, c4) == (1, 2, 0, 1, 0)
    for other in (own, whole, outside, packed):
        for a, b in zip(jax.tree.leaves(ahead), jax.tree.leaves(other), strict=True):
            if np.issubdtype(np.asarray(a).dtype, np.integer):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            else:
                np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-5, atol=1e-6)
    assert float(jnp.mean(ahead[0])) > 0
    assert abs(float(g0)) > 1e-3
    np.testing.assert_allclose([float(g1), float(g2), float(g3), float(g4)], float(g0), rtol=1e-4)


@pytest.mark.slow  # ~40 s on 2 cores
@pytest.mark.parametrize("name", ["furnace", pytest.param("cornell_area", marks=pytest.mark.data)])
def test_cpu_trace_ahead_traces_the_same_paths(name, monkeypatch, request):
    # On the CPU (its own route: Embree's surfaces, dense and compacted batches) each bounce tracing
    # the rays it makes (`path.CPU_TRACE_AHEAD`) against each bounce tracing its rays first: the same
    # radiance, first hits and gradient to the rounding of differently fused programs. The furnace's
    # glossy sphere in its environment, and the Cornell box, whose emissive ceiling's light the
    # traced-ahead rays collect where they are traced (no bounce after the last).
    if name == "cornell_area":
        request.getfixturevalue("data_dir")
        sc = scene.load(name, overrides={"camera.width": 16, "camera.height": 16, "render.spp": 16,
                                         "render.max_depth": 4})
    else:
        sc = _with_material(scene.load(name, overrides={"camera.width": 16, "camera.height": 16, "render.spp": 64}),
                            "glossy")
    monkeypatch.setattr(path, "_on_cpu", lambda: True)
    monkeypatch.setattr(path, "CPU_CHUNK", 2048)  # (several chunks and batches, some of them dense)
    k = int(sc.materials.model_id[int(sc.geometry.material[0])])

    def scaled(x):
        params = list(sc.materials.params)
        params[k] = jax.tree.map(lambda p: p * x, params[k])
        return eqx.tree_at(lambda y: y.materials.params, sc, tuple(params))

    out = {}
    for ahead in (True, False):
        monkeypatch.setattr(path, "CPU_TRACE_AHEAD", ahead)
        img = jax.jit(lambda s: path.samples(s, 3, jitter=True, aovs=True))(sc)
        g = jax.jit(jax.grad(lambda x: jnp.mean(path.samples(scaled(x), 3, jitter=True))))(jnp.float32(0.9))
        out[ahead] = img, g
    (a, ga), (b, gb) = out[True], out[False]
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        if np.issubdtype(np.asarray(x).dtype, np.integer):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        else:
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
    assert float(jnp.mean(a[0])) > (0.5 if name == "furnace" else 0.05) and abs(float(ga)) > 1e-3
    np.testing.assert_allclose(float(ga), float(gb), rtol=1e-4)


@pytest.mark.slow  # 17-20 s on 2 cores
def test_unconditional_bounces_equal_skipped_dead_bounces(furnace, monkeypatch):
    # On a GPU every bounce runs (no `lax.cond` skipping a batch whose paths are all dead): dead
    # paths must then contribute nothing. Made here by telling the path tracer it is not on the
    # CPU, at a depth where the whole batch has died (the furnace's max_depth 10: a convex sphere,
    # every path escapes after its first bounces): the images agree to float32 rounding (the two
    # programs fuse differently).
    sc = _with_material(furnace, "glossy")
    skipped = jax.jit(lambda s: path.samples(s, 5, jitter=True, aovs=True))(sc)
    monkeypatch.setattr(path, "_on_cpu", lambda: False)
    always = jax.jit(lambda s: path.samples(s, 5, jitter=True, aovs=True))(sc)
    for a, b in zip(jax.tree.leaves(skipped), jax.tree.leaves(always), strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-5, atol=1e-6)
    assert float(jnp.mean(skipped[0])) > 0


@pytest.mark.slow  # 17-20 s on 2 cores
def test_surfaces_from_the_traversal_equal_the_gathered_ones(furnace, monkeypatch):
    # On the CPU a bounce takes each hit's point and geometric normal from the traversal
    # (`geometry.intersect_surface`: Embree computes them in double from the triangle it holds)
    # instead of gathering the corners (`geometry.surface`, what the GPU does). The same pass with
    # the surfaces rebuilt from the corners must agree to float32 rounding: same first hits, and
    # radiance within a few ulps (the furnace's glossy sphere: paths bounce up to 10 times).
    sc = _with_material(furnace, "glossy")
    L, first = jax.jit(lambda s: path.samples(s, 2, jitter=True, aovs=True))(sc)
    calls = []

    def gathered(geo, o, d, active):
        calls.append(1)
        hit = geo.intersect(o, d, 0.0, jnp.where(active, jnp.inf, -1.0))
        return hit, geo.surface(hit.prim, hit.u, hit.v)

    monkeypatch.setattr(path, "intersect_surface_active", gathered)
    L2, first2 = jax.jit(lambda s: path.samples(s, 2, jitter=True, aovs=True))(sc)
    assert jax.default_backend() != "cpu" or calls  # the CPU pass takes its surfaces there
    for k in first:
        np.testing.assert_array_equal(np.asarray(first[k]), np.asarray(first2[k]))
    np.testing.assert_allclose(np.asarray(L), np.asarray(L2), rtol=1e-5, atol=1e-6)
    assert float(jnp.mean(L)) > 0.5


@pytest.mark.slow  # 17-20 s on 2 cores
def test_chunked_pass_traces_an_edited_mesh(furnace, monkeypatch):
    # On the CPU with Embree the pass keys Embree's scene by the triangle table it traces
    # (`path._keyed`), which lets large meshes go in chunks too. The key is made in the pass from
    # the scene it is given: after a render of the sphere, the same compiled pass on the scene with
    # its triangles moved (eqx.tree_at) must trace the moved mesh, whose first hits are checked
    # against jaxrt's own XLA traversal of the moved mesh (independent of Embree's scene cache).
    monkeypatch.setattr(path, "CPU_CHUNK", 1500)
    f = jax.jit(lambda s: path.samples(s, 0, jitter=True, aovs=True))
    L0, first0 = f(furnace)
    geo = furnace.geometry
    v = geo.vertices * jnp.float32([1.0, 1.0, 0.5])  # squash z: the camera on +z meets it farther
    tri = geo.tree.triangles * jnp.tile(jnp.float32([1.0, 1.0, 0.5]), 3)
    moved = eqx.tree_at(lambda s: (s.geometry.vertices, s.geometry.tree.triangles), furnace, (v, tri))
    L1, first1 = f(moved)
    assert f._cache_size() == 1
    o = jnp.broadcast_to(furnace.camera.position, first1["d"].shape)
    # (a tree built for the moved mesh: the moved table's old boxes would not bound it)
    ref = accel.intersect(accel.build(np.asarray(v), np.asarray(geo.faces)), o, first1["d"], impl="xla")
    prim, t = np.asarray(first1["prim"]), np.asarray(first1["t"])
    same = prim == np.asarray(ref.prim)
    assert same.mean() > 0.999  # up to ties at edges between Embree and the XLA loop
    hit = same & (prim >= 0)
    assert hit.sum() > 1000
    np.testing.assert_allclose(t[hit], np.asarray(ref.t)[hit], rtol=1e-5)
    # the sphere's front at z = 1 before, 0.5 after: the camera at z = 4 sees it 0.5 farther
    both = hit & (np.asarray(first0["prim"]) >= 0)
    assert np.median(t[both] - np.asarray(first0["t"])[both]) > 0.4
    if jax.default_backend() == "cpu" and accel.uses_embree():
        n = 16 * 16 * furnace.settings.spp
        assert path._batch_sizes(n, 0)[1] < n  # the pass ran in chunks


def test_skipping_a_model_absent_from_a_chunk_changes_nothing(furnace, monkeypatch):
    # With several BSDF models, the CPU pass skips a model's evaluation and sampling in a chunk none
    # of whose continuing paths meets it (`path._where_present`). The same compiled pass with the
    # skip's predicate forced true (a traced flag: one program, so no other fusion or rounding)
    # must give the same radiance bit for bit: the zeros of a skipped model are never selected.
    monkeypatch.setattr(path, "CPU_CHUNK", 1500)
    geo = furnace.geometry
    y = np.asarray(jnp.stack(geo.triangles(jnp.arange(geo.triangle_count)))[..., 1].mean(0))
    m = np.where(y > 0, furnace.materials.index("glossy"), furnace.materials.index("white")).astype(np.int32)
    sc = eqx.tree_at(lambda s: s.geometry.material, furnace, jnp.asarray(m))
    orig = path._where_present

    def run(s, force):
        monkeypatch.setattr(path, "_where_present",
                            lambda p, fn, *a: orig(None if p is None else p | force, fn, *a))
        return path.samples(s, 0, jitter=True, aovs=True)

    f = jax.jit(run)
    (a, first), (b, _) = f(sc, jnp.bool_(False)), f(sc, jnp.bool_(True))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert f._cache_size() == 1
    # the scene has chunks whose camera rays meet one model only, and chunks that meet both
    n = a.shape[0] * a.shape[1]
    chunk = path._batch_sizes(n, 0)[1]
    prim = np.asarray(first["prim"])
    mat = np.where(prim >= 0, m[np.maximum(prim, 0)], -1)
    pad = -(-n // chunk) * chunk - n
    kinds = [set(c[c >= 0].tolist()) for c in np.pad(mat, (0, pad), constant_values=-1).reshape(-1, chunk)]
    if jax.default_backend() == "cpu":
        assert any(len(k) == 1 for k in kinds) and any(len(k) == 2 for k in kinds)
    assert float(jnp.mean(a)) > 0


# --------------------------------------------------------------------------- gradients


@pytest.mark.slow  # a reverse-mode compile of the path tracer (~30 s) plus 72 renders
def test_gradient_unbiased_vs_finite_differences(furnace):
    """d(mean image)/d(m) of a Cook-Torrance sphere in the furnace: m moves the sampling density
    too, which the estimator must not differentiate (see jaxrt.integrators.path). Mean of per-pass gradient
    estimates vs central differences of many-sample renders (common random numbers within each
    difference, other passes than the gradients), within their combined standard error."""
    sc = _with_material(furnace, "glossy")
    k = sc.materials.models.index("cook_torrance")

    def set_m(s, m):
        params = list(s.materials.params)
        params[k] = dict(params[k], m=jnp.full_like(params[k]["m"], m))
        return eqx.tree_at(lambda x: x.materials.params, s, tuple(params))

    def loss(m, i):
        return jnp.mean(path.samples(set_m(sc, m), i, jitter=True))

    grad = jax.jit(jax.grad(loss))
    m0, h = 0.2, 0.02
    g = np.array([float(grad(jnp.float32(m0), i)) for i in range(24)])
    fwd = lambda m, i: float(np.mean(np.asarray(path.samples_jit(set_m(sc, m), i, jitter=True), np.float64)))
    fd = np.array([(fwd(m0 + h, i) - fwd(m0 - h, i)) / (2 * h) for i in range(1000, 1024)])
    se = math.sqrt(g.var(ddof=1) / len(g) + fd.var(ddof=1) / len(fd))
    assert abs(g.mean()) > 5 * se  # a real, resolved gradient
    # plus 2 % for the O(h²) truncation of the central difference
    assert abs(g.mean() - fd.mean()) < K * se + 0.02 * abs(fd.mean()), (g.mean(), fd.mean(), se)


@pytest.mark.slow  # another reverse-mode compile plus 72 renders
@pytest.mark.data
def test_gradient_multibounce_cornell_vs_finite_differences(data_dir):
    """d(mean image)/ds with the Cornell box's white reflectance scaled by s: interreflection makes
    the image a polynomial in s over up to 3 bounces, so the estimate must differentiate every
    vertex's f along the path, the NEE and the MIS-weighted emission hits."""
    sc = scene.load("cornell_area", overrides={"camera.width": 8, "camera.height": 8, "render.spp": 64,
                                               "render.max_depth": 3})
    i_white = sc.materials.index("white")
    k, row = int(sc.materials.model_id[i_white]), int(sc.materials.row[i_white])
    base = sc.materials.params[k]["rho_d"]

    def set_s(s_, x):
        params = list(s_.materials.params)
        params[k] = dict(params[k], rho_d=base.at[row].multiply(x))
        return eqx.tree_at(lambda y: y.materials.params, s_, tuple(params))

    grad = jax.jit(jax.grad(lambda x, i: jnp.mean(path.samples(set_s(sc, x), i, jitter=True))))
    x0, h = 1.0, 0.05
    g = np.array([float(grad(jnp.float32(x0), i)) for i in range(24)])
    fwd = lambda x, i: float(np.mean(np.asarray(path.samples_jit(set_s(sc, x), i, jitter=True), np.float64)))
    fd = np.array([(fwd(x0 + h, i) - fwd(x0 - h, i)) / (2 * h) for i in range(1000, 1024)])
    se = math.sqrt(g.var(ddof=1) / len(g) + fd.var(ddof=1) / len(fd))
    assert abs(g.mean()) > 5 * se
    assert abs(g.mean() - fd.mean()) < K * se + 0.01 * abs(fd.mean()), (g.mean(), fd.mean(), se)


# --------------------------------------------------------------------------- Whitted equality


def test_point_lights_depth_one_equals_whitted():
    from test_render_util import lab_dict

    import jaxrt as render

    # the lab scene: Lambert and Phong under a point light with hard shadows, a δ = 1 mirror and a
    # glass slab (both contribute nothing at depth 1 in either integrator), background 0
    d = lab_dict("top", width=24, height=16)
    d["render"] = {"max_depth": 1, "spp": 1, "background": 0.0}
    w = np.asarray(render.frame(scene.load(d)))
    d["render"]["integrator"] = "path"
    sp = scene.load(d)
    p = np.asarray(path.samples_jit(sp, 0)).reshape(w.shape)
    assert (w.max(-1) > 0).mean() > 0.3
    np.testing.assert_allclose(p, w, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- environment maps


def _sky(h=16, w=32):
    """A synthetic sky: a vertical gradient plus a small bright sun."""
    v = (np.arange(h) + 0.5) / h
    tex = np.zeros((h, w, 3))
    tex[...] = (0.2 + 0.8 * (1 - v))[:, None, None] * np.array([0.5, 0.7, 1.0])
    tex[3:5, 20:22] = [40.0, 35.0, 30.0]
    tex[h - 2:] = 0.0  # a black patch: zero density where there is no light
    return tex


def _dirs(theta, phi):
    """World directions for the map's (θ from +y, φ) in Mitsuba's lat-long convention."""
    st = np.sin(theta)
    return np.stack([np.sin(phi) * st, np.cos(theta), -np.cos(phi) * st], -1)


def _rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def test_envmap_pdf_integrates_to_one_and_matches_lookup():
    env = envmap.from_array(_sky(), rotate=30.0)
    n = 512
    theta = (np.arange(n) + 0.5) / n * np.pi
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d = _dirs(T, P) @ _rot_y(30.0).T  # the map turned by +30° about +y
    pdf = np.asarray(envmap.pdf(env, jnp.asarray(d, jnp.float32)), np.float64)
    total = np.sum(pdf * np.sin(T)) * (np.pi / n) * (np.pi / n)
    assert abs(total - 1.0) < 5e-3
    # the lookup of the rotated map: texel (row, col) of the unrotated angles
    tex = _sky()
    rows = np.minimum((T / np.pi * 16).astype(int), 15)
    cols = np.minimum((P / (2 * np.pi) * 32).astype(int), 31)
    got = np.asarray(envmap.radiance(env, jnp.asarray(d, jnp.float32)))
    assert np.mean(np.all(np.isclose(got, tex[rows, cols], rtol=1e-5), -1)) > 0.99  # texel borders aside


def test_envmap_sampling_chi_square():
    from scipy import stats

    env = envmap.from_array(_sky(), rotate=-50.0)
    n = 200_000
    u = jax.random.uniform(jax.random.key(7), (n, 2))
    wi, _, pdf = (np.asarray(x, np.float64) for x in envmap.sample(env, u))
    ok = pdf > 0
    assert ok.mean() > 0.999
    np.testing.assert_allclose(np.linalg.norm(wi[ok], axis=-1), 1.0, atol=1e-5)
    # the returned pdf and radiance are those of the direction returned
    # (up to float32 rounding of directions on texel borders: a few in 10^4)
    again = np.asarray(envmap.pdf(env, jnp.asarray(wi[ok], jnp.float32)), np.float64)
    assert np.mean(np.isclose(pdf[ok], again, rtol=2e-3)) > 0.999
    # bin world directions on a coarse (cosθ, φ) grid unrelated to the texels; expected counts by
    # quadrature of `pdf` over each bin
    nb_t, nb_p, sub = 12, 24, 24
    ct = np.clip(wi[ok, 1], -1, 1)
    ph = np.mod(np.arctan2(wi[ok, 2], wi[ok, 0]), 2 * np.pi)
    bt = np.minimum(((1 - ct) / 2 * nb_t).astype(int), nb_t - 1)
    bp = np.minimum((ph / (2 * np.pi) * nb_p).astype(int), nb_p - 1)
    observed = np.bincount(bt * nb_p + bp, minlength=nb_t * nb_p)
    zc = 1 - 2 * (np.arange(nb_t * sub) + 0.5) / (nb_t * sub)
    pc = (np.arange(nb_p * sub) + 0.5) / (nb_p * sub) * 2 * np.pi
    Z, Pg = np.meshgrid(zc, pc, indexing="ij")
    r = np.sqrt(1 - Z**2)
    d = np.stack([r * np.cos(Pg), Z, r * np.sin(Pg)], -1)
    dens = np.asarray(envmap.pdf(env, jnp.asarray(d, jnp.float32)), np.float64)
    cell = (2.0 / (nb_t * sub)) * (2 * np.pi / (nb_p * sub))  # dω = dz dφ
    expected = dens.reshape(nb_t, sub, nb_p, sub).sum((1, 3)).reshape(-1) * cell * ok.sum()
    assert abs(expected.sum() / ok.sum() - 1) < 5e-3
    big = expected > 20
    assert observed[~big].sum() < 0.01 * n
    chi2 = np.sum((observed[big] - expected[big]) ** 2 / expected[big])
    p = stats.chi2.sf(chi2, big.sum() - 1)
    assert p > 1e-4, f"chi2 {chi2:.1f} on {big.sum() - 1} dof, p = {p:.2e}"


def test_constant_environment_sampling():
    env = envmap.constant([1.0, 2.0, 3.0])
    u = jax.random.uniform(jax.random.key(1), (50_000, 2))
    wi, rad, pdf = (np.asarray(x) for x in envmap.sample(env, u))
    np.testing.assert_allclose(pdf, 1 / (4 * np.pi), rtol=1e-6)
    np.testing.assert_allclose(rad, np.broadcast_to([1.0, 2.0, 3.0], rad.shape))
    # uniform on the sphere: mean 0, each coordinate's second moment 1/3
    assert np.all(np.abs(wi.mean(0)) < 4.5 * math.sqrt(1 / 3 / len(wi)))
    assert np.all(np.abs((wi**2).mean(0) - 1 / 3) < 0.01)


# --------------------------------------------------------------------------- lit planes: env and area light

PLANE_RHO = np.array([0.6, 0.5, 0.4])
QUAD_H, QUAD_SIZE, QUAD_LE = 1.0, 0.5, np.array([4.0, 3.0, 2.0])
PLANE_CAM = {"position": [0.0, 0.5, 1.5], "look_at": [0.0, 0.0, 0.2], "vfov": 30.0, "width": 16, "height": 16}


def _plane_dict(exr, quad_y, quad_rot):
    # the same structure for both checks (one compile): plane + emissive quad + lat-long map
    return {
        "camera": PLANE_CAM,
        "render": {"integrator": "path", "max_depth": 1, "spp": 256},
        "environment": {"file": str(exr), "rotate": 30.0},
        "materials": {"plane": {"model": "lambert", "rho_d": PLANE_RHO.tolist()},
                      "light": {"model": "lambert", "rho_d": 0.0, "emission": QUAD_LE.tolist()}},
        "objects": [
            {"name": "plane", "primitive": "plane", "size": [40.0, 40.0], "material": "plane"},
            {"name": "quad", "primitive": "plane", "size": [QUAD_SIZE, QUAD_SIZE], "rotate": [quad_rot, 0.0, 0.0],
             "translate": [0.0, quad_y, 0.0], "material": "light"},
        ],
    }


@pytest.fixture(scope="module")
def plane_scenes(tmp_path_factory):
    from jaxrt import image

    d = tmp_path_factory.mktemp("env")
    image.write_exr(d / "sky.exr", _sky().astype(np.float32))
    image.write_exr(d / "black.exr", np.zeros((16, 32, 3), np.float32))
    # environment only: the quad is under the plane, emitting downwards (the plane's top never sees it)
    env_lit = scene.load(_plane_dict(d / "sky.exr", -1.0, 180.0))
    # area light only: the quad above the plane facing down, a black environment of the same shape
    area_lit = scene.load(_plane_dict(d / "black.exr", QUAD_H, 180.0))
    return env_lit, area_lit


def _plane_points(sc, sub=4):
    """Hit points on y = 0 of a sub×sub grid of rays per pixel (pinhole; rows top to bottom)."""
    cam = {k: np.asarray(getattr(sc.camera, k), np.float64) for k in ("position", "look_at", "up", "vfov")}
    f = cam["look_at"] - cam["position"]
    f /= np.linalg.norm(f)
    r = np.cross(f, cam["up"])
    r /= np.linalg.norm(r)
    up = np.cross(r, f)
    w, h = sc.camera.width, sc.camera.height
    t = math.tan(math.radians(cam["vfov"]) / 2)
    s = (np.arange(sub) + 0.5) / sub
    cols = (np.arange(w)[:, None] + s[None]).reshape(-1)
    rows = (np.arange(h)[:, None] + s[None]).reshape(-1)
    x = (2 * cols / w - 1) * t * w / h
    y = (1 - 2 * rows / h) * t
    d = x[None, :, None] * r + y[:, None, None] * up + f  # (h*sub, w*sub, 3)
    tt = -cam["position"][1] / d[..., 1]
    assert np.all(tt > 0)
    return cam["position"] + tt[..., None] * d


def test_env_lit_lambert_plane_matches_quadrature(plane_scenes):
    env_lit, _ = plane_scenes
    _check_env_lit_plane(path.samples_jit(env_lit, 0, jitter=True))


def _check_env_lit_plane(L):
    m, se = _pixel_stats(L)
    # L_o = rho/pi ∫_{y>0} L_env(ω) cosθ dω, the same at every point of the plane (nothing occludes)
    n = 1024
    theta = (np.arange(n) + 0.5) / n * np.pi
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    dmap = _dirs(T, P)
    dworld = dmap @ _rot_y(30.0).T
    tex = _sky()
    rows = np.minimum((T / np.pi * 16).astype(int), 15)
    cols = np.minimum((P / (2 * np.pi) * 32).astype(int), 31)
    cos = np.maximum(dworld[..., 1], 0.0)
    irr = np.sum(tex[rows, cols] * (cos * np.sin(T))[..., None], (0, 1)) * (np.pi / n) ** 2
    ref = PLANE_RHO / np.pi * irr
    z = (m - ref) / se
    assert np.max(np.abs(z)) < K, f"max |z| = {np.max(np.abs(z)):.2f}"
    mean_se = np.sqrt(np.sum(se**2, 0)) / len(se)
    assert np.all(np.abs(m.mean(0) - ref) < K * mean_se + 2e-3 * ref)


def _rect_ff(px, pz, h, half):
    """Form factor from a differential area at (px, 0, pz) facing +y to the square |x|,|z| <= half at
    height h, parallel and facing down: signed superposition of the corner formula."""

    def corner(x, z):
        X, Y = x / h, z / h
        a, b = np.sqrt(1 + X**2), np.sqrt(1 + Y**2)
        return (X / a * np.arctan(Y / a) + Y / b * np.arctan(X / b)) / (2 * np.pi)

    x0, x1, z0, z1 = -half - px, half - px, -half - pz, half - pz
    return corner(x1, z1) - corner(x0, z1) - corner(x1, z0) + corner(x0, z0)


def test_area_light_on_lambert_plane_matches_form_factor(plane_scenes):
    _, area_lit = plane_scenes
    _check_area_lit_plane(path.samples_jit(area_lit, 0, jitter=True), area_lit)


def _check_area_lit_plane(L, area_lit):
    m, se = _pixel_stats(L)
    pts = _plane_points(area_lit)  # (16*4, 16*4, 3)
    ff = _rect_ff(pts[..., 0], pts[..., 2], QUAD_H, QUAD_SIZE / 2)
    ff = ff.reshape(16, 4, 16, 4).mean((1, 3)).reshape(-1)  # box filter over each pixel
    ref = PLANE_RHO[None] * QUAD_LE[None] * ff[:, None]  # L_o = rho/pi · E, E = pi·L_e·F
    assert ff.max() > 0.05 and ff.min() < 0.5 * ff.max()  # soft falloff across the view
    z = (m - ref) / np.maximum(se, 1e-12)
    assert np.max(np.abs(z)) < K, f"max |z| = {np.max(np.abs(z)):.2f}"
    mean_se = np.sqrt(np.sum(se**2, 0)) / len(se)
    assert np.all(np.abs(m.mean(0) - ref.mean(0)) < K * mean_se + 1e-3 * ref.mean(0))


@pytest.mark.slow  # ~15-20 s on 2 cores
def test_last_rays_to_the_emitters_trace_the_same_paths(plane_scenes, monkeypatch):
    # The GPU route (made here by telling the path tracer it is not on the CPU; these small scenes
    # run every bounce on the whole batch) with the rays of the last vertex tested against the
    # emitters only and an any-hit query (`path.LAST_RAYS_EMITTERS`) against the same rays' closest
    # hits (0): the same radiance per path, to the rounding of differently fused programs; and the
    # closed forms of the lit planes (max_depth 1: half of each pixel's light, by MIS weight, comes
    # through those rays). Each scene holds an emissive quad and an environment: the quad under the
    # plane beneath a sky whose light the rays must escape to, and above the plane under a black sky.
    env_lit, area_lit = plane_scenes
    monkeypatch.setattr(path, "_on_cpu", lambda: False)
    calls = []
    orig = path.accel.intersect_few
    monkeypatch.setattr(path.accel, "intersect_few", lambda *a, **k: calls.append(1) or orig(*a, **k))
    # and the quad above the plane under the sky: rays that meet the quad do not escape to the sky
    both = eqx.tree_at(lambda s: s.environment, area_lit, env_lit.environment)
    for sc, check in ((env_lit, _check_env_lit_plane), (area_lit, lambda L: _check_area_lit_plane(L, area_lit)),
                      (both, None)):
        out = {}
        for n in (16, 0):
            monkeypatch.setattr(path, "LAST_RAYS_EMITTERS", n)
            calls.clear()
            out[n] = np.asarray(jax.jit(lambda s: path.samples(s, 0, jitter=True))(sc))
            assert len(calls) == (n > 0)
        np.testing.assert_allclose(out[16], out[0], rtol=1e-5, atol=1e-6)
        if check is not None:
            check(out[16])


# --------------------------------------------------------------------------- thin lens


def test_thin_lens_focus_plane_sharp_and_circle_of_confusion():
    from jaxrt import camera

    f, A = 5.0, 0.4
    cam = camera.Camera(position=jnp.zeros(3), look_at=jnp.array([0.0, 0.0, -1.0]), up=jnp.array([0.0, 1.0, 0.0]),
                        vfov=jnp.asarray(30.0), aperture=jnp.asarray(A), focus_distance=jnp.asarray(f),
                        width=3, height=3)
    spp = 4096
    o, d = (np.asarray(x, np.float64).reshape(3, 3, spp, 3) for x in camera.generate_rays(cam, spp, 3, jitter=False))
    o, d = o[1, 1], d[1, 1]  # the centre pixel: its chief ray is the view axis (-z)
    for depth in (f, 2.0, 12.0):
        t = (-depth - o[:, 2]) / d[:, 2]
        p = o + t[:, None] * d
        radius = np.linalg.norm(p[:, :2], axis=-1)
        coc = A / 2 * abs(1 - depth / f)  # thin lens: blur radius on the plane at `depth`
        assert radius.max() <= coc + 1e-5
        assert radius.max() >= 0.97 * coc  # lens samples reach the rim
        # uniform lens disk: mean radius 2/3 of the rim
        assert abs(radius.mean() - 2 / 3 * coc) < 0.02 * coc + 1e-6


# --------------------------------------------------------------------------- Mitsuba 3


def _mitsuba_cornell(sc, spp, seeds, depth):
    """Mitsuba 3 scalar_rgb `path` on exactly the triangles of `sc` (one OBJ per material)."""
    import os
    import tempfile

    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    v = np.asarray(sc.geometry.vertices, np.float64)
    faces = np.asarray(sc.geometry.faces)
    mat = np.asarray(sc.geometry.material)
    cam = sc.camera
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": depth + 1},  # Mitsuba counts the camera ray
         "sensor": {"type": "perspective", "fov": float(cam.vfov), "fov_axis": "y",
                    "to_world": mi.ScalarTransform4f().look_at(origin=np.asarray(cam.position).tolist(),
                                                               target=np.asarray(cam.look_at).tolist(),
                                                               up=np.asarray(cam.up).tolist()),
                    "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                    "sampler": {"type": "independent", "sample_count": spp}}}
    with tempfile.TemporaryDirectory() as tmp:
        for m, name in enumerate(sc.materials.names):
            sel = faces[mat == m]
            if not len(sel):
                continue
            fn = os.path.join(tmp, f"{name}.obj")
            with open(fn, "w") as fh:
                fh.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in v)
                fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in sel)
            k, row = int(sc.materials.model_id[m]), int(sc.materials.row[m])
            assert sc.materials.models[k] == "lambert"
            rho = np.asarray(sc.materials.params[k]["rho_d"][row], np.float64).tolist()
            ent = {"type": "obj", "filename": fn, "face_normals": True,
                   "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse",
                                                         "reflectance": {"type": "rgb", "value": rho}}}}
            em = np.asarray(sc.area_lights.emission[m], np.float64)
            if em.max() > 0:
                ent["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": em.tolist()}}
            d[name] = ent
        ms = mi.load_dict(d)
        return np.stack([np.asarray(mi.render(ms, seed=s), np.float64)[..., :3] for s in seeds])


def _compare_cornell(res, spp, depth, mi_spp, mi_runs, block):
    sc = scene.load("cornell_area", overrides={"camera.width": res, "camera.height": res, "render.spp": spp,
                                               "render.max_depth": depth})
    L = np.asarray(path.samples_jit(sc, 0, jitter=True), np.float64)  # (P, S, 3)
    ours = L.reshape(res // block, block, res // block, block, spp, 3)
    ref = _mitsuba_cornell(sc, mi_spp, range(mi_runs), depth).reshape(mi_runs, res // block, block, res // block,
                                                                        block, 3)
    # region means: blocks of block×block pixels; ours' SE from the samples, Mitsuba's from its runs
    o_mean = ours.mean((1, 3, 4))
    o_se = ours.mean((1, 3)).std(2, ddof=1) / math.sqrt(spp)
    r_runs = ref.mean((2, 4))
    r_mean = r_runs.mean(0)
    r_se = r_runs.std(0, ddof=1) / math.sqrt(mi_runs)
    z = (o_mean - r_mean) / np.sqrt(o_se**2 + r_se**2)
    assert np.max(np.abs(z)) < K, f"max |z| = {np.max(np.abs(z)):.2f}\n{np.round(z[..., 0], 1)}"
    # the whole image per channel (regions are independent; the channels of one path are not)
    img_se = np.sqrt(np.sum(o_se**2, (0, 1)) / o_se[..., 0].size**2 + r_runs.mean((1, 2)).var(0, ddof=1) / mi_runs)
    z_img = (o_mean.mean((0, 1)) - r_mean.mean((0, 1))) / img_se
    assert np.all(np.abs(z_img) < K), z_img
    assert r_mean.mean() > 0.05  # a lit image


@pytest.mark.mitsuba
@pytest.mark.data
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_cornell_area_light_agrees_with_mitsuba(data_dir):
    _compare_cornell(res=16, spp=512, depth=4, mi_spp=512, mi_runs=8, block=4)


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.data
def test_cornell_area_light_agrees_with_mitsuba_deep(data_dir):
    _compare_cornell(res=32, spp=512, depth=8, mi_spp=512, mi_runs=8, block=4)


# --------------------------------------------------------------------------- scene input


def _base(**extra):
    d = {"camera": {"position": [0, 0, 3], "look_at": [0, 0, 0], "width": 4, "height": 4},
         "materials": {"m": {"model": "lambert"}},
         "objects": [{"primitive": "sphere", "material": "m"}]}
    d.update(extra)
    return d


@pytest.mark.parametrize("extra, needle", [
    ({}, "lights"),  # no point light, no environment, no emitter: nothing lights the scene
    ({"environment": {"radiance": 1.0, "file": "a.exr"}}, "exactly one of"),
    ({"environment": {}}, "exactly one of"),
    ({"environment": {"file": "sky.png"}}, "OpenEXR"),
    ({"environment": {"file": "missing.hdr"}}, "no such file"),
    ({"environment": {"file": "missing.exr"}}, "no such file"),
    ({"environment": {"radiance": [1, -1, 1]}}, "radiance"),
    ({"environment": {"radiance": 1.0, "scale": -2.0}}, "scale"),
    ({"environment": {"radiance": 1.0, "sun": 1}}, "unknown key"),
    ({"environment": {"radiance": 1.0}, "materials": {"m": {"model": "glass", "emission": 1.0}}}, "emission"),
    ({"environment": {"radiance": 1.0}, "materials": {"m": {"model": "lambert", "emission": [1, 2]}}}, "emission"),
    ({"environment": {"radiance": 1.0}, "render": {"integrator": "bdpt"}}, "integrator"),
])
def test_bad_path_scene_input(extra, needle, tmp_path):
    with pytest.raises(InputError, match=needle):
        scene.parse(_base(**extra), base_dir=tmp_path)


def test_emission_and_environment_build(tmp_path):
    d = _base(environment={"radiance": [0.5, 0.5, 0.5], "scale": 2.0},
              materials={"m": {"model": "lambert", "emission": [1.0, 2.0, 3.0]}})
    sc = scene.load(d)
    assert sc.lights.count == 0
    assert sc.area_lights.count == sc.geometry.faces.shape[0]
    np.testing.assert_allclose(np.asarray(sc.area_lights.emission), [[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(np.asarray(envmap.radiance(sc.environment, jnp.array([[0.0, 1.0, 0.0]]))), [[1, 1, 1]])


def test_whitted_escaping_rays_see_the_environment(tmp_path):
    # Whitted's shade uses escaped_radiance for rays that leave the scene: the environment when
    # there is one (here a rotated lat-long map), else `background`
    from jaxrt import image, integrators

    image.write_exr(tmp_path / "sky.exr", _sky().astype(np.float32))
    d = _base(environment={"file": "sky.exr", "rotate": 30.0}, render={"background": [0.1, 0.2, 0.3]})
    sc = scene.load(d, base_dir=tmp_path)
    theta, phi = np.array([0.3, 1.2, 2.5]), np.array([0.4, 2.0, 5.5])
    dirs = _dirs(theta, phi) @ _rot_y(30.0).T
    want = _sky()[(theta / np.pi * 16).astype(int), (phi / (2 * np.pi) * 32).astype(int)]
    got = np.asarray(direct.escaped_radiance(sc, jnp.asarray(dirs, jnp.float32)))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    no_env = scene.load(_base(lights=[{"position": [0, 3, 0], "intensity": 1.0}], render={"background": 0.5}))
    np.testing.assert_allclose(np.asarray(direct.escaped_radiance(no_env, jnp.asarray(dirs, jnp.float32))), 0.5)


def _write_rgbe(path, rgb):
    """A flat (uncompressed) Radiance RGBE file written from the format's definition (Ward, Graphics
    Gems II): shared exponent e with mantissas floor(c / 2^e · 256), independent of OpenCV."""
    m = rgb.max(-1)
    e = np.where(m > 1e-32, np.floor(np.log2(np.maximum(m, 1e-32))) + 1, 0)
    scale = np.where(m > 1e-32, 256.0 / np.exp2(e), 0.0)
    mant = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    exp = np.where(m > 1e-32, e + 128, 0).astype(np.uint8)
    h, w = rgb.shape[:2]
    with open(path, "wb") as f:
        f.write(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
        f.write(np.concatenate([mant, exp[..., None]], axis=-1).tobytes())


def test_radiance_hdr_environment_matches_the_exr_one(tmp_path):
    """A .hdr map (written independently of the reader) lights the scene like the same map as EXR:
    same orientation (row 0 = +y), channel order and scale, within RGBE's 8-bit mantissas."""
    from jaxrt import image

    sky = _sky().astype(np.float32) + np.asarray([0.0, 0.1, 0.3], np.float32)  # channels differ
    _write_rgbe(tmp_path / "sky.hdr", sky)
    image.write_exr(tmp_path / "sky.exr", sky)
    hdr, exr = envmap.load(tmp_path / "sky.hdr"), envmap.load(tmp_path / "sky.exr")
    # RGBE keeps 8 bits below the pixel's largest channel: error < max channel / 128 per channel
    a, b = np.asarray(hdr.texels), np.asarray(exr.texels)
    assert np.all(np.abs(a - b) <= b.max(-1, keepdims=True) * 2.0 ** -7 + 1e-6)
    d = np.asarray([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], np.float32)
    la, lb = np.asarray(envmap.radiance(hdr, d)), np.asarray(envmap.radiance(exr, d))
    assert np.all(np.abs(la - lb) <= lb.max(-1, keepdims=True) * 2.0 ** -7 + 1e-6)
    assert np.ptp(lb[:, 2] - lb[:, 0]) >= 0 and np.all(lb[:, 2] > lb[:, 0])  # blue offset: channels not swapped
    (tmp_path / "bad.hdr").write_bytes(b"not an image")
    with pytest.raises(InputError, match="bad.hdr"):
        envmap.load(tmp_path / "bad.hdr")


@pytest.mark.parametrize("k", [0, 1, 7, 2**31 - 1])
def test_fold_in_uniforms_are_jax_random_bit_for_bit(k):
    # the unrolled Threefry (the path tracer's numbers with another key type, and the 20-round
    # block it shares with `counter_uniforms`) must be exactly jax.random.uniform(fold_in(key, k), (8,))
    from jaxrt.integrators.common import fold_in_uniforms

    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(12345), i))(jnp.arange(4099, dtype=jnp.uint32))
    ref = jax.vmap(lambda pk: jax.random.uniform(jax.random.fold_in(pk, k), (8,)))(keys)
    got = jax.jit(fold_in_uniforms, static_argnums=2)(keys, jnp.int32(k), 8)
    assert got.shape == (4099, 8) and got.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))


# Random123's known-answer vectors for Threefry-2x32 (its tests/kat_vectors): rounds, key, counter,
# the block's two output words. Independent of JAX: the 13-round rows are not a JAX PRNG at all.
_THREEFRY_KAT = [
    (13, (0, 0), (0, 0), (0x9D1C5EC6, 0x8BD50731)),
    (13, (0xFFFFFFFF, 0xFFFFFFFF), (0xFFFFFFFF, 0xFFFFFFFF), (0xFD36D048, 0x2D17272C)),
    (13, (0x13198A2E, 0x03707344), (0x243F6A88, 0x85A308D3), (0xBA3E4725, 0xF27D669E)),
    (20, (0, 0), (0, 0), (0x6B200159, 0x99BA4EFE)),
    (20, (0x13198A2E, 0x03707344), (0x243F6A88, 0x85A308D3), (0xC4923A9C, 0x483DF7A0)),
    (32, (0xFFFFFFFF, 0xFFFFFFFF), (0xFFFFFFFF, 0xFFFFFFFF), (0x6E2FE0D0, 0xB1B76F82)),
]


@pytest.mark.parametrize("rounds, key, counter, words", _THREEFRY_KAT)
def test_threefry_block_matches_random123_known_answers(rounds, key, counter, words):
    from jaxrt._random import threefry2x32

    u32 = jnp.uint32
    got = threefry2x32(u32(key[0]), u32(key[1]), u32(counter[0]), u32(counter[1]), rounds=rounds)
    assert (int(got[0]), int(got[1])) == words


def test_unrolled_fold_in_is_jax_random_fold_in_bit_for_bit():
    # the paths' keys (one key, many data) and the high word of a tile's path index (a key per datum)
    from jaxrt import _random

    data = jnp.asarray([0, 1, 7, 2**31 - 1, 2**32 - 1, 123456789], jnp.uint32)
    key = jax.random.key(2024)
    ref = jax.vmap(lambda d: jax.random.fold_in(key, d))(data)
    got = jax.jit(_random.fold_in)(key, data)
    np.testing.assert_array_equal(np.asarray(jax.random.key_data(got)), np.asarray(jax.random.key_data(ref)))
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(3), i))(jnp.arange(6, dtype=jnp.uint32))
    ref = jax.vmap(jax.random.fold_in)(keys, data)
    got = jax.jit(_random.fold_in)(keys, data)
    np.testing.assert_array_equal(np.asarray(jax.random.key_data(got)), np.asarray(jax.random.key_data(ref)))


def test_counter_uniforms_are_threefry13_words_and_look_independent():
    """The path tracer's per-bounce numbers: element 2j and 2j+1 at bounce k are the two words of the
    Threefry-2x32-13 block (key, counter (k, j)) (checked on Random123's all-zero vector), mapped to
    [0, 1) by their top 23 bits; over 2^17 keys each of the 8 columns is uniform and no two columns,
    nor a column and the next bounce's, are correlated beyond chance."""
    from jaxrt.integrators.common import counter_uniforms

    zero = jax.random.wrap_key_data(jnp.zeros((1, 2), jnp.uint32))
    words = np.array([0x9D1C5EC6, 0x8BD50731], np.uint64)
    expect = ((words >> 9) / 2.0**23).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(counter_uniforms(zero, 0, 2))[0], expect)
    n = 2**17
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(7), i))(jnp.arange(n, dtype=jnp.uint32))
    f = jax.jit(counter_uniforms, static_argnums=2)
    u0, u1 = np.asarray(f(keys, jnp.uint32(3), 8), np.float64), np.asarray(f(keys, jnp.uint32(4), 8), np.float64)
    assert u0.shape == (n, 8) and u0.min() >= 0.0 and u0.max() < 1.0
    se = 1.0 / np.sqrt(n)
    # uniform: mean 1/2 (sd 0.289/sqrt(n)), variance 1/12, a 64-bin histogram's chi-square (63 dof)
    assert np.all(np.abs(u0.mean(0) - 0.5) < 5 * 0.289 * se)
    assert np.all(np.abs(u0.var(0) - 1 / 12) < 5 * 0.0745 * se)
    counts = np.stack([np.bincount((u0[:, c] * 64).astype(int), minlength=64) for c in range(8)])
    chi2 = ((counts - n / 64) ** 2 / (n / 64)).sum(1)
    assert np.all(chi2 < 120), chi2  # P(chi2_63 > 120) ~ 1e-5
    # independent: correlations of the 8 columns with each other and with the next bounce's
    c = np.corrcoef(np.concatenate([u0, u1], axis=1).T)
    off = c[~np.eye(16, dtype=bool)]
    assert np.all(np.abs(off) < 5 * se), np.abs(off).max()


@pytest.mark.parametrize("loop", [True, False], ids=["loop", "unrolled"])
def test_envmap_row_search_matches_numpy_searchsorted(loop, monkeypatch):
    # the environment sampler's per-sample binary search in a row of the 2-D cdf table must count
    # exactly what numpy's searchsorted(side="right") counts, ties and empty bins included, as the
    # CPU's loop and as the GPU's unrolled steps
    monkeypatch.setattr(envmap, "_search_in_loop", lambda: loop)
    rng = np.random.default_rng(5)
    for m in (2, 3, 64, 129, 130):
        w = rng.random((17, m - 1)) * (rng.random((17, m - 1)) < 0.6)  # zero-width bins (plateaus)
        cdf = np.concatenate([np.zeros((17, 1)), np.cumsum(w, 1)], 1).astype(np.float32)
        cdf /= np.maximum(cdf[:, -1:], 1e-30)
        row = rng.integers(0, 17, 5000)
        u = rng.random(5000).astype(np.float32)
        u[:200] = cdf[row[:200], rng.integers(0, m, 200)]  # exactly on entries (ties)
        u[200:210] = 0.0
        got = np.asarray(jax.jit(envmap._count_le)(jnp.asarray(cdf), jnp.asarray(row, jnp.int32), jnp.asarray(u)))
        ref = np.array([np.searchsorted(cdf[r], x, side="right") for r, x in zip(row, u)])
        np.testing.assert_array_equal(got, ref)


def test_envmap_atan2_and_acos_within_a_few_ulps_of_float64():
    # the environment map's written-out atan2 and acos (`envmap._atan2`, `_acos`) against numpy in
    # float64: every octant, ratios near the tan(π/8) switch, huge and tiny components, signed
    # zeros, and cosines at ±1 and next to them
    rng = np.random.default_rng(7)
    n = 200_000
    y = rng.standard_normal(n) * np.exp(rng.uniform(-30, 30, n))
    x = rng.standard_normal(n) * np.exp(rng.uniform(-30, 30, n))
    near = rng.uniform(0.40, 0.43, 1000) * rng.choice([-1, 1], 1000)
    y = np.concatenate([y, near, [0.0, -0.0, 0.0, -0.0, 1.0, -1.0, 2.0, -2.0, 3.0, 1e-38]])
    x = np.concatenate([x, np.ones(1000), [1.0, 1.0, -1.0, -1.0, 0.0, 0.0, -0.0, -2.0, 3.0, -1.0]])
    y32, x32 = y.astype(np.float32), x.astype(np.float32)
    got = np.asarray(jax.jit(envmap._atan2)(jnp.asarray(y32), jnp.asarray(x32)), np.float64)
    ref = np.arctan2(y32.astype(np.float64), x32.astype(np.float64))
    ulp = np.spacing(np.abs(ref).astype(np.float32)).astype(np.float64)
    assert np.max(np.abs(got - ref) / ulp) < 4.0
    np.testing.assert_array_equal(np.signbit(got[-10:]), np.signbit(ref[-10:]))
    c = np.concatenate([rng.uniform(-1, 1, n), [1.0, -1.0, 0.0, -0.0, 1 - 2**-24, -1 + 2**-24, 0.5, -0.5]])
    c32 = c.astype(np.float32)
    got = np.asarray(jax.jit(envmap._acos)(jnp.asarray(c32)), np.float64)
    ref = np.arccos(c32.astype(np.float64))
    ulp = np.spacing(np.maximum(np.abs(ref), 1e-30).astype(np.float32)).astype(np.float64)
    assert np.max(np.abs(got - ref) / ulp) < 4.0
    assert got[-8] == 0.0 and abs(got[-7] - np.pi) < 3e-7
