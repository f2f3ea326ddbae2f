"""Image I/O: linear EXR through OpenEXR, display PNG through the sRGB encoding of IEC 61966-2-1.

Both writers go through `jaxrt.fsutil.atomic_path`, so a failed or interrupted write never leaves
a half-written file. Images are (H, W, 3) linear RGB; extra single-channel AOVs (H, W) can be
stored beside the colour in the same EXR.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from jaxtyping import Float

from jaxrt.errors import InputError
from jaxrt.fsutil import atomic_path


def _finite_rgb(image, what: str) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise InputError(f"{what}: expected an (H, W, 3) RGB image, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise InputError(f"{what}: image contains NaN or Inf; refusing to write it")
    return img


def write_exr(
    path: str | os.PathLike,
    image: Float[np.ndarray, "H W 3"],
    aovs: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write a linear float32 RGB image (and optional AOVs) to an OpenEXR file, atomically.

    Args:
        image: (H, W, 3) linear RGB.
        aovs: name -> (H, W) or (H, W, 3) arrays; stored as channels `name` or `name.R/G/B`
            (single-channel ones keep their dtype if float, others are stored as float32).
    """
    import OpenEXR

    path = Path(path)
    img = _finite_rgb(image, str(path))
    channels: dict[str, np.ndarray] = {"RGB": np.ascontiguousarray(img)}
    for name, a in (aovs or {}).items():
        a = np.asarray(a)
        if a.shape[:2] != img.shape[:2]:
            raise InputError(f"{path}: AOV {name!r} has shape {a.shape}, expected {img.shape[:2]} leading dims")
        a = np.ascontiguousarray(np.nan_to_num(a.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0))
        if a.ndim == 3 and a.shape[-1] == 3:
            channels[f"{name}.RGB"] = a
        elif a.ndim == 2:
            channels[name] = a
        else:
            raise InputError(f"{path}: AOV {name!r} must be (H, W) or (H, W, 3), got {a.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))
    return path


def read_exr(path: str | os.PathLike, channels: bool = False):
    """Read an EXR written by `write_exr` (or any RGB EXR) as float32 (H, W, 3).

    With `channels=True` return a dict of every channel group instead (e.g. "RGB", "depth").
    Raises InputError for a missing/unreadable file or one without R, G, B channels.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such EXR file")
    try:
        with OpenEXR.File(str(path), separate_channels=False) as f:
            ch = {k: np.array(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises plain RuntimeError/OSError on corrupt input
        raise InputError(f"{path}: not a readable OpenEXR file ({e})") from None
    if channels:
        return ch
    if "RGB" in ch:
        return ch["RGB"]
    if "RGBA" in ch:
        return ch["RGBA"][..., :3]
    raise InputError(f"{path}: EXR has no RGB channels (found {', '.join(sorted(ch))})")


#: The allowed display exposure in stops: 2^±64 (1.8e19) is far beyond any useful display scaling
#: and stays finite in float32.
MAX_EXPOSURE = 64.0


def check_exposure(exposure: float, flag: str = "exposure") -> float:
    """`exposure` as a float if it is a number of stops in [-MAX_EXPOSURE, MAX_EXPOSURE], else InputError
    naming `flag`."""
    try:
        ev = float(exposure)
    except (TypeError, ValueError):
        ev = float("nan")
    if not -MAX_EXPOSURE <= ev <= MAX_EXPOSURE:
        raise InputError(f"{flag}: expected a number of stops in [{-MAX_EXPOSURE:g}, {MAX_EXPOSURE:g}], "
                         f"got {exposure!r}")
    return ev


def srgb_decode(v: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1:1999, the EOTF): encoded values in [0, 1] -> linear, float64.

    The arithmetic of colour-science's `eotf_sRGB` (the same break point, the linear segment's value at
    0.0031308, and the same operations), so the values are colour-science's bit for bit, without its
    import: `import colour` loads scipy and matplotlib, 1.5-2 CPU seconds, more than a small render."""
    v = np.asarray(v, np.float64)
    return np.where(_SRGB_BREAK >= v, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


#: The encoded value of the linear break point 0.0031308 (≈ 0.04045): the encoding's linear segment there.
_SRGB_BREAK = 0.0031308 * 12.92


@functools.cache
def _srgb_thresholds() -> np.ndarray:
    """The 255 linear values at which the 8-bit sRGB code steps up: code k covers linear values in
    [t[k-1], t[k]), t[k] = sRGB⁻¹((k + ½)/255) (IEC 61966-2-1, `srgb_decode`).

    Encoding by lookup in this table gives round(255 · sRGB(x)) (the sRGB curve is increasing), in
    float32 and without float64 temporaries; the tests compare it with the direct encoding."""
    mid = (np.arange(255, dtype=np.float64) + 0.5) / 255.0
    return srgb_decode(mid).astype(np.float32)


def to_srgb8(image: Float[np.ndarray, "H W 3"], exposure: float = 0.0) -> np.ndarray:
    """Linear RGB -> 8-bit sRGB: scale by 2^exposure, clip to [0, 1], sRGB transfer (IEC 61966-2-1,
    applied as a 256-level lookup: `_srgb_thresholds`)."""
    check_exposure(exposure)
    img = _finite_rgb(image, "image")
    t = _srgb_thresholds()
    out = np.empty(img.shape, np.uint8)
    scale = np.float32(2.0**exposure)
    rows = max(1, (1 << 20) // max(1, img.shape[1]))  # strips bound the float32 temporary
    for r in range(0, img.shape[0], rows):
        lin = np.clip(img[r:r + rows] * scale, 0.0, 1.0)
        out[r:r + rows] = np.searchsorted(t, lin, side="right")
    return out


def write_png(path: str | os.PathLike, image: Float[np.ndarray, "H W 3"], exposure: float = 0.0) -> Path:
    """Write a display PNG (sRGB-encoded, exposure in stops) atomically."""
    from PIL import Image

    path = Path(path)
    rgb8 = to_srgb8(image, exposure)
    with atomic_path(path) as tmp:
        # zlib level 1: a 1024² render encodes in ~0.15 s instead of ~0.25 s at PIL's default 6, for
        # a file ~10 % larger (a display copy beside the EXR; the time is part of every render's wait)
        Image.fromarray(rgb8, mode="RGB").save(tmp, format="PNG", compress_level=1)
    return path


def write(path: str | os.PathLike, image, exposure: float = 0.0, aovs: Mapping[str, np.ndarray] | None = None) -> Path:
    """Write by suffix: `.exr` (linear, with AOVs) or `.png` (sRGB with exposure)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".exr":
        return write_exr(path, image, aovs)
    if suffix == ".png":
        return write_png(path, image, exposure)
    raise InputError(f"{path}: unsupported image format {suffix!r}; allowed: .exr, .png")
