"""Textures: UV-mapped images and a procedural checkerboard for any material parameter.

A `Texture` is a pytree whose values (texels, uv scale and offset) are traced and whose kind and
wrap mode are static: changing a texture's contents never recompiles, changing its size may.

Lookup conventions (`lookup(tex, uv)`):
- uv = (0, 0) is the image's bottom-left corner and (1, 1) its top-right (OpenGL / pbrt / OBJ
  convention: v grows upwards while image rows grow downwards). uv is first mapped by
  uv' = uv * uv_scale + uv_offset.
- Image textures are filtered bilinearly between texel centres, which lie at ((i + 0.5)/W,
  (j + 0.5)/H); the wrap mode decides the neighbours outside [0, 1): "repeat" (period 1),
  "clamp" (edge texels extend), "mirror" (period 2, reflected every other tile).
- The checkerboard alternates its two values on unit cells of uv': value 0 where
  floor(u') + floor(v') is even, value 1 where it is odd (so `scale = 8` gives 8 x 8 cells over
  [0, 1]^2). It has no filtering; the wrap mode does not apply.
- The result is differentiable with respect to the texels (a bilinear gather is linear in them),
  the checker values, uv_scale, uv_offset and uv (piecewise linear; the checker is piecewise
  constant in uv).

Files (`read_image`): PNG (8 or 16 bit, via Pillow) and OpenEXR (via `jaxrt.image.read_exr`, linear).
PNG values are decoded from sRGB to linear (IEC 61966-2-1, `jaxrt.image.srgb_decode`) for RGB
parameters (colours), and read as linear values v / (2^bits - 1) for scalar parameters (roughness-like maps are data, not
colours). A scalar parameter needs a one-channel image (grey PNG, or an EXR with a Y or a single
channel), an RGB parameter a three-channel one (an alpha channel is ignored; a grey image is
broadcast to RGB). Values outside the parameter's declared
[lo, hi] or non-finite values are an `InputError` naming the file and the field (not clipped:
an out-of-range map is almost always a mistake, e.g. an sRGB colour map used for roughness).
"""

from __future__ import annotations

import os
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrt.errors import InputError

WRAPS = ("repeat", "clamp", "mirror")
KINDS = ("image", "checker")


class Texture(eqx.Module):
    """One texture.

    texels: (H, W, C) linear values (image), or (1, 2, C) the two checker values; C = 3 for RGB
        parameters, 1 for scalar ones.
    uv_scale, uv_offset: (2,) affine map applied to uv before the lookup.
    kind: "image" | "checker" (static); wrap: "repeat" | "clamp" | "mirror" (static).
    """

    texels: Float[Array, "H W C"]
    uv_scale: Float[Array, "2"]
    uv_offset: Float[Array, "2"]
    kind: str = eqx.field(static=True, default="image")
    wrap: str = eqx.field(static=True, default="repeat")


def _wrap_index(i, n: int, wrap: str):
    """Integer texel index i (any integer) -> [0, n) under the wrap mode."""
    if wrap == "repeat":
        return jnp.mod(i, n)
    if wrap == "clamp":
        return jnp.clip(i, 0, n - 1)
    m = jnp.mod(i, 2 * n)  # mirror: 0..n-1 forwards, then n-1..0
    return jnp.where(m < n, m, 2 * n - 1 - m)


def lookup(tex: Texture, uv: Float[Array, "... 2"]) -> Float[Array, "... C"]:
    """Filtered texture value at uv (see the module docstring), (..., C) with C the texel channels."""
    uvp = uv * tex.uv_scale + tex.uv_offset
    if tex.kind == "checker":
        cell = jnp.floor(uvp[..., 0]) + jnp.floor(uvp[..., 1])
        odd = jnp.mod(cell, 2.0) >= 1.0
        return jnp.where(odd[..., None], tex.texels[0, 1], tex.texels[0, 0])
    h, w = tex.texels.shape[0], tex.texels.shape[1]
    x = uvp[..., 0] * w - 0.5
    y = (1.0 - uvp[..., 1]) * h - 0.5  # row 0 is the top of the image, v = 1
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    i0, j0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    i0w, i1w = _wrap_index(i0, w, tex.wrap), _wrap_index(i0 + 1, w, tex.wrap)
    j0w, j1w = _wrap_index(j0, h, tex.wrap), _wrap_index(j0 + 1, h, tex.wrap)
    t = tex.texels
    top = (1.0 - fx) * t[j0w, i0w] + fx * t[j0w, i1w]
    bottom = (1.0 - fx) * t[j1w, i0w] + fx * t[j1w, i1w]
    return (1.0 - fy) * top + fy * bottom


def make(texels, kind: str = "image", wrap: str = "repeat", uv_scale=(1.0, 1.0), uv_offset=(0.0, 0.0)) -> Texture:
    """A `Texture` from numpy/array values (no validation; see `jaxrt.scene` for the checked path)."""
    texels = jnp.asarray(texels, jnp.float32)
    if texels.ndim == 2:
        texels = texels[..., None]
    return Texture(texels, jnp.broadcast_to(jnp.asarray(uv_scale, jnp.float32), (2,)),
                   jnp.broadcast_to(jnp.asarray(uv_offset, jnp.float32), (2,)), kind, wrap)


def value(tex: Texture, uv: Float[Array, "... 2"], rgb: bool) -> Float[Array, "..."]:
    """`lookup` shaped like a parameter: (..., 3) for RGB parameters, (...) for scalar ones."""
    v = lookup(tex, uv)
    if rgb:
        return jnp.broadcast_to(v, v.shape[:-1] + (3,))
    return v[..., 0]


# ---- files -----------------------------------------------------------------------------------

def read_image(path: str | os.PathLike, rgb: bool, where: str) -> np.ndarray:
    """Read a PNG or EXR texture as float32 (H, W, 3) (rgb) or (H, W, 1), linear (see module docstring).

    Raises InputError naming `where` (the scene field) and the file for a missing/unreadable file,
    an unsupported extension or a channel count that does not fit the parameter.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{where}: texture file {path} does not exist")
    ext = path.suffix.lower()
    if ext == ".png":
        try:
            from PIL import Image

            with Image.open(path) as im:
                mode = im.mode
                arr = np.asarray(im)
        except Exception as e:  # Pillow raises several kinds on corrupt files
            raise InputError(f"{where}: {path} is not a readable PNG ({e})") from None
        bits = 16 if arr.dtype == np.uint16 or mode.startswith("I;16") or mode == "I" else 8
        if mode == "P":
            raise InputError(f"{where}: {path}: palette PNGs are not supported; save it as grey or RGB")
        vals = arr.astype(np.float64) / (2**bits - 1)
        if vals.ndim == 2:
            vals = vals[..., None]
        chans = vals.shape[-1]
        if chans in (2, 4):  # drop alpha
            vals = vals[..., :-1]
        if rgb:
            from jaxrt.image import srgb_decode

            vals = srgb_decode(vals)
    elif ext == ".exr":
        from jaxrt.image import read_exr

        groups = read_exr(path, channels=True)  # {"RGB": (H, W, 3), "Y": (H, W), ...}
        if rgb and ("RGB" in groups or "RGBA" in groups):
            vals = groups["RGB"] if "RGB" in groups else groups["RGBA"][..., :3]
        elif "Y" in groups:
            vals = groups["Y"]
        elif len(groups) == 1:
            vals = next(iter(groups.values()))
        else:
            raise InputError(f"{where}: {path} has channels {', '.join(sorted(groups))}; allowed: "
                             f"{'RGB or ' if rgb else ''}a single channel (Y)")
        vals = np.asarray(vals, np.float64)
        if vals.ndim == 2:
            vals = vals[..., None]
    else:
        raise InputError(f"{where}: texture {path} has an unsupported type {ext!r}; allowed: .png, .exr")
    c = vals.shape[-1]
    if rgb:
        if c == 1:
            vals = np.repeat(vals, 3, axis=-1)
        elif c != 3:
            raise InputError(f"{where}: {path} has {c} channels; allowed for an RGB parameter: 1 or 3 (+ alpha)")
    elif c != 1:
        raise InputError(f"{where}: {path} has {c} colour channels but the parameter is a scalar; "
                         "allowed: a one-channel (grey) image")
    if vals.shape[0] < 1 or vals.shape[1] < 1:
        raise InputError(f"{where}: {path} is empty")
    return vals.astype(np.float32)
