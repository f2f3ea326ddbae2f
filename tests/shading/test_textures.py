"""Textures: bilinear lookup and wrap modes against an independent numpy construction (np.pad with
'wrap' / 'edge' / 'symmetric' then plain bilinear interpolation), the checkerboard's exact values,
a textured plane rendered and compared pixel by pixel with ρd(uv)/π·I·cosθ/d² computed in numpy
(with its own sRGB decoding of the PNG), the gradient of a pixel with respect to a texel against
finite differences, and bad texture inputs."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as R
from jaxrt import scene as S
from jaxrt.shading import textures as T
from jaxrt.errors import InputError
from test_render_util import pinhole_rays, ray_plane_y0

PAD_MODE = {"repeat": "wrap", "clamp": "edge", "mirror": "symmetric"}


def bilinear_ref(img, uv, wrap):
    """float64 numpy: extend the image by whole copies with np.pad, then bilinear between texel centres."""
    h, w = img.shape[:2]
    k = 4  # pad by 4 image sizes on each side: enough for uv in [-3, 4)
    big = np.pad(img.astype(np.float64), ((k * h, k * h), (k * w, k * w), (0, 0)), mode=PAD_MODE[wrap])
    x = uv[:, 0] * w - 0.5 + k * w
    y = (1.0 - uv[:, 1]) * h - 0.5 + k * h  # v = 1 is the top row
    out = np.zeros((len(uv), img.shape[2]))
    for n in range(len(uv)):
        x0, y0 = math.floor(x[n]), math.floor(y[n])
        fx, fy = x[n] - x0, y[n] - y0
        out[n] = ((1 - fx) * (1 - fy) * big[y0, x0] + fx * (1 - fy) * big[y0, x0 + 1]
                  + (1 - fx) * fy * big[y0 + 1, x0] + fx * fy * big[y0 + 1, x0 + 1])
    return out


@pytest.mark.parametrize("wrap", ["repeat", "clamp", "mirror"])
def test_bilinear_lookup_matches_numpy(wrap):
    rng = np.random.default_rng(0)
    img = rng.random((5, 7, 3)).astype(np.float32)
    uv = rng.uniform(-1.5, 2.5, (500, 2))
    scale, offset = np.array([1.3, 0.7]), np.array([0.1, -0.2])
    tex = T.make(img, wrap=wrap, uv_scale=scale, uv_offset=offset)
    got = np.asarray(jax.jit(T.lookup)(tex, jnp.asarray(uv, jnp.float32)))
    ref = bilinear_ref(img, uv * scale + offset, wrap)
    np.testing.assert_allclose(got, ref, atol=2e-5)
    # at texel centres the lookup returns the texel itself (v = 1 is the top row)
    j, i = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    centres = np.stack([(i + 0.5) / 7, 1 - (j + 0.5) / 5], -1).reshape(-1, 2)
    plain = T.make(img, wrap=wrap)
    np.testing.assert_allclose(np.asarray(T.lookup(plain, jnp.asarray(centres, jnp.float32))),
                               img.reshape(-1, 3), atol=1e-6)


def test_lookup_is_differentiable_in_texels_and_uv_map():
    """d lookup / d texel is the bilinear weight (numpy reference with a one-hot image)."""
    rng = np.random.default_rng(1)
    img = rng.random((4, 6, 1)).astype(np.float32)
    uv = jnp.asarray(rng.uniform(-1, 2, (8, 2)), jnp.float32)
    tex = T.make(img, wrap="mirror")
    g = jax.jacobian(lambda t: T.lookup(eqx.tree_at(lambda x: x.texels, tex, t), uv)[:, 0])(tex.texels)
    for (j, i) in [(0, 0), (2, 3), (3, 5)]:
        onehot = np.zeros_like(img)
        onehot[j, i] = 1
        np.testing.assert_allclose(np.asarray(g)[:, j, i, 0], bilinear_ref(onehot, np.asarray(uv), "mirror")[:, 0],
                                   atol=1e-6)
    go = jax.grad(lambda o: jnp.sum(T.lookup(eqx.tree_at(lambda x: x.uv_offset, tex, o), uv)))(tex.uv_offset)
    assert np.all(np.isfinite(np.asarray(go))) and np.any(np.asarray(go) != 0)


def test_checkerboard_exact_values():
    a, b = np.array([0.8, 0.7, 0.6]), np.array([0.1, 0.2, 0.3])
    tex = T.make(np.stack([a, b])[None], kind="checker", uv_scale=8.0)
    rng = np.random.default_rng(2)
    cells = rng.integers(-16, 24, (300, 2))
    frac = rng.uniform(0.01, 0.99, (300, 2))
    uv = (cells + frac) / 8.0
    got = np.asarray(T.lookup(tex, jnp.asarray(uv, jnp.float32)))
    expect = np.where((np.sum(cells, -1) % 2 == 0)[:, None], a, b)
    np.testing.assert_array_equal(got, expect.astype(np.float32))


# ---- scene syntax, rendering, gradients ---------------------------------------------------------

PLANE = 4.0
LIGHT_POS, LIGHT_I = np.array([0.3, 3.0, -0.4]), np.array([8.0, 9.0, 10.0])
CAM = dict(position=[0.0, 4.0, 0.5], look_at=[0.0, 0.0, 0.0], vfov=40.0, width=32, height=32)


def _write_png(path, arr8):
    from PIL import Image

    Image.fromarray(arr8).save(path)


def _srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _plane_doc(rho_d, wrap="repeat"):
    return {
        "camera": dict(CAM),
        "lights": [{"position": LIGHT_POS.tolist(), "intensity": LIGHT_I.tolist()}],
        "materials": {"tex": {"model": "lambert", "rho_d": rho_d}},
        "objects": [{"primitive": "plane", "size": [PLANE, PLANE], "material": "tex"}],
        "render": {"max_depth": 1, "background": 0.0},
    }


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    d = tmp_path_factory.mktemp("tex")
    rng = np.random.default_rng(3)
    arr8 = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    _write_png(d / "albedo.png", arr8)
    sc = S.load(_plane_doc({"texture": "albedo.png", "wrap": "mirror", "scale": [1.5, 1.0]}), base_dir=d)
    gb = R.gbuffer(sc)
    return sc, gb, arr8


def test_textured_plane_render_matches_numpy(textured):
    sc, gb, arr8 = textured
    img = np.asarray(R.reshade(gb, sc), np.float64).reshape(-1, 3)
    assert np.all(np.isfinite(img))
    o, d = pinhole_rays(CAM["position"], CAM["look_at"], CAM["vfov"], CAM["width"], CAM["height"])
    t = ray_plane_y0(o, d)
    p = o + t[:, None] * d
    assert np.all(np.abs(p[:, [0, 2]]) < PLANE / 2)  # every pixel sees the plane
    # plane(): uv (0,0) at (-x, -z) corner, (1,1) at (+x, +z)
    uv = np.stack([(p[:, 0] + PLANE / 2) / PLANE, (p[:, 2] + PLANE / 2) / PLANE], -1) * np.array([1.5, 1.0])
    rho = bilinear_ref(_srgb_to_linear(arr8 / 255.0), uv, "mirror")
    to_l = LIGHT_POS - p
    d2 = np.sum(to_l**2, -1)
    cos = to_l[:, 1] / np.sqrt(d2)
    expect = rho / np.pi * LIGHT_I * (cos / d2)[:, None]
    np.testing.assert_allclose(img, expect, rtol=1e-3, atol=1e-6)
    # the pixels really vary with the texture (not a constant albedo)
    assert np.std(img[:, 0] / expect[:, 0].mean()) > 0.05


def test_pixel_gradient_wrt_texel_matches_finite_differences(textured):
    sc, gb, _ = textured
    tex0 = sc.materials.textures[0].texels
    pix = [(5, 7), (16, 16), (28, 3)]

    def pixels(texels):
        img = R.reshade(gb, sc.with_texture("tex", "rho_d", texels))
        return jnp.stack([img[i, j] for i, j in pix])  # (3 pixels, 3)

    jac = np.asarray(jax.jacobian(lambda t: pixels(t)[:, 1])(tex0))  # green channel (P, H, W, 3)
    h = 0.05
    checked = 0
    for jj, ii in [(0, 0), (1, 2), (3, 4), (2, 1)]:
        e = np.zeros(tex0.shape, np.float32)
        e[jj, ii, 1] = h
        fd = (np.asarray(pixels(tex0 + e), np.float64) - np.asarray(pixels(tex0 - e), np.float64))[:, 1] / (2 * h)
        np.testing.assert_allclose(jac[:, jj, ii, 1], fd, rtol=2e-3, atol=1e-7)
        checked += int(np.sum(np.abs(fd) > 0))
    assert checked >= 2  # some of the chosen texels do influence the chosen pixels


def test_changing_texels_does_not_recompile(textured):
    sc, gb, _ = textured
    f = jax.jit(R.reshade)
    f(gb, sc)
    n = f._cache_size()
    sc2 = sc.with_texture("tex", "rho_d", sc.materials.textures[0].texels * 0.5)
    img2 = f(gb, sc2)
    assert f._cache_size() == n
    np.testing.assert_allclose(np.asarray(img2), 0.5 * np.asarray(f(gb, sc)), rtol=1e-5, atol=1e-7)
    with pytest.raises(InputError, match="textured"):
        sc.with_material("tex", rho_d=0.5)
    with pytest.raises(InputError, match="shape"):
        sc.with_texture("tex", "rho_d", np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match="finite"):
        sc.with_texture("tex", "rho_d", np.full(sc.materials.textures[0].texels.shape, np.nan))
    with pytest.raises(InputError, match="not textured"):
        sc.with_texture("tex", "rho_s", sc.materials.textures[0].texels)


def _parse(doc, base):
    return S.parse(doc, base_dir=base)


def test_checker_in_scene_file_and_uvs_of_primitives(tmp_path):
    spec = _parse(_plane_doc({"checker": [[0.8, 0.8, 0.8], [0.1, 0.1, 0.1]], "scale": 8}), tmp_path)
    ts = spec.materials["tex"].textures["rho_d"]
    assert ts.kind == "checker" and ts.texels.shape == (1, 2, 3) and ts.uv_scale == (8.0, 8.0)
    sc = S.build(spec)
    assert sc.geometry.uvs.shape == (sc.geometry.vertices.shape[0], 2)
    # plane corners: uv (0,0) at (-x,-z), (1,1) at (+x,+z)
    v, uv = np.asarray(sc.geometry.vertices), np.asarray(sc.geometry.uvs)
    np.testing.assert_allclose(uv, np.stack([(v[:, 0] + PLANE / 2) / PLANE, (v[:, 2] + PLANE / 2) / PLANE], -1))


BAD = [
    ({"texture": "missing.png"}, "does not exist"),
    ({"texture": "grey.png"}, None),  # grey PNG for an RGB parameter is allowed (broadcast)
    ({"texture": "albedo.txt"}, "unsupported type"),
    ({"texture": "albedo.png", "wrap": "tile"}, "wrap.*repeat, clamp, mirror"),
    ({"texture": "albedo.png", "checker": [0, 1]}, "exactly one of"),
    ({"checker": [0.1]}, "two values"),
    ({"checker": [0.1, 1.5]}, r"checker value 2.*\[0, 1\]"),
    ({"checker": [0.1, 0.5], "scale": 0}, "non-zero"),
    ({"checker": [0.1, 0.5], "filter": "nearest"}, "unknown texture key 'filter'"),
    ({"texture": "bright.exr"}, r"bright.exr has values in \[2, 2\], outside the allowed range \[0, 1\]"),
]


@pytest.mark.parametrize("value,match", BAD, ids=[str(i) for i in range(len(BAD))])
def test_bad_texture_inputs_name_file_and_field(tmp_path, value, match):
    from jaxrt.image import write_exr

    _write_png(tmp_path / "albedo.png", np.zeros((2, 2, 3), np.uint8))
    _write_png(tmp_path / "grey.png", np.full((2, 2), 128, np.uint8))
    (tmp_path / "albedo.txt").write_text("x")
    write_exr(tmp_path / "bright.exr", np.full((2, 2, 3), 2.0, np.float32))
    doc = _plane_doc(value)
    if match is None:
        assert _parse(doc, tmp_path).materials["tex"].textures["rho_d"].texels.shape == (2, 2, 3)
        return
    with pytest.raises(InputError, match=match) as e:
        _parse(doc, tmp_path)
    assert "materials.tex.rho_d" in str(e.value)


def test_scalar_parameter_needs_one_channel(tmp_path):
    _write_png(tmp_path / "rgb.png", np.zeros((2, 2, 3), np.uint8))
    arr = np.array([[0, 255], [128, 64]], np.uint8)
    _write_png(tmp_path / "rough.png", arr)
    doc = _plane_doc(0.5)
    doc["materials"]["tex"] = {"model": "disney", "roughness": {"texture": "rgb.png"}}
    with pytest.raises(InputError, match="materials.tex.roughness.*rgb.png.*one-channel"):
        _parse(doc, tmp_path)
    doc["materials"]["tex"] = {"model": "disney", "roughness": {"checker": [[0.1, 0.2, 0.3], 0.5]}}
    with pytest.raises(InputError, match="materials.tex.roughness: checker value 1 must be a number"):
        _parse(doc, tmp_path)
    doc["materials"]["tex"] = {"model": "disney", "roughness": {"texture": "rough.png"}}
    ts = _parse(doc, tmp_path).materials["tex"].textures["roughness"]
    np.testing.assert_allclose(ts.texels[..., 0], arr / 255.0, rtol=1e-6)  # linear, not sRGB-decoded


@pytest.mark.slow
def test_textured_example_scene_renders(tmp_path):
    """`jaxrt render textured` (checker floor, checker roughness and colour on Disney spheres) runs and is finite."""
    from jaxrt import cli
    from jaxrt.image import read_exr

    exr = tmp_path / "t.exr"
    assert cli.main(["render", "textured", "-o", str(exr), "--width", "32", "--height", "20", "-q"]) == 0
    img = read_exr(exr)
    assert img.shape == (20, 32, 3) and np.all(np.isfinite(img)) and img.max() > 0


def test_box_faces_map_to_unit_square():
    from jaxrt.geometry import shapes

    size = np.array([1.0, 2.0, 3.0])
    b = shapes.box(size=tuple(size))
    v, n, uv = (np.asarray(x, np.float64) for x in (b.vertices, b.normals, b.uvs))
    for a, (i, j) in enumerate([(1, 2), (0, 2), (0, 1)]):
        on = np.abs(n[:, a]) > 0.5
        assert on.sum() == 12  # two faces of two triangles per axis
        np.testing.assert_allclose(uv[on], np.stack([v[on, i] / size[i], v[on, j] / size[j]], -1) + 0.5, atol=1e-6)


def test_sphere_uv_is_latitude_longitude_without_a_seam_sweep():
    from jaxrt.geometry import shapes

    s = shapes.sphere(radius=1.0, subdivisions=3)
    v, uv, f = (np.asarray(x, np.float64) for x in (s.vertices, s.uvs, s.faces))
    f = f.astype(int)
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    # v: latitude (1 at +y); u: longitude around +y, up to a whole turn at seam copies
    np.testing.assert_allclose(uv[:, 1], 0.5 + np.arcsin(np.clip(n[:, 1], -1, 1)) / np.pi, atol=1e-6)
    lon = np.mod(np.arctan2(n[:, 0], n[:, 2]) / (2 * np.pi) + 0.5, 1.0)
    d = np.mod(uv[:, 0] - lon + 0.5, 1.0) - 0.5
    polar = np.abs(n[:, 1]) > 0.999
    np.testing.assert_allclose(d[~polar], 0.0, atol=1e-6)
    # away from the poles no face spans more than a small part of the turn
    span = uv[f, 0].max(1) - uv[f, 0].min(1)
    near_pole = np.abs(n[f, 1]).max(1) > 0.97
    assert span[~near_pole].max() < 0.1


@pytest.mark.slow  # 12 s on 2 cores
def test_gather_params_textured_scalar_parameter_and_float64_gradient(tmp_path):
    """gather_params(..., uv) returns the texture value only for the textured material's slots, and
    the Disney BRDF's gradient with respect to a roughness texel matches float64 central differences."""
    import brdfs
    from jaxrt.shading.material import gather_params

    _write_png(tmp_path / "rough.png", np.array([[40, 200], [120, 90]], np.uint8))
    doc = _plane_doc(0.5)
    doc["materials"] = {"a": {"model": "disney", "roughness": {"texture": "rough.png", "wrap": "clamp"}},
                        "b": {"model": "disney", "roughness": 0.3}}
    doc["objects"][0]["material"] = "a"
    sc = S.load(doc, base_dir=tmp_path)
    mats = sc.materials
    rng = np.random.default_rng(5)
    B = 12
    uv = rng.uniform(0, 1, (B, 2))
    mat = np.arange(B) % 2  # alternate materials a (textured) and b (constant)
    tex = mats.textures[0]
    p = gather_params(mats, jnp.asarray(mat), 0, jnp.asarray(uv, jnp.float32))
    ref = bilinear_ref(np.asarray(tex.texels), uv, "clamp")[:, 0]
    np.testing.assert_allclose(np.asarray(p["roughness"]), np.where(mat == 0, ref, 0.3), atol=1e-6)
    assert p["roughness"].shape == (B,) and p["base_color"].shape == (B, 3)
    # uv=None keeps the old call form: constants (a textured parameter's constant is its texture mean)
    p0 = gather_params(mats, jnp.asarray(mat), 0)
    np.testing.assert_allclose(np.asarray(p0["roughness"]), np.where(mat == 0, np.mean(np.asarray(tex.texels)), 0.3),
                               rtol=1e-6)

    m = brdfs.get("disney")
    wo = np.tile([[0.3, 0.1, 0.95]], (B, 1))
    wi = wo * np.array([-1, -1, 1]) + 0.2 * rng.normal(size=(B, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.3
    wo, wi = (w / np.linalg.norm(w, axis=-1, keepdims=True) for w in (wo, wi))
    with jax.enable_x64(True):
        mats64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if jnp.issubdtype(x.dtype, jnp.floating)
                                        else x, mats)

        def total(t):
            mm = eqx.tree_at(lambda q: q.textures[0].texels, mats64, t)
            pp = gather_params(mm, jnp.asarray(mat), 0, jnp.asarray(uv))
            return jnp.sum(m.eval(pp, jnp.asarray(wi), jnp.asarray(wo)))

        t0 = mats64.textures[0].texels
        g = np.asarray(jax.grad(total)(t0))
        total = jax.jit(total)
        fd = np.zeros(t0.shape)
        for idx in np.ndindex(t0.shape):
            e = np.zeros(t0.shape)
            e[idx] = 1e-6
            fd[idx] = (float(total(t0 + e)) - float(total(t0 - e))) / 2e-6
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(fd) > 0)
