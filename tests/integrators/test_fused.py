"""The fused Whitted forward pass (`integrators.whitted`, behind `render.frame`) against the two-pass
`shade(trace(scene), scene)` (itself checked against closed forms and Mitsuba elsewhere), its
custom VJP against the two-pass gradients, and one gradient against central finite differences.

Three small scenes cover every branch of the ray tree: the shipped spheres (seven models, mirror,
glass with the default ray budget, spp = 2, an environment map), a built scene (glass as the first
object, a checker-textured floor, mirrors, two lights, ray_budget = 1 so branches are dropped) and
the shipped instances scene (two-level BVH, a reflective floor). Each compiles `render.frame`
(aovs=True), `render.trace` and `render.shade` once.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import envmap, integrators
import jaxrt as R
from jaxrt import scene as S
from jaxrt.shading import material

W, H = 24, 16
BG = [0.05, 0.06, 0.09]


def _built_dict():
    return {
        "camera": {"position": [0.0, 1.6, 5.0], "look_at": [0.0, 0.7, 0.0], "vfov": 38.0, "width": W, "height": H},
        "lights": [{"position": [3.0, 6.0, 4.0], "intensity": [60.0, 50.0, 40.0]},
                   {"position": [-4.0, 3.0, 2.0], "intensity": [10.0, 20.0, 30.0]}],
        "materials": {
            "glass": {"model": "glass", "n_t": 1.5},
            "floor": {"model": "lambert", "rho_d": {"checker": [[0.8, 0.8, 0.8], [0.1, 0.2, 0.1]], "scale": 4},
                      "delta": 0.3},
            "mirror": {"model": "lambert", "rho_d": 0.05, "delta": 0.9},
            "plastic": {"model": "phong", "rho_d": [0.5, 0.1, 0.1], "rho_s": 0.4, "s": 40.0, "delta": 0.2},
        },
        "objects": [
            # first: face 0 is glass, so a miss (prim -1, read as face 0) must still see the background
            {"name": "ball", "primitive": "sphere", "radius": 1.1, "subdivisions": 2, "translate": [0.0, 1.1, 0.3],
             "material": "glass"},
            {"name": "floor", "primitive": "plane", "size": [40.0, 40.0], "material": "floor"},
            {"name": "mirror", "primitive": "sphere", "radius": 0.5, "subdivisions": 2,
             "translate": [-1.4, 0.5, -0.5], "material": "mirror"},
            {"name": "red", "primitive": "sphere", "radius": 0.5, "subdivisions": 2, "translate": [1.4, 0.5, -0.5],
             "material": "plastic"},
        ],
        "render": {"max_depth": 4, "ray_budget": 1, "background": BG},
    }


def _scene(name):
    if name == "spheres_env":
        sc = S.load("spheres", overrides={"camera.width": W, "camera.height": H, "render.spp": 2})
        texels = np.random.default_rng(1).uniform(0.0, 2.0, (8, 16, 3))
        return eqx.tree_at(lambda s: s.environment, sc, envmap.from_array(texels), is_leaf=lambda x: x is None)
    if name == "built":
        return S.load(_built_dict())
    return S.load(name, overrides={"camera.width": W, "camera.height": H})


# the two-level BVH's traversal compiles slowly on CPU (~20 s for trace + frame): a slow case
SCENES = ("spheres_env", "built", pytest.param("instances", marks=pytest.mark.slow))


@pytest.fixture(scope="module", params=SCENES)
def case(request):
    sc = _scene(request.param)
    gb = R.trace(sc)
    img, aovs = R.frame(sc, aovs=True)
    ref, ref_aovs = R.shade(gb, sc, aovs=True)
    return dict(name=request.param, scene=sc, gb=gb, img=np.asarray(img), aovs=jax.device_get(aovs),
                ref=np.asarray(ref), ref_aovs=jax.device_get(ref_aovs))


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_fused_image_equals_two_pass(case):
    img, ref = case["img"], case["ref"]
    assert img.shape == (H, W, 3) and np.all(np.isfinite(img))
    assert ref.max() > 0.0
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6 * ref.max())


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_fused_aovs_equal_two_pass(case):
    a, b = case["aovs"], case["ref_aovs"]
    assert set(a) == set(b) == {"depth", "normal", "albedo", "object_id"}
    np.testing.assert_array_equal(a["object_id"], b["object_id"])
    for k in ("depth", "normal", "albedo"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-7, err_msg=k)
    assert np.any(a["object_id"] >= 0) and np.any(a["depth"] > 0)


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_scenes_exercise_the_branches(case):
    """Guards the coverage the comparisons above rely on."""
    gb, sc = case["gb"], case["scene"]
    active = np.asarray(gb.active)
    branch = np.asarray(gb.branch)
    deep = active[1:]
    assert deep.any(), "no secondary rays"
    if case["name"] != "instances":
        assert np.any(deep & (branch[1:] == integrators.whitted.GLASS_T)), "no glass transmission"
        assert np.any(deep & (branch[1:] == integrators.whitted.MIRROR)), "no mirror bounce"
    if case["name"] == "built":
        assert int(gb.dropped) > 0, "ray_budget=1 dropped no branch"
        assert sc.lights.count == 2
    if case["name"] == "spheres_env":
        assert sc.settings.spp == 2 and sc.environment is not None


@pytest.mark.parametrize("spp", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_direct_light_frame_equals_two_pass(spp):
    """max_depth 1 runs the ray-tree loop's body once, outside a loop, and at one sample per pixel
    writes the image as the level's contributions in pixel order (a gather, not a scatter-add): the
    image and AOVs against the two-pass `shade(trace(scene))`, and tiles against the frame."""
    from jaxrt import render_tiles

    doc = _built_dict()
    doc["render"].update(max_depth=1, spp=spp)
    sc = S.load(doc)
    img, aovs = (jax.device_get(x) for x in R.frame(sc, aovs=True))
    ref, ref_aovs = (jax.device_get(x) for x in R.shade(R.trace(sc), sc, aovs=True))
    assert np.isfinite(img).all() and ref.max() > 0.1 and np.mean(aovs["object_id"] >= 0) > 0.5
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6 * ref.max())
    np.testing.assert_array_equal(aovs["object_id"], ref_aovs["object_id"])
    plan = render_tiles.plan(sc, memory="8G", max_tile_rays=96 * spp)  # strips of 4 rows, the last overlapping
    assert plan.tiles > 2 and plan.shape[2] == spp
    tiled = render_tiles.render(sc, use_plan=plan)
    # the tile program rounds a few ulps apart from the frame's (`jaxrt.render_tiles`); a wrong
    # pixel order would move whole pixels
    np.testing.assert_allclose(tiled, img, rtol=1e-4, atol=1e-5 * ref.max())


def test_escaped_rays_see_the_background_when_face_0_is_glass():
    """Pixels whose primary ray misses everything are exactly the background (the built scene's face
    0 is glass; a miss reads face 0's material)."""
    sc = S.load(_built_dict())
    assert bool(material.is_glass(sc.materials, sc.geometry.material[:1])[0])
    img, aovs = R.frame(sc, aovs=True)
    miss = np.asarray(aovs["object_id"]) < 0
    assert miss.sum() > 10
    np.testing.assert_array_equal(np.asarray(img)[miss], np.broadcast_to(np.float32(BG), (miss.sum(), 3)))


def _while_carry_shapes(jaxpr):
    """Shapes of every lax.while_loop carry in a (closed) jaxpr, recursing into sub-jaxprs."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "while":
            out += [tuple(v.aval.shape) for v in eqn.outvars]
        for p in eqn.params.values():
            for sub in (p if isinstance(p, (tuple, list)) else (p,)):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    out += _while_carry_shapes(inner)
    return out


def test_primal_pass_records_no_gbuffer():
    """Without a gradient the fused pass carries no (max_depth, slots) GBuffer arrays; `trace` does."""
    sc = S.load(_built_dict())
    D, B = sc.settings.max_depth, sc.settings.ray_budget * sc.camera.num_pixels * sc.settings.spp
    lead = lambda shapes: [s for s in shapes if s[:2] == (D, B)]
    fused = _while_carry_shapes(jax.make_jaxpr(lambda s: integrators.whitted.whitted(s, aovs=True))(sc).jaxpr)
    traced = _while_carry_shapes(jax.make_jaxpr(integrators.trace)(sc).jaxpr)
    assert fused and not lead(fused), lead(fused)
    assert len(lead(traced)) >= 10  # the check can see a recorded GBuffer


# ---------------------------------------------------------------------------------------- gradients


def _weights(seed):
    return jnp.asarray(np.random.default_rng(seed).uniform(0.5, 1.5, (H, W, 3)), jnp.float32)


def _loss_fused(sc, w, aovs):
    if aovs:
        img, a = R.frame(sc, aovs=True)
        return jnp.sum(img * w) + jnp.sum(a["albedo"] * w) + jnp.sum(a["normal"] * w)
    return jnp.sum(R.frame(sc) * w)


def _loss_two_pass(sc, gb, w, aovs):
    if aovs:
        img, a = integrators.shade(gb, sc, aovs=True)
        return jnp.sum(img * w) + jnp.sum(a["albedo"] * w) + jnp.sum(a["normal"] * w)
    return jnp.sum(integrators.shade(gb, sc) * w)


@pytest.fixture(scope="module")
def built_grads():
    sc = S.load(_built_dict())
    gb = R.trace(sc)
    w = _weights(0)
    g_fused = jax.jit(jax.grad(_loss_fused, allow_int=True), static_argnums=2)(sc, w, False)
    g_ref = jax.jit(jax.grad(_loss_two_pass, allow_int=True), static_argnums=3)(sc, gb, w, False)
    return sc, w, g_fused, g_ref


def _float_leaves(g):
    return [x for x in jax.tree_util.tree_leaves(g) if x.dtype != jax.dtypes.float0]


def _assert_same_grads(g_fused, g_ref):
    a, b = _float_leaves(g_fused), _float_leaves(g_ref)
    assert len(a) == len(b) and len(a) > 10
    for x, y in zip(a, b):
        x, y = np.asarray(x), np.asarray(y)
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-5 * max(np.abs(y).max(), 1e-30))


def _pick(sc, g):
    """The gradient entries the test names: (material param / δ / light) -> (fused-grad value)."""
    mats = sc.materials
    k_p, k_g = mats.models.index("phong"), mats.models.index("glass")
    r_p = int(mats.row[mats.index("plastic")])
    r_g = int(mats.row[mats.index("glass")])
    return {
        "plastic.s": g.materials.params[k_p]["s"][r_p],
        "plastic.rho_s": g.materials.params[k_p]["rho_s"][r_p],
        "glass.n_t": g.materials.params[k_g]["n_t"][r_g],
        "mirror.delta": g.materials.delta[mats.index("mirror")],
        "floor.delta": g.materials.delta[mats.index("floor")],
        "light0.position": g.lights.position[0],
        "light1.intensity": g.lights.intensity[1],
    }


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_fused_gradients_equal_two_pass(built_grads):
    sc, _, g_fused, g_ref = built_grads
    _assert_same_grads(g_fused, g_ref)
    picked = {k: np.asarray(v) for k, v in _pick(sc, g_fused).items()}
    for k, v in picked.items():  # the named parameters all reach the loss (the comparison is not 0 == 0)
        assert np.all(np.isfinite(v)) and np.any(v != 0), (k, v)
    # the textured floor's texels get gradients too
    tex = _float_leaves(g_fused.materials.textures)
    assert tex and np.any(np.asarray(tex[0]) != 0)


@pytest.mark.slow  # ~25 s of compiles
def test_fused_gradients_with_aovs_equal_two_pass():
    """aovs=True: the loss also reads the albedo and normal AOVs (object_id has no cotangent)."""
    sc = _scene("spheres_env")
    gb = R.trace(sc)
    w = _weights(1)
    g_fused = jax.jit(jax.grad(_loss_fused, allow_int=True), static_argnums=2)(sc, w, True)
    g_ref = jax.jit(jax.grad(_loss_two_pass, allow_int=True), static_argnums=3)(sc, gb, w, True)
    _assert_same_grads(g_fused, g_ref)
    assert np.any(np.asarray(g_fused.environment.texels) != 0)  # escaped rays reach the map
    assert np.any(np.asarray(g_fused.geometry.vertices) != 0)  # the normal AOV and shading move with vertices


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_fused_gradients_match_finite_differences(built_grads):
    """Central differences of the fused image itself (float32) for parameters that do not change the
    traced tree: light intensity and ρ_s are linear in the image, the Phong exponent is smooth.
    (Independent of both the custom VJP and `shade`'s autodiff.)"""
    sc, w, g_fused, _ = built_grads
    w64 = np.asarray(w, np.float64)
    # the float32 image summed in float64 on the host: only per-pixel rounding is left in the difference
    f = lambda s: float(np.sum(np.asarray(R.frame(s), np.float64) * w64))
    picked = _pick(sc, g_fused)
    checks = [
        ("light1.intensity", 0.5 * 20.0, lambda s, h: s.with_light(1, intensity=[10.0, 20.0 + h, 30.0]), 1),
        # rho_s is RGB; the edit moves all three channels
        ("plastic.rho_s", 0.1, lambda s, h: s.with_material("plastic", rho_s=0.4 + h), "sum"),
        ("plastic.s", 0.5, lambda s, h: s.with_material("plastic", s=40.0 + h), None),
    ]
    for name, h, edit, comp in checks:
        fd = (f(edit(sc, h)) - f(edit(sc, -h))) / (2 * h)
        g = np.asarray(picked[name])
        g = float(g.sum() if comp == "sum" else g[comp] if comp is not None else g)
        assert abs(fd) > 1e-3, (name, fd)
        # measured: 3e-8, 1e-7 and 6e-5 (the exponent's O(h^2) truncation) relative
        np.testing.assert_allclose(g, fd, rtol=2e-4, err_msg=name)


def test_sample_order_blocks_and_inverse():
    """Level-0 order: a permutation of the samples, each pixel's samples together, 32 consecutive slots
    an 8x4 pixel block where the image divides into blocks, and `first` the slot of each pixel's first
    sample (odd sizes and spp > 1 too)."""
    from jaxrt.integrators import sample_order

    for h, w, spp in ((8, 16, 1), (12, 40, 1), (7, 13, 3), (1, 5, 2)):
        order, first = sample_order(h, w, spp)
        assert sorted(order.tolist()) == list(range(h * w * spp))
        pix = order // spp
        assert np.array_equal(order % spp, np.tile(np.arange(spp), h * w))
        assert np.array_equal(pix[first], np.arange(h * w)) and np.array_equal(order[first] % spp, np.zeros(h * w))
        if h % 4 == 0 and w % 8 == 0 and spp == 1:
            y, x = np.divmod(pix.reshape(-1, 32), w)
            assert np.all(y.max(1) - y.min(1) == 3) and np.all(x.max(1) - x.min(1) == 7)


def test_sample_order_arrays_are_sample_orders_tables():
    """The slot order made in a program from indices (whole 8x4 blocks) or read from constants
    (otherwise) equals `sample_order`'s numpy tables, and a program of a block-divisible image holds
    no table-sized constant."""
    from jaxrt.integrators import sample_order
    from jaxrt.integrators.common import sample_order_arrays

    for h, w, spp in ((8, 16, 1), (12, 40, 3), (64, 24, 2), (7, 13, 3), (4, 12, 1)):
        order, first = sample_order(h, w, spp)
        got = jax.jit(sample_order_arrays, static_argnums=(0, 1, 2))(h, w, spp)
        np.testing.assert_array_equal(np.asarray(got[0]), order, err_msg=f"{h}x{w}x{spp}")
        np.testing.assert_array_equal(np.asarray(got[1]), first, err_msg=f"{h}x{w}x{spp}")
        assert got[0].dtype == got[1].dtype == np.int32  # made unsigned on the CPU, returned as int32
    text = jax.jit(sample_order_arrays, static_argnums=(0, 1, 2)).lower(256, 256, 1).as_text()
    assert len(text) < 20_000, len(text)  # no 65,536-entry table in the program (such a table: ~1 MB of text)
