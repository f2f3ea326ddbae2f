"""Glare (jaxrt.glare): energy, the convolution against a float64 brute force, the diffraction PSF
against closed forms (the Airy pattern's first zero, a polygon's rotational symmetry), off by
default, and bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage
from scipy.special import j1, jn_zeros

import jaxrt as R
from jaxrt import glare as G
from jaxrt import integrators
from jaxrt import scene as S
from jaxrt.errors import InputError
from test_bad_input import one_line_error, run_cli

# a small PSF: the Airy radius at 650 nm, 1.22·0.65 µm·16 / 4 µm = 3.2 px, fits size / 8
SMALL_PSF = G.Glare(size=31, f_number=16.0, pixel_pitch=4.0)
SHIPPED = {"camera.width": 24, "camera.height": 24}  # as tests/integrators/test_render_scenes.py


def _images():
    rng = np.random.default_rng(7)
    noise = rng.random((12, 16, 3)) * rng.random((12, 16, 1)) ** 6 * 50.0
    point = np.zeros((9, 20, 3))
    point[4, 13] = [3e3, 2e3, 1e3]
    corner = np.zeros((12, 16, 3))
    corner[0, 15] = 1e4
    corner[11, 0, 1] = 5.0
    return {"random": noise, "point": point, "corner": corner}


def _brute_force(img: np.ndarray, p: np.ndarray, g: G.Glare) -> np.ndarray:
    """float64 direct sum over source pixels: each pixel's spread (its share above the threshold)
    lands through the PSF, renormalised over the frame; what is spread leaves the pixel."""
    h, w, _ = img.shape
    k = p.shape[-1]
    c = k // 2
    luma = img @ np.array([0.2126, 0.7152, 0.0722])
    frac = np.where(luma > g.threshold, (luma - g.threshold) / np.where(luma > 0, luma, 1.0), 0.0)
    spread = g.strength * frac[..., None] * img
    out = img - spread
    for y, x in zip(*np.nonzero(spread.sum(-1))):
        for ch in range(3):
            # the PSF centred on (y, x), cut to the frame
            window = np.zeros((h + 2 * k, w + 2 * k))
            window[y + k - c:y + k - c + k, x + k - c:x + k - c + k] = p[ch]
            inside = window[k:k + h, k:k + w]
            out[..., ch] += spread[y, x, ch] * inside / inside.sum()
    return out


@pytest.mark.parametrize("name", ["random", "point", "corner"])
@pytest.mark.parametrize("g", [SMALL_PSF, dataclasses.replace(SMALL_PSF, aperture="circle", threshold=2.0,
                                                              strength=0.7)], ids=["whole", "threshold"])
def test_sum_is_preserved_and_matches_a_float64_direct_convolution(name, g):
    img = _images()[name]
    out = np.asarray(G.apply(img.astype(np.float32), g), np.float64)
    assert out.shape == img.shape and np.all(np.isfinite(out))
    np.testing.assert_allclose(out.sum(axis=(0, 1)), img.astype(np.float32).astype(np.float64).sum(axis=(0, 1)),
                               rtol=1e-6)
    ref = _brute_force(img.astype(np.float32).astype(np.float64), np.asarray(G.psf(g), np.float64), g)
    assert np.abs(out - ref).max() <= 1e-5 * img.max()
    assert np.abs(out - img).max() > 0.01 * img.max()  # light did move


def test_airy_first_zero():
    """A circular aperture's PSF is the Airy pattern: the first minimum of its radial profile lies at
    j1,1/π · λN/p pixels (j1,1 = 3.8317, the first zero of J1) in each channel, within 1 %
    (the pixel integration shifts the minimum of a ring of radius 11-16 px by less than 0.5 %)."""
    g = G.Glare(aperture="circle", f_number=80.0, pixel_pitch=4.0, size=255)
    p = np.asarray(G.psf(g), np.float64)
    np.testing.assert_allclose(p.sum(axis=(1, 2)), 1.0, rtol=1e-5)
    k = p.shape[-1]
    y, x = np.mgrid[:k, :k] - k // 2
    r = np.hypot(x, y).ravel()
    width = 0.25
    bins = np.minimum((r / width).astype(int), int(k // 2 / width))
    counts = np.bincount(bins)
    for ch, lam in enumerate(G.WAVELENGTHS):
        expected = jn_zeros(1, 1)[0] / np.pi * lam * g.f_number / (g.pixel_pitch * 1e-6)
        keep = counts > 0
        prof = (np.bincount(bins, p[ch].ravel()) / np.maximum(counts, 1))[keep]
        radius = (np.bincount(bins, r) / np.maximum(counts, 1))[keep]
        i = next(i for i in range(1, len(prof) - 1) if prof[i] < prof[i - 1] and prof[i] <= prof[i + 1])
        a, b, c = np.polyfit(radius[i - 1:i + 2], prof[i - 1:i + 2], 2)
        assert abs(-b / (2 * a) / expected - 1) < 0.01, (lam, -b / (2 * a), expected)


def test_circular_psf_core_is_the_pixel_integrated_airy_pattern():
    """Within 20 px of the centre, each channel's PSF is the Airy pattern (2·J1(x)/x)², x = π·r·p/(λN),
    normalised to unit energy over the plane and averaged over each pixel (8×8 midpoint samples),
    within 2 % of its peak (measured: 1.0 %, from the pixel integration of the FFT's samples and the
    energy of the tails beyond the 255-px window, which the normalised PSF holds inside it)."""
    g = G.Glare(aperture="circle", f_number=32.0, pixel_pitch=4.0, size=255)
    p = np.asarray(G.psf(g), np.float64)
    c, half = p.shape[-1] // 2, 20
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(float)
    r = np.hypot(x[..., None, None] + sub[None, :], y[..., None, None] + sub[:, None])
    for ch, lam in enumerate(G.WAVELENGTHS):
        a = np.pi * g.pixel_pitch * 1e-6 / (lam * g.f_number)  # x = a·r, r in pixels
        t = np.maximum(a * r, 1e-12)
        ref = ((2 * j1(t) / t) ** 2).mean(axis=(-1, -2)) * a * a / (4 * np.pi)  # ∫(2J1(ar)/(ar))² dA = 4π/a²
        got = p[ch, c - half:c + half + 1, c - half:c + half + 1]
        assert np.abs(got - ref).max() < 0.02 * ref.max(), lam


@pytest.mark.parametrize("blades", [5, 6])
def test_polygon_psf_has_the_aperture_symmetry(blades):
    """A regular N-gon's PSF repeats under rotation by 2π/N, and by π/N for odd N (|FFT|² is also
    centrosymmetric): 2N-fold for odd N, N-fold for even N; half that step is not a symmetry."""
    g = G.Glare(blades=blades, f_number=32.0, pixel_pitch=4.0, size=127)
    p = np.asarray(G.psf(g), np.float64)[1]
    k = p.shape[-1]
    y, x = np.mgrid[:k, :k] - k // 2
    disk = np.hypot(x, y) < 50
    fold = 2 * blades if blades % 2 else blades

    def change(degrees):
        q = ndimage.rotate(p, degrees, reshape=False, order=3)
        return np.abs(q - p)[disk].sum() / p[disk].sum()

    assert change(360 / fold) < 0.025 and change(720 / fold) < 0.025  # cubic interpolation: 0.4-1.5 %
    assert change(180 / fold) > 0.05
    assert np.abs(p - p[::-1, ::-1]).max() < 1e-6 * p.max()


def test_glare_off_by_default_is_the_renderer_s_image():
    # spheres at 24x24 without AOVs: the program tests/integrators/test_render_scenes.py compiles too
    sc = S.load("spheres", overrides=SHIPPED)
    assert sc.glare is None and S.parse(S.find_scene("spheres")).glare is None
    ref = np.asarray(integrators.frame(sc))
    assert np.array_equal(np.asarray(R.render("spheres", overrides=SHIPPED)), ref)
    on = np.asarray(R.render("spheres", overrides={**SHIPPED, "glare.aperture": "circle", "glare.size": 31}))
    assert np.all(np.isfinite(on)) and not np.array_equal(on, ref)
    np.testing.assert_allclose(on.astype(np.float64).sum((0, 1)), ref.astype(np.float64).sum((0, 1)), rtol=1e-6)
    assert sc.with_glare(G.Glare()).without_glare() == sc


def test_cli_glare_renders_the_whole_image_after_the_tiles(tmp_path, capsys):
    exr = tmp_path / "g.exr"
    rc, err = run_cli(["render", "spheres", "-q", "-o", exr, "--width", 24, "--height", 24,
                       "--glare", "blades=5,size=31,threshold=0.5", "--memory", "64M"], capsys)
    assert rc == 0, err
    from jaxrt import image

    got = image.read_exr(exr)
    ref = G.apply(integrators.frame(S.load("spheres", overrides=SHIPPED)), G.Glare(blades=5, size=31, threshold=0.5))
    np.testing.assert_allclose(got, np.asarray(ref), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("argv, needles", [
    (["--glare", "blades=2"], ["[glare] blades", "[3, 32]"]),
    (["--glare", "size=64"], ["[glare] size", "odd"]),
    (["--glare", "aperture=hexagon"], ["[glare] aperture", "polygon, circle"]),
    (["--glare", "aperture=circle,blades=6"], ["[glare] blades", "polygon"]),
    (["--glare", "f_number=1000"], ["[glare]", "size / 8"]),
    (["--glare", "strength"], ["--glare strength", "KEY=VALUE"]),
    (["--glare", "gain=2"], ["--glare gain=2", "unknown key 'gain'"]),
])
def test_cli_bad_glare_is_one_line_exit_2_before_work(argv, needles, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    one_line_error(*run_cli(["render", "spheres", *argv], capsys), *needles)
    assert list(tmp_path.iterdir()) == []


def test_scene_file_glare_table(tmp_path):
    text = S.find_scene("spheres").read_text()
    good = tmp_path / "good.toml"
    good.write_text(text + '\n[glare]\naperture = "polygon"\nblades = 7\nrotation = 10\nthreshold = 4\n')
    assert S.parse(good).glare == G.Glare(blades=7, rotation=10.0, threshold=4.0)
    empty = tmp_path / "empty.toml"
    empty.write_text(text + "\n[glare]\n")
    assert S.parse(empty).glare == G.Glare()
    bad = tmp_path / "bad.toml"
    for line, needles in [("strength = 1.5", ["bad.toml", "[glare] strength", "[0, 1]"]),
                          ("blur = 2", ["bad.toml", "[glare] blur", "unknown key"]),
                          ("blades = 4.0", ["bad.toml", "[glare] blades", "integer"])]:
        bad.write_text(text + f"\n[glare]\n{line}\n")
        with pytest.raises(InputError) as e:
            S.parse(bad)
        assert "\n" not in str(e.value) and all(n in str(e.value) for n in needles), str(e.value)
    with pytest.raises(InputError, match="pixel_pitch"):
        G.Glare(pixel_pitch=0.0)
    with pytest.raises(InputError, match="450 nm"):
        G.Glare(f_number=1.0)


def test_cli_glare_option_values():
    from jaxrt.cli.render import parse_glare_option

    assert parse_glare_option("on") == ("on", {}) and parse_glare_option("off") == ("off", {})
    mode, values = parse_glare_option("aperture=circle, f_number=22.5,size=63")
    assert mode == "set" and values == {"aperture": "circle", "f_number": 22.5, "size": 63}
    # the values become the [glare] table's, checked by the scene parser
    spec = S.parse(S.find_scene("spheres"), overrides={f"glare.{k}": v for k, v in values.items()})
    assert spec.glare == G.Glare(aperture="circle", f_number=22.5, size=63)


def test_cli_glare_off_renders_the_scene_without_its_glare_table(tmp_path, capsys):
    toml = tmp_path / "spheres_glare.toml"
    toml.write_text(S.find_scene("spheres").read_text() + "\n[glare]\nblades = 5\n")
    assert S.parse(toml).glare == G.Glare(blades=5)
    exr = tmp_path / "off.exr"
    rc, err = run_cli(["render", toml, "-q", "-o", exr, "--width", 24, "--height", 24, "--glare", "off"], capsys)
    assert rc == 0, err
    from jaxrt import image

    ref = np.asarray(integrators.frame(S.load("spheres", overrides=SHIPPED)))
    assert np.array_equal(image.read_exr(exr), ref)
