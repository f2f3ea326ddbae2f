"""Environment lighting: a latitude-longitude radiance map or a constant environment.

Mapping (the same as Mitsuba 3's `envmap`, so one EXR lights both renderers identically): in the
map's own frame (+y up) a unit direction d has

    u = atan2(d_x, -d_z) / 2π  (mod 1)      v = acos(d_y) / π           (row 0 = straight up)

and texel (row, col) = (floor(v·H), floor(u·W)) holds RGB radiance [W/(m²·sr)], looked up as a
piecewise-constant function (nearest texel, so lookup and sampling density describe the same
function). `rotate` turns the map about +y; `scale` multiplies it.

Importance sampling (pbrt-v4 sec. 12.5): the 2D piecewise-constant distribution over (u, v) with
weights luminance(texel)·sinθ(row centre), sampled through a marginal CDF over rows and one
conditional CDF per row. A (u, v) density p_uv becomes a solid-angle density
p_ω = p_uv / (2π² sinθ), the Jacobian of the lat-long map at the sampled θ. Directions with
sinθ = 0 (the poles) have pdf 0 and are never returned (a failed sample has pdf 0).

A constant environment (`radiance = [r, g, b]`) is sampled uniformly over the sphere, pdf 1/(4π).

OpenEXR files are read through OpenEXR (`jaxrt.image.read_exr`); Radiance RGBE files (.hdr, .pic)
through OpenCV (`pip install 'jaxrt[hdr]'`, opencv-python-headless), since nothing else in the stack
reads them (Pillow and matplotlib do not). Both give linear RGB with row 0 at the top (+y).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrt.errors import InputError
from jaxrt.shading.surface import dot

_LUM = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance weights: all positive, so lum = 0 iff black


def luminance(rgb: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Rec. 709 luminance of linear RGB."""
    return rgb[..., 0] * _LUM[0] + rgb[..., 1] * _LUM[1] + rgb[..., 2] * _LUM[2]


class EnvMap(eqx.Module):
    """Environment radiance (traced values; the texel shape and `uniform` are static).

    Attributes:
        texels: (H, W, 3) RGB radiance [W/(m²·sr)], scale applied; (1, 1, 3) for a constant one.
        rotation: (3, 3) world -> map frame (a rotation about +y).
        row_cdf: (H + 1,) marginal CDF over rows, from 0 to 1.
        col_cdf: (H, W + 1) conditional CDF over columns of each row, from 0 to 1.
        weight_sum: () Σ luminance·sinθ over all texels (0: a black map, nothing is sampled).
        uniform: static; True for a constant environment (uniform sphere sampling).
    """

    texels: Float[Array, "H W 3"]
    rotation: Float[Array, "3 3"]
    row_cdf: Float[Array, " H1"]
    col_cdf: Float[Array, "H W1"]
    weight_sum: Float[Array, ""]
    uniform: bool = eqx.field(static=True, default=False)

    def radiance(self, d: Float[Array, "*B 3"]) -> Float[Array, "*B 3"]:
        return radiance(self, d)

    def sample(self, u: Float[Array, "*B 2"]):
        return sample(self, u)

    def pdf(self, wi: Float[Array, "*B 3"]) -> Float[Array, "*B"]:
        return pdf(self, wi)


def _rotation_y(degrees: float) -> np.ndarray:
    # world -> map: the map turned by +degrees about +y means directions turn by -degrees
    a = math.radians(-degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], np.float32)


def constant(radiance_rgb) -> EnvMap:
    """A uniform environment of RGB radiance `radiance_rgb` [W/(m²·sr)]."""
    tex = jnp.asarray(np.broadcast_to(np.asarray(radiance_rgb, np.float32), (3,))).reshape(1, 1, 3)
    return EnvMap(tex, jnp.eye(3), jnp.array([0.0, 1.0]), jnp.array([[0.0, 1.0]]), jnp.asarray(1.0), uniform=True)


def from_array(texels: Float[np.ndarray, "H W 3"], scale: float = 1.0, rotate: float = 0.0) -> EnvMap:
    """A lat-long map from an (H, W, 3) array of non-negative finite radiance (host numpy)."""
    tex = np.asarray(texels, np.float64) * float(scale)
    if tex.ndim != 3 or tex.shape[-1] != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
        raise InputError(f"environment map: expected an (H, W, 3) RGB image, got shape {tex.shape}")
    if not np.all(np.isfinite(tex)) or np.any(tex < 0):
        raise InputError("environment map: texels must be finite and non-negative")
    if np.any(tex > np.finfo(np.float32).max):
        raise InputError(f"environment map: texels × scale reach {tex.max():g}, beyond float32's "
                         f"{np.finfo(np.float32).max:g}")
    h = tex.shape[0]
    theta = (np.arange(h) + 0.5) / h * np.pi
    f = (tex @ np.asarray(_LUM)) * np.sin(theta)[:, None]  # (H, W)
    row = f.sum(1)
    total = row.sum()
    row_cdf = np.concatenate([[0.0], np.cumsum(row)]) / (total if total > 0 else 1.0)
    col_cdf = np.concatenate([np.zeros((h, 1)), np.cumsum(f, 1)], 1) / np.where(row > 0, row, 1.0)[:, None]
    row_cdf[-1] = 1.0 if total > 0 else 0.0
    col_cdf[:, -1] = np.where(row > 0, 1.0, 0.0)
    return EnvMap(jnp.asarray(tex, jnp.float32), jnp.asarray(_rotation_y(rotate)), jnp.asarray(row_cdf, jnp.float32),
                  jnp.asarray(col_cdf, jnp.float32), jnp.asarray(total, jnp.float32), uniform=False)


SUFFIXES = (".exr", ".hdr", ".pic")


def _read_rgbe(path: Path):
    """(H, W, 3) float32 linear RGB of a Radiance RGBE file, through OpenCV."""
    try:
        import cv2
    except ImportError:
        raise InputError(f"{path}: reading Radiance .hdr needs OpenCV: pip install 'jaxrt[hdr]' "
                         "(opencv-python-headless), or convert the map to OpenEXR") from None
    if not path.is_file():
        raise InputError(f"{path}: no such environment map file")
    bgr = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if bgr is None or bgr.ndim != 3 or bgr.dtype != np.float32:
        raise InputError(f"{path}: not a readable Radiance RGBE (.hdr) image")
    return np.ascontiguousarray(bgr[..., ::-1])  # OpenCV orders channels B, G, R


def load(path: str | os.PathLike, scale: float = 1.0, rotate: float = 0.0) -> EnvMap:
    """Read a lat-long OpenEXR (.exr) or Radiance RGBE (.hdr, .pic) file (see module docstring);
    InputError naming the file otherwise."""
    from jaxrt import image

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(f"{path}: environment maps must be OpenEXR (.exr) or Radiance RGBE (.hdr, .pic) "
                         f"files, not {suffix or 'files without a suffix'}")
    tex = image.read_exr(path) if suffix == ".exr" else _read_rgbe(path)
    try:
        return from_array(tex, scale, rotate)
    except InputError as e:
        raise InputError(f"{path}: {e}") from None


def _rotate(m, d, transpose: bool):
    """m @ d (or m.T @ d) of each direction, as its three components: a row's `dot` with d each, written
    out, as XLA:CPU runs a (B, 3) x (3, 3) product as a library (YNNPACK) fusion that takes longer
    than the arithmetic."""
    m = m.T if transpose else m
    return tuple(dot(m[i], d) for i in range(3))


def _atan2(y, x):
    """atan2(y, x) in float32 from a polynomial, within ~3 ulp (XLA's: 1.5): Cephes' atanf (S. L.
    Moshier, "Methods and Programs for Mathematical Functions", 1989): the ratio of the smaller to
    the larger |component| in [0, 1], above tan(π/8) moved by (a - 1)/(a + 1) and π/4, an odd
    polynomial of degree 9, then the octant. XLA:CPU calls a scalar routine for atan2 and acos, one
    element at a time on one thread (~25-40 ns each against ~2-3 ns here, vectorised): a path
    tracer calls it for every escaped ray and environment pdf. Used on the CPU only (`_to_uv`). Signed zeros and infinities of the
    larger component as atan2's; atan2(±0, ±0) = ±0 or ±π by x's sign."""
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi, lo = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    a = lo / jnp.where(hi > 0, hi, 1.0)
    big = a > 0.41421356237309503  # tan(π/8)
    t = jnp.where(big, (a - 1.0) / (a + 1.0), a)
    z = t * t
    p = ((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1
    r = t + t * z * p
    r = jnp.where(big, r + math.pi / 4, r)
    r = jnp.where(ay > ax, math.pi / 2 - r, r)
    r = jnp.where(jnp.signbit(x), math.pi - r, r)
    return jnp.where(jnp.signbit(y), -r, r)


def _acos(c):
    """arccos(c) for c in [-1, 1] as `_atan2`(√((1 - c)(1 + c)), c): within ~3.5 ulp (1 - c and 1 + c
    are exact where they matter)."""
    return _atan2(jnp.sqrt((1.0 - c) * (1.0 + c)), c)


def _to_uv(env: EnvMap, d):
    dx, dy, dz = _rotate(env.rotation, d, transpose=False)
    # the polynomials on the CPU only: a GPU's atan2 and acos are fast and accurate already
    cpu = jax.default_backend() == "cpu"
    u = (_atan2 if cpu else jnp.arctan2)(dx, -dz) * (0.5 / math.pi)
    u = u - jnp.floor(u)
    cos_t = jnp.clip(dy, -1.0, 1.0)
    v = (_acos if cpu else jnp.arccos)(cos_t) / math.pi
    return u, v, jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))


def _from_uv(env: EnvMap, u, v):
    theta, phi = v * math.pi, u * 2.0 * math.pi
    st = jnp.sin(theta)
    d = jnp.stack([jnp.sin(phi) * st, jnp.cos(theta), -jnp.cos(phi) * st], axis=-1)
    # map -> world (the inverse of a rotation is its transpose)
    return jnp.stack(_rotate(env.rotation, d, transpose=True), axis=-1), st


def _texel(env: EnvMap, u, v):
    h, w = env.texels.shape[:2]
    r = jnp.clip(jnp.floor(v * h).astype(jnp.int32), 0, h - 1)
    c = jnp.clip(jnp.floor(u * w).astype(jnp.int32), 0, w - 1)
    return r, c


def radiance(env: EnvMap, d: Float[Array, "*B 3"]) -> Float[Array, "*B 3"]:
    """Radiance arriving from world direction d (unit, pointing away from the scene)."""
    if env.uniform:
        return jnp.broadcast_to(env.texels[0, 0], d.shape)
    u, v, _ = _to_uv(env, d)
    r, c = _texel(env, u, v)
    return env.texels[r, c]


def pdf(env: EnvMap, wi: Float[Array, "*B 3"]) -> Float[Array, "*B"]:
    """Solid-angle density [1/sr] with which `sample` returns world direction wi."""
    if env.uniform:
        return jnp.full(wi.shape[:-1], 1.0 / (4.0 * math.pi))
    h, w = env.texels.shape[:2]
    u, v, st = _to_uv(env, wi)
    r, c = _texel(env, u, v)
    p_row = env.row_cdf[r + 1] - env.row_cdf[r]
    p_col = env.col_cdf[r, c + 1] - env.col_cdf[r, c]
    p_uv = p_row * p_col * (h * w)
    ok = (st > 1e-7) & (env.weight_sum > 0)
    return jnp.where(ok, p_uv / (2.0 * math.pi**2 * jnp.where(ok, st, 1.0)), 0.0)


def _search_in_loop() -> bool:
    # `_count_le`'s binary search as a loop (CPU) or unrolled (elsewhere)
    return jax.default_backend() == "cpu"


def _count_le(cdf, row, u):
    """Number of entries <= u in row `row` of the nondecreasing rows of cdf (R, m), per sample:
    ``jnp.searchsorted(cdf[row], u, side="right")``, by a binary search that gathers one entry per
    step instead of each sample's whole row (on the CPU the row gathers of a vmapped searchsorted
    moved m floats per sample)."""
    m = cdf.shape[-1]

    def step(_, lohi):
        lo, hi = lohi
        mid = (lo + hi) >> 1  # both non-negative: the halving without a signed division's corrections
        right = cdf[row, jnp.minimum(mid, m - 1)] <= u
        open_ = lo < hi
        return jnp.where(open_ & right, mid + 1, lo), jnp.where(open_ & ~right, mid, hi)

    lohi = (jnp.zeros(jnp.shape(u), jnp.int32), jnp.full(jnp.shape(u), m, jnp.int32))
    if _search_in_loop():
        # a loop on the CPU: unrolled, XLA:CPU fuses the chain of dependent gathers into each consumer
        lo, _ = jax.lax.fori_loop(0, m.bit_length(), step, lohi)
        return lo  # each step halves [lo, hi): m + 1 candidate counts
    # unrolled elsewhere: on a GPU every iteration of a loop is a host round trip for its condition
    # plus copies of its state (~15 of each per environment sample of a path-tracing bounce); the
    # barrier keeps the result computed once rather than fused into each consumer
    for i in range(m.bit_length()):
        lohi = step(i, lohi)
    return jax.lax.optimization_barrier(lohi[0])


def _sample_cdf(cdf, u, row=None):
    """Index i with cdf[i] <= u < cdf[i+1] and the offset of u within that bin in [0, 1); with
    `row`, in row `row` of a 2-D cdf."""
    n = cdf.shape[-1] - 1
    if row is None:
        cdf, row = cdf[None], jnp.zeros(jnp.shape(u), jnp.int32)
    i = jnp.clip(_count_le(cdf, row, u) - 1, 0, n - 1)
    lo, hi = cdf[row, i], cdf[row, i + 1]
    width = hi - lo
    t = jnp.where(width > 0, (u - lo) / jnp.where(width > 0, width, 1.0), 0.5)
    return i, jnp.clip(t, 0.0, 1.0 - 1e-7)


def sample(env: EnvMap, u: Float[Array, "*B 2"]):
    """Importance-sample a direction from u in [0, 1)^2.

    Returns:
        wi (*B, 3) unit world direction towards the environment, radiance (*B, 3) arriving along
        it, pdf (*B,) solid-angle density [1/sr]; pdf 0 marks a failed sample (black map, pole).
    """
    u = jax.lax.stop_gradient(u)
    if env.uniform:
        z = 1.0 - 2.0 * u[..., 0]
        r = jnp.sqrt(jnp.maximum(1.0 - z * z, 0.0))
        phi = 2.0 * math.pi * u[..., 1]
        wi = jnp.stack([r * jnp.cos(phi), z, r * jnp.sin(phi)], axis=-1)
        return wi, jnp.broadcast_to(env.texels[0, 0], wi.shape), jnp.full(wi.shape[:-1], 1.0 / (4.0 * math.pi))
    h, w = env.texels.shape[:2]
    row_cdf = jax.lax.stop_gradient(env.row_cdf)
    col_cdf = jax.lax.stop_gradient(env.col_cdf)
    r, tv = _sample_cdf(row_cdf, u[..., 0])
    c, tu = _sample_cdf(col_cdf, u[..., 1], r)
    uu = (c + tu) / w
    vv = (r + tv) / h
    wi, st = _from_uv(env, uu, vv)
    p_uv = (row_cdf[r + 1] - row_cdf[r]) * (col_cdf[r, c + 1] - col_cdf[r, c]) * (h * w)
    ok = (st > 1e-7) & (p_uv > 0) & (env.weight_sum > 0)
    p = jnp.where(ok, p_uv / (2.0 * math.pi**2 * jnp.where(ok, st, 1.0)), 0.0)
    return wi, jnp.where(ok[..., None], env.texels[r, c], 0.0), p
