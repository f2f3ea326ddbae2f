"""EXR/PNG output: round trips, sRGB encoding against the IEC 61966-2-1 formula, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest

from jaxrt import image
from jaxrt.errors import InputError


def test_exr_round_trips_bit_exactly_with_aovs(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 50, (7, 5, 3)).astype(np.float32)
    depth = rng.uniform(0, 9, (7, 5)).astype(np.float32)
    p = image.write_exr(tmp_path / "a.exr", img, {"depth": depth, "normal": -img})
    assert np.array_equal(image.read_exr(p), img)
    ch = image.read_exr(p, channels=True)
    assert np.array_equal(ch["depth"], depth) and np.array_equal(ch["normal.RGB"], -img)


def test_png_is_srgb_encoded_with_exposure(tmp_path):
    from PIL import Image

    lin = np.linspace(0, 1.2, 60, dtype=np.float32)
    img = np.stack([lin, lin * 0.5, lin * 0.25], -1)[None]
    p = image.write_png(tmp_path / "a.png", img, exposure=1.0)
    got = np.asarray(Image.open(p)).astype(np.int64)
    x = np.clip(img.astype(np.float64) * 2.0, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)  # IEC 61966-2-1
    assert np.abs(got - np.round(srgb * 255)).max() <= 1


def test_srgb_lookup_equals_the_direct_encoding_away_from_code_boundaries():
    """The 256-level lookup of `to_srgb8` gives round(255 sRGB(x)) as colour-science's float64 curve
    computes it, for every float32 value on a dense sweep, except within 1e-6 (relative) of the 255
    code boundaries, where float rounding of the two computations may differ by one code."""
    import colour

    x = np.concatenate([np.linspace(0, 1, 400_003, dtype=np.float32),
                        np.geomspace(1e-9, 1e-2, 20_000).astype(np.float32)])
    got = image.to_srgb8(np.repeat(x[None, :, None], 3, -1))[0, :, 0].astype(np.int64)
    ref = np.round(np.asarray(colour.cctf_encoding(x.astype(np.float64), function="sRGB")) * 255).astype(np.int64)
    edges = np.asarray(colour.cctf_decoding((np.arange(255) + 0.5) / 255, function="sRGB"))
    i = np.clip(np.searchsorted(edges, x), 1, 254)
    gap = np.minimum(np.abs(x - edges[i - 1]) / edges[i - 1], np.abs(x - edges[i]) / edges[i])
    near = gap < 1e-6
    assert np.abs(got - ref).max() <= 1
    assert np.array_equal(got[~near], ref[~near]) and near.mean() < 1e-3
    assert got[0] == 0 and got[400_002] == 255  # 0 and 1 map to the end codes


def test_srgb_decoding_is_colour_sciences_bit_for_bit():
    """`srgb_decode` (no colour-science import) gives colour-science's sRGB EOTF exactly: every 8- and
    16-bit code, the values around the curve's break point, and the PNG encoder's 255 code edges."""
    import colour

    brk = 0.0031308 * 12.92
    v = np.concatenate([np.arange(256) / 255, np.arange(65536) / 65535,
                        np.nextafter(brk, np.array([0.0, 1.0])), [brk], (np.arange(255) + 0.5) / 255])
    ref = np.asarray(colour.cctf_decoding(v, function="sRGB"), np.float64)
    got = image.srgb_decode(v)
    assert got.dtype == np.float64 and np.array_equal(got, ref)
    # the lookup table of `to_srgb8`, hence every PNG, is the one colour-science's curve gives
    edges = (np.arange(255) + 0.5) / 255
    assert np.array_equal(image.to_srgb8(np.repeat(
        np.asarray(colour.cctf_decoding(edges, function="sRGB")).astype(np.float32)[None, :, None], 3, -1))[0, :, 0],
        np.arange(1, 256))


def test_non_finite_images_are_refused_and_nothing_is_written(tmp_path):
    img = np.zeros((2, 2, 3), np.float32)
    img[0, 0, 1] = np.nan
    for name in ("a.exr", "a.png"):
        with pytest.raises(InputError, match="NaN or Inf"):
            image.write(tmp_path / name, img)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    p = tmp_path / "keep.exr"
    old = np.ones((2, 2, 3), np.float32)
    image.write_exr(p, old)
    import OpenEXR

    class Boom:
        def __init__(self, *a, **k):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *a):
            return False

        def write(self, path):
            open(path, "wb").write(b"partial")
            raise OSError("disk full")

    monkeypatch.setattr(OpenEXR, "File", Boom)
    with pytest.raises(OSError):
        image.write_exr(p, np.zeros((2, 2, 3), np.float32))
    monkeypatch.undo()
    assert np.array_equal(image.read_exr(p), old)
    assert [q.name for q in tmp_path.iterdir()] == ["keep.exr"]


def test_read_errors(tmp_path):
    with pytest.raises(InputError, match="no such EXR"):
        image.read_exr(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(InputError, match="not a readable OpenEXR"):
        image.read_exr(tmp_path / "bad.exr")
    with pytest.raises(InputError, match="shape"):
        image.write_exr(tmp_path / "x.exr", np.zeros((2, 2)))


def test_render_writes_exr_and_png_at_once_as_one_after_the_other(tmp_path):
    """`jaxrt render`'s writers run at the same time (`cli.render.write_outputs`): the files equal
    those of the writers called one after the other, byte for byte, and an error in either (a
    non-finite pixel) reaches the caller after both have finished."""
    from jaxrt.cli.render import write_outputs

    rng = np.random.default_rng(3)
    img = rng.random((96, 128, 3), dtype=np.float32) * 2.0
    aovs = {"depth": rng.random((96, 128), dtype=np.float32)}
    image.write_exr(tmp_path / "one.exr", img, aovs)
    image.write_png(tmp_path / "one.png", img, exposure=0.5)
    tmp = {"a.exr": tmp_path / "both.exr", "a.png": tmp_path / "both.png"}
    write_outputs(tmp, "a.exr", "a.png", img, aovs, 0.5)
    assert (tmp_path / "both.exr").read_bytes() == (tmp_path / "one.exr").read_bytes()
    assert (tmp_path / "both.png").read_bytes() == (tmp_path / "one.png").read_bytes()
    bad = img.copy()
    bad[5, 7, 1] = np.nan
    with pytest.raises(InputError):
        write_outputs({"a.exr": tmp_path / "x.exr", "a.png": tmp_path / "x.png"}, "a.exr", "a.png", bad, None, 0.0)
