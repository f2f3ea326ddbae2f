"""Tiled rendering (`jaxrt.render_tiles`, `integrators.tile`) against the untiled render
(`integrators.frame`), the memory budget, and Ctrl-C in `jaxrt render`.

The references are independent of the tiling code: `jax.random.uniform` for the camera's random
numbers, the whole-image `integrators.frame` for images and AOVs, XLA's own `memory_analysis()` for
memory, and the wall clock for Ctrl-C. Two small built scenes keep compilation short: a Whitted
scene (glass under the default ray budget, a mirror, Phong, a checker texture, two point lights)
and a path-traced one (an emissive quad, a point light, glossy and diffuse surfaces), at 45x37
pixels, so no tile size below divides the image.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import camera as C
from jaxrt import integrators, render_tiles
from jaxrt import scene as S
from jaxrt.errors import InputError

REPO = Path(__file__).resolve().parents[1]
W, H = 45, 37
# XLA:CPU evaluates the same per-ray arithmetic identically for every program shape only without
# FMA contraction and YNNPACK reduction fusions (see `jaxrt.render_tiles`)
EXACT_FLAGS = "--xla_cpu_max_isa=AVX --xla_cpu_experimental_ynn_fusion_type="


def whitted_doc(w=W, h=H, spp=2):
    return {
        "camera": {"position": [0.0, 1.6, 5.0], "look_at": [0.0, 0.7, 0.0], "vfov": 38.0, "width": w, "height": h},
        "lights": [{"position": [3.0, 6.0, 4.0], "intensity": [60.0, 50.0, 40.0]},
                   {"position": [-4.0, 3.0, 2.0], "intensity": [10.0, 20.0, 30.0]}],
        "materials": {
            "glass": {"model": "glass", "n_t": 1.5},
            "floor": {"model": "lambert", "rho_d": {"checker": [[0.8, 0.8, 0.8], [0.1, 0.2, 0.1]], "scale": 4},
                      "delta": 0.3},
            "plastic": {"model": "phong", "rho_d": [0.5, 0.1, 0.1], "rho_s": 0.4, "s": 40.0, "delta": 0.2},
        },
        "objects": [
            {"name": "ball", "primitive": "sphere", "radius": 0.9, "subdivisions": 2, "translate": [-0.6, 0.9, 0.3],
             "material": "glass"},
            {"name": "floor", "primitive": "plane", "size": [40.0, 40.0], "material": "floor"},
            {"name": "red", "primitive": "sphere", "radius": 0.5, "subdivisions": 2, "translate": [1.2, 0.5, -0.5],
             "material": "plastic"},
        ],
        "render": {"max_depth": 4, "spp": spp, "background": [0.05, 0.06, 0.09]},
    }


def path_doc(w=W, h=H, spp=6):
    return {
        "camera": {"position": [0.0, 1.5, 5.0], "look_at": [0.0, 0.8, 0.0], "vfov": 40.0, "width": w, "height": h},
        "lights": [{"position": [2.0, 3.0, 3.0], "intensity": 8.0}],
        "materials": {
            "white": {"model": "lambert", "rho_d": 0.7},
            "glossy": {"model": "phong", "rho_d": [0.2, 0.4, 0.6], "rho_s": 0.5, "s": 30.0, "delta": 0.1},
            "lamp": {"model": "lambert", "rho_d": 0.0, "emission": [6.0, 5.0, 4.0]},
        },
        "objects": [
            {"name": "floor", "primitive": "plane", "size": [10.0, 10.0], "material": "white"},
            {"name": "ball", "primitive": "sphere", "radius": 0.8, "subdivisions": 2, "translate": [0.0, 0.8, 0.0],
             "material": "glossy"},
            {"name": "lamp", "primitive": "plane", "size": [1.5, 1.5], "rotate": [180.0, 0.0, 0.0],
             "translate": [0.0, 3.0, 0.0], "material": "lamp"},
        ],
        "render": {"integrator": "path", "max_depth": 4, "spp": spp},
    }


def _frame(sc):
    img, aovs = integrators.frame(sc, aovs=True)
    return np.asarray(img), {k: np.asarray(v) for k, v in aovs.items()}


@pytest.fixture(scope="module")
def whitted():
    sc = S.load(whitted_doc())
    return sc, *_frame(sc)


@pytest.fixture(scope="module")
def path():
    sc = S.load(path_doc())
    return sc, *_frame(sc)


# ---- random numbers and rays: the tile's are the image's -------------------------------------------

@pytest.mark.parametrize("partitionable", [True, False])
def test_uniform_at_is_jax_random_uniform(partitionable):
    with jax.threefry_partitionable(partitionable):
        key = jax.random.fold_in(jax.random.key(11), 3)
        for size in (7, 4 * 13 * 7):  # odd sizes: the original layout pads its second half
            ref = np.asarray(jax.random.uniform(key, (size,), jnp.float32))
            idx = np.random.default_rng(size).permutation(size)
            got = np.asarray(jax.jit(lambda k, i, n=size: C.uniform_at(k, i, n))(key, idx))
            np.testing.assert_array_equal(got.view(np.uint32), ref[idx].view(np.uint32))


_CAMERA = dict(position=[1.0, 2.0, 3.0], look_at=[0.0, 0.5, -1.0], up=[0.0, 1.0, 0.0], vfov=35.0, aperture=0.2,
               focus_distance=5.0, width=13, height=7)
# (row0, col0, sample0, height, width, samples) of windows of the 7x13 image's 5 samples per pixel
_WINDOWS = [(2, 3, 1, 4, 6, 3), (5, 9, 4, 2, 4, 1)]


def window_ray_pairs():
    """(window's rays, the image's rays of the same pixels and samples) for each of `_WINDOWS`, as
    (origins, directions) pairs of numpy arrays (th, tw, sb, 3)."""
    cam = C.Camera(**{k: v if isinstance(v, int) else jnp.asarray(v) for k, v in _CAMERA.items()})
    gen = jax.jit(C.generate_rays, static_argnames=("spp", "jitter"))
    o, d = (np.asarray(x).reshape(7, 13, 5, 3) for x in gen(cam, 5, 9))
    for r0, c0, s0, th, tw, sb in _WINDOWS:
        win = C.Window(jnp.int32(r0), jnp.int32(c0), jnp.int32(s0), jnp.int32(sb), th, tw, sb)
        ow, dw = (np.asarray(x).reshape(th, tw, sb, 3) for x in gen(cam, 5, 9, window=win))
        yield (ow, dw), (o[r0:r0 + th, c0:c0 + tw, s0:s0 + sb], d[r0:r0 + th, c0:c0 + tw, s0:s0 + sb]), (o, d)


def test_window_rays_are_the_image_rays():
    """A window's rays are the image's rays of its pixels and samples (same pixel, same random
    counters): bit for bit where XLA evaluates both programs' arithmetic alike (the exact flags:
    `test_tiles_are_bit_identical_where_the_arithmetic_is_shape_independent`), within rounding here,
    where XLA:CPU may contract a·b + c into an FMA in one program and not in the other. Rounding is
    far below what the wrong pixel, sample or random number would change (checked below)."""
    # a few ulps of the terms: of 1 for a unit direction's components (some cancel to ~0)
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=0, atol=4 * 2.0**-24)  # noqa: E731
    for i, ((ow, dw), (oi, di), (o, d)) in enumerate(window_ray_pairs()):
        np.testing.assert_array_max_ulp(ow, oi, maxulp=4)
        close(dw, di)
        if i == 0:  # the tolerance tells neighbours apart: one sample or one column off fails it
            r0, c0, s0, th, tw, sb = _WINDOWS[0]
            for shifted in (d[r0:r0 + th, c0:c0 + tw, s0 + 1:s0 + sb + 1],
                            d[r0:r0 + th, c0 + 1:c0 + tw + 1, s0:s0 + sb]):
                with pytest.raises(AssertionError):
                    close(dw, shifted)


# ---- plans ------------------------------------------------------------------------------------------

def _coverage(p):
    n = np.zeros((p.height, p.width, p.spp), int)
    th, tw, sb = p.shape
    for (r, c), (r0, c0), (s0, count) in p.steps:
        assert 0 <= r0 <= r < r0 + th <= p.height and 0 <= c0 <= c < c0 + tw <= p.width  # inside the image
        assert 1 <= count <= sb and s0 + count <= p.spp
        n[r:min(r + th, p.height), c:min(c + tw, p.width), s0:s0 + count] += 1
    return n


@pytest.mark.parametrize("w, h, spp, rays", [(45, 37, 2, 700), (45, 37, 6, 100), (45, 37, 1, 37), (3, 2, 5, 2),
                                              (1000, 3, 1, 900)])
def test_plan_covers_every_pixel_sample_once(w, h, spp, rays):
    sc = S.load(whitted_doc(w, h, spp))
    p = render_tiles.plan(sc, memory="8G", max_tile_rays=rays)
    assert p.shape is not None and p.shape[0] * p.shape[1] * p.shape[2] <= rays
    np.testing.assert_array_equal(_coverage(p), 1)


def test_plan_tiles_within_the_budget_and_keeps_samples_together():
    sc = S.load(whitted_doc(512, 512, 4))
    per_sample, per_pixel = render_tiles.tile_cost(sc)
    budget = 40 << 20
    p = render_tiles.plan(sc, memory=budget)
    th, tw, sb = p.shape
    assert sb == 4 and tw == 512 and th % 4 == 0  # full-width strips of whole 8x4 blocks, all samples
    assert p.fixed + th * tw * (sb * per_sample + per_pixel) <= budget
    assert p.tiles == -(-512 // th)


# ---- images: tiled == untiled ---------------------------------------------------------------------

def _close(a, b):
    """With the default XLA flags the two program shapes round each ray's floats differently by a
    few ulps, which can flip a rare discrete decision (`jaxrt.render_tiles`): 99 % of the pixels
    within 1e-4 relative, and the mean difference at rounding level. A tile with the wrong random
    numbers or pixels fails both (its noise differs at every pixel)."""
    a, b = (x.reshape(x.shape[0], x.shape[1], -1).astype(np.float64) for x in (a, b))
    d = np.abs(a - b).max(-1)
    rel = d / np.maximum(np.abs(b).max(-1), 1e-2)
    assert np.mean(rel > 1e-4) <= 0.01, np.quantile(rel, 0.99)
    assert d.mean() <= 1e-5 * max(np.abs(b).mean(), 1e-3), d.mean()


def _check_aovs(got, ref):
    assert set(got) == set(ref) == {"depth", "normal", "albedo", "object_id"}
    assert np.mean(got["object_id"] != ref["object_id"]) <= 0.01
    for k in ("depth", "normal", "albedo"):
        _close(got[k], ref[k])


def test_whitted_tiles_equal_the_frame(whitted):
    sc, ref, ref_aovs = whitted
    p = render_tiles.plan(sc, memory="8G", aovs=True, max_tile_rays=400)  # 200 pixels x 2 samples
    assert p.shape[2] == 2 and p.tiles > 4 and H % p.shape[0]  # strips; the last one overlaps
    img, aovs = render_tiles.render(sc, aovs=True, use_plan=p)
    assert img.shape == (H, W, 3) and img.dtype == np.float32 and np.isfinite(img).all() and img.max() > 0.1
    _close(img, ref)
    _check_aovs(aovs, ref_aovs)


def test_path_tiles_and_sample_batches_equal_the_frame(path):
    sc, ref, ref_aovs = path
    p = render_tiles.plan(sc, memory="8G", aovs=True, max_tile_rays=100)  # batches of 3 of the 6 samples
    assert p.shape[2] == 3 and len({s for _, _, s in p.steps}) == 2 and W % p.shape[1] and H % p.shape[0]
    img, aovs = render_tiles.render(sc, aovs=True, use_plan=p)
    assert np.isfinite(img).all() and img.max() > 0.1
    _close(img, ref)
    _check_aovs(aovs, ref_aovs)


_EXACT = r"""
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import test_tiles as T
from jaxrt import integrators, render_tiles, scene as S
out = {"window_rays": all(np.array_equal(a, b) for w, i, _ in T.window_ray_pairs() for a, b in zip(w, i))}
for name, doc, rays in (("whitted", T.whitted_doc(), 400), ("path", T.path_doc(), 240), ("batches", T.path_doc(), 100)):
    sc = S.load(doc)
    ref, ref_aovs = integrators.frame(sc, aovs=True)
    ref = np.asarray(ref)
    p = render_tiles.plan(sc, memory="8G", aovs=True, max_tile_rays=rays)
    img, aovs = render_tiles.render(sc, aovs=True, use_plan=p)
    bad_aovs = [k for k in aovs if not np.array_equal(aovs[k], np.asarray(ref_aovs[k]))]
    rel = float(np.max(np.abs(img - ref) / np.maximum(ref, 1e-30)))
    out[name] = dict(shape=p.shape, batches=len({s for _, _, s in p.steps}), spp=p.spp, equal=bool(np.array_equal(img, ref)),
                     rel=rel, bad_aovs=bad_aovs, max=float(ref.max()))
print(json.dumps(out))
"""


@pytest.mark.slow  # five compilations in a fresh process: about 75 s on this 2-core CPU
def test_tiles_are_bit_identical_where_the_arithmetic_is_shape_independent(tmp_path):
    """With FMA contraction and YNNPACK reductions off, every ray's arithmetic is the same in the tile
    program and the frame program, so the tiled image is the frame's bit for bit (whole-spp tiles),
    and within the float32 re-summation of the batch means when samples are split: the frame sums
    spp non-negative samples (≤ spp·2⁻²⁴ relative error, first order), the tiles sum sb per batch and
    then nb batches (≤ (sb + nb)·2⁻²⁴), so |Δ| ≤ (2·spp + nb)·2⁻²⁴·pixel."""
    import json

    env = dict(os.environ, XLA_FLAGS=EXACT_FLAGS, JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, "-c", _EXACT, str(Path(__file__).parent)], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["window_rays"]  # a window's rays are the image's bit for bit (`test_window_rays_are_the_image_rays`)
    for name in ("whitted", "path"):
        o = out[name]
        assert o["shape"][2] == o["spp"] and o["batches"] == 1 and o["max"] > 0.1
        assert o["equal"] and o["bad_aovs"] == [], o
    b = out["batches"]
    assert b["batches"] == 2 and not b["bad_aovs"], b
    assert 0 < b["rel"] <= (2 * b["spp"] + b["batches"]) * 2.0**-24, b


# ---- memory ---------------------------------------------------------------------------------------

# the tiles of the image tests above, so the programs measured here are already compiled
TILE_RAYS = {"whitted": 400, "path": 100}


@pytest.mark.parametrize("which", ["whitted", "path"])
def test_compiled_tile_fits_the_budget_and_the_bound_holds(which, request):
    sc = request.getfixturevalue(which)[0]
    per_sample, per_pixel = render_tiles.tile_cost(sc, aovs=True)
    th, tw, sb = render_tiles.plan(sc, memory="8G", aovs=True, max_tile_rays=TILE_RAYS[which]).shape
    bound = th * tw * (sb * per_sample + per_pixel)
    budget = render_tiles.plan(sc, memory="8G", aovs=True).fixed + bound  # room for exactly that tile
    p = render_tiles.compile_plan(sc, render_tiles.plan(sc, memory=budget, aovs=True), aovs=True)
    assert p.shape == (th, tw, sb)
    # XLA's own account of the program that runs: temporaries + outputs + code
    win = C.Window(jnp.int32(0), jnp.int32(0), jnp.int32(0), jnp.int32(sb), th, tw, sb)
    m = integrators.tile.lower(sc, win, aovs=True).compile().memory_analysis()
    measured = m.temp_size_in_bytes + m.output_size_in_bytes + m.generated_code_size_in_bytes
    assert measured == p.tile_bytes > 0
    assert measured <= bound  # the planning bound is an upper bound
    assert p.fixed + measured <= budget


@pytest.mark.slow  # two or three new tile compilations
@pytest.mark.parametrize("pixels", [150, 600])
def test_an_underestimated_tile_is_measured_and_shrunk_to_fit(whitted, monkeypatch, pixels):
    """`compile_plan` measures what it compiled: with `tile_cost` 8x too low the plan asks for a tile
    (150) or the whole frame (600) that does not fit; the measurement shrinks it until it does."""
    sc = whitted[0]
    true_cost = render_tiles.tile_cost(sc)
    fixed = render_tiles.plan(sc, memory="8G").fixed
    budget = fixed + pixels * sum(true_cost)
    monkeypatch.setattr(render_tiles, "tile_cost", lambda scene, aovs=False: (true_cost[0] // 8, true_cost[1] // 8))
    p0 = render_tiles.plan(sc, memory=budget)
    p = render_tiles.compile_plan(sc, p0)
    asked = H * W if p0.shape is None else p0.shape[0] * p0.shape[1]
    assert (p0.shape is None) == (pixels == 600) and asked > 2 * pixels
    assert p.shape[0] * p.shape[1] < asked and fixed + p.tile_bytes <= budget
    np.testing.assert_array_equal(_coverage(p), 1)


def test_a_job_that_cannot_fit_one_tile_is_refused_before_work(whitted):
    sc = whitted[0]
    with pytest.raises(InputError, match=r"--memory or JAXRT_MEMORY") as e:
        render_tiles.plan(sc, memory="64K")
    assert "\n" not in str(e.value) and "64 KiB" in str(e.value)


def test_cli_refuses_a_budget_too_small_in_one_line(tmp_path, monkeypatch, capsys):
    from jaxrt import cli

    out = tmp_path / "x.exr"
    monkeypatch.setenv("JAXRT_MEMORY", "100K")
    assert cli.main(["render", "spheres", "--width", "64", "--height", "64", "-q", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxrt render: error:") and "\n" not in err and "JAXRT_MEMORY" in err and "100 KiB" in err
    monkeypatch.delenv("JAXRT_MEMORY")
    assert cli.main(["render", "spheres", "--memory", "lots", "-q", "-o", str(out)]) == 2
    assert "--memory" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_render_that_fits_runs_the_compiled_frame_without_compiling(whitted):
    from jax import monitoring

    sc, ref, ref_aovs = whitted  # the fixture called integrators.frame(sc, aovs=True)
    compiles, active = [], [True]

    def listen(event, duration, **kw):
        if active[0] and event == "/jax/core/compile/backend_compile_duration":
            compiles.append(event)

    monitoring.register_event_duration_secs_listener(listen)
    tiles_before = integrators.tile._cache_size()
    try:
        img, aovs = render_tiles.render(sc, memory="auto", aovs=True)
    finally:
        active[0] = False
    assert compiles == [] and integrators.tile._cache_size() == tiles_before
    np.testing.assert_array_equal(img, ref)
    for k in ref_aovs:
        np.testing.assert_array_equal(aovs[k], ref_aovs[k])



@pytest.mark.parametrize("max_rays", [None, pytest.param(40, marks=pytest.mark.slow)])  # one frame; tiles of at most 40 ray samples
def test_compile_ahead_compiles_the_render_program_while_the_tree_builds(max_rays):
    """`render_tiles.compile_ahead` on the scene `scene.build` hands to on_shapes (its BVH arrays
    shapes only) compiles, in its own thread, the program the render of the built scene then runs:
    the render compiles nothing more, the render program is compiled once as without
    `compile_ahead` (a scene of other, unused shapes), and the image is that of the frame program
    compiled from the built scene."""
    from jax import monitoring

    events, active = [], [True]
    programs = ("jit(call)", "jit(_frame)", "jit(_tile)")  # a stored program's, or jax.jit's with the cache off

    def listen(event, duration, **kw):
        if active[0] and event == "/jax/core/compile/backend_compile_duration":
            events.append((threading.current_thread().name, kw.get("fun_name") in programs))

    def job(w, h, ahead):
        threads, n0 = [], len(events)
        on_shapes = (lambda s: threads.append(render_tiles.compile_ahead(s, max_tile_rays=max_rays))) if ahead else None
        sc = S.build(S.parse(whitted_doc(w=w, h=h, spp=1)), on_shapes=on_shapes)  # shapes no other test compiles
        for t in threads:
            t.join()
        n1 = len(events)
        img = render_tiles.render(sc, max_tile_rays=max_rays)
        return sc, img, threads, events[n0:n1], events[n1:]

    monitoring.register_event_duration_secs_listener(listen)
    try:
        _, _, _, plain_build, plain_render = job(14, 11, ahead=False)
        sc, img, threads, built, rendered = job(13, 11, ahead=True)
    finally:
        active[0] = False
    assert len(threads) == 1 and rendered == [], (built, rendered)
    assert [e for e in built if e[1]] == [("jaxrt-compile", True)], built
    assert sum(e[1] for e in plain_build + plain_render) == 1, (plain_build, plain_render)
    p = render_tiles.plan(sc, max_tile_rays=max_rays)
    assert (p.shape is None) == (max_rays is None)
    ref = np.asarray(jax.jit(integrators.REGISTRY["whitted"][0])(sc))  # compiled from the built scene
    if max_rays is None:
        np.testing.assert_array_equal(img, ref)
    else:  # tiles round as the tile program does (`integrators.tile`'s docstring)
        np.testing.assert_allclose(img, ref, rtol=2e-6, atol=1e-7)


def test_compile_ahead_leaves_photon_mapping_to_its_pass_check():
    doc = whitted_doc(w=8, h=8, spp=1)
    doc["render"] = {**doc.get("render", {}), "integrator": "sppm"}
    threads = []
    S.build(S.parse(doc), on_shapes=lambda s: threads.append(render_tiles.compile_ahead(s)))
    assert threads == [None]


# ---- Ctrl-C ---------------------------------------------------------------------------------------

SCENE_TOML = """
[camera]
position = [0.0, 1.6, 5.0]
look_at = [0.0, 0.7, 0.0]
width = 256
height = 256
[render]
max_depth = 2
[[lights]]
position = [3.0, 6.0, 4.0]
intensity = 60.0
[materials.m]
model = "lambert"
rho_d = 0.5
delta = 0.3
[[objects]]
primitive = "sphere"
radius = 0.9
translate = [0.0, 0.9, 0.0]
material = "m"
[[objects]]
primitive = "plane"
size = [20.0, 20.0]
material = "m"
"""


def _start_render(tmp_path, *extra):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE_TOML)
    cmd = [sys.executable, "-m", "jaxrt.cli", "render", str(scene), "-o", str(tmp_path / "out.exr"), *extra]
    # SIGINT back to its default in the child: a test run started in the background of a non-interactive
    # shell ignores SIGINT, the child would inherit that, and Python then installs no Ctrl-C handler
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    err = bytearray()

    def pump():
        while chunk := proc.stderr.read1(4096):
            err.extend(chunk)

    threading.Thread(target=pump, daemon=True).start()
    return proc, err


def _interrupt_when(proc, err, needle: bytes, timeout: float):
    t0 = time.monotonic()
    while not re.search(needle, err):
        assert proc.poll() is None, err.decode(errors="replace")[-2000:]
        assert time.monotonic() - t0 < timeout, err.decode(errors="replace")[-2000:]
        time.sleep(0.02)
    t_sig = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rc = proc.wait(timeout=30)
    return rc, time.monotonic() - t_sig


def _assert_interrupted(rc, took, err, tmp_path):
    text = err.decode(errors="replace")
    assert rc == 130, text[-2000:]
    assert took < 2.0, took  # target: within one tile / a fraction of a second on this CPU
    assert "jaxrt: interrupted" in text and "Traceback" not in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]  # nothing written, no temporary file


def test_ctrl_c_between_tiles_exits_130_and_writes_nothing(tmp_path):
    # 256² pixels within 8 MiB: about 13000 pixels a tile, 6 tiles, each well under a second here
    proc, err = _start_render(tmp_path, "--memory", "8M")
    rc, took = _interrupt_when(proc, err, rb"\| *[1-9][0-9]*/[0-9]+ ", timeout=240)  # a tile done
    _assert_interrupted(rc, took, err, tmp_path)


def test_ctrl_c_during_compilation_exits_130_at_once(tmp_path):
    proc, err = _start_render(tmp_path)
    rc, took = _interrupt_when(proc, err, b"compiling", timeout=240)
    _assert_interrupted(rc, took, err, tmp_path)


@pytest.mark.parametrize("traversal,embree,expect", [("auto", True, ["traverse_embree"]),
                                                     ("auto", False, ["traverse_embree", "traverse_cpu"]),
                                                     ("embree", True, ["traverse_embree"]),
                                                     ("cpu", True, ["traverse_cpu"]), ("xla", True, [])])
def test_the_cli_builds_the_native_kernel_it_uses_in_a_thread_of_its_own(monkeypatch, traversal, embree, expect):
    """`cli.render.start_kernels` (called by `jaxrt render` and `jaxrt fit` after their input checks)
    loads the native kernel the traversal will use in a background thread: Embree's where it loads,
    jaxrt's own only where it does not (or with JAXRT_TRAVERSAL=cpu), as `jaxrt.accel.bvh` chooses."""
    from jaxrt.accel import traverse_cpu, traverse_embree
    from jaxrt.cli import render as cli_render

    calls = []

    def recorder(name, ok):
        def available():
            calls.append((name, threading.current_thread().name))
            return ok
        return available

    monkeypatch.setattr(traverse_cpu, "available", recorder("traverse_cpu", True))
    monkeypatch.setattr(traverse_embree, "available", recorder("traverse_embree", embree))
    monkeypatch.setattr(cli_render, "_kernels", [])
    monkeypatch.setenv("JAXRT_TRAVERSAL", traversal)
    cli_render.start_kernels()
    for t in cli_render._kernels:
        t.join(60)
    assert calls == [(n, "jaxrt-kernels") for n in expect]
    cli_render.start_kernels()  # once per process
    assert len(calls) == len(expect)
