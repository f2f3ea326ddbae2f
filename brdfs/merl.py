"""MERL measured BRDFs: the `.binary` tables of Matusik et al. 2003, interpolated in JAX.

W. Matusik, H. Pfister, M. Brand and L. McMillan, "A Data-Driven Reflectance Model", ACM TOG 22(3)
(SIGGRAPH 2003). Each file tabulates an isotropic BRDF over Rusinkiewicz's (1998) half/difference
angles (brdfs.halfdiff):

    int32 dims[3] = {90, 90, 180}                    (θh, θd, φd), little-endian
    float64 values[3][90][90][180]                   planar: all R, then G, then B; φd fastest
    12 + 34,992,000 bytes

    BRDF [1/sr] = value × scale,   scale = (1/1500, 1.15/1500, 1.66/1500) for (R, G, B)
    θh = (i/90)² · π/2   (index i = sqrt(θh / (π/2)) · 90, the non-linear spacing)
    θd = j · π/180,      φd = k · π/180 over [0, π)  (f(φd + π) = f(φd) by reciprocity)
    negative values mark samples that were not measured

Interpolation. Sample (i, j, k) sits at exactly those angles (as in the reference lookup of the
MERL distribution and the interpolating reader of Sztrajman et al.'s `fastmerl.py`); `eval` is
trilinear in the continuous indices (sqrt(θh/(π/2))·90, θd/(π/2)·90, (φd mod π)/π·180): θh and θd
are clamped to the table (nearest value beyond index 89, i.e. θh > 88.0° or θd > 89°), φd is
periodic (index 179 interpolates towards index 0 = φd of π). Missing samples are left out: the
weights of the valid corners among the eight are renormalised, so a cell with some missing corners
takes the weighted mean of the others, and a point whose eight corners are all missing is 0. `eval`
is 0 unless both directions are above the horizon.

Parameters. The pytree is {"table": (..., 90, 90, 180, 3) float32 [1/sr] (missing = -1),
"cdf": (..., 11, 65), "pmf": (..., 11, 64), "ps": (..., 11)} (the last three are the importance
sampler's tables, brdfs._measured_sampling); `load(path)` builds it from a file, `from_table` from an array.
Sampling mixes cosine sampling with a half-vector lobe tabulated from the data at load time.

`tabulate(model, p)` samples any model on the MERL grid and `write` stores a table as a `.binary`
file (both used by the tests, and to convert analytic materials to the format).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs import _measured_sampling as S
from brdfs.base import Lobe, Model, Params
from brdfs.errors import InputError
from brdfs.halfdiff import angles, directions

RES = (90, 90, 180)
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
HEADER_BYTES = 12
FILE_BYTES = HEADER_BYTES + 3 * 8 * RES[0] * RES[1] * RES[2]  # 34,992,012
MISSING = -1.0

SHAPES = {"table": RES + (3,), **S.SHAPES}


def read(path: str | os.PathLike) -> np.ndarray:
    """The BRDF table (90, 90, 180, 3) float32 [1/sr] of a MERL `.binary` file, missing samples = -1.

    Raises InputError (one line naming the file) for a missing file, a wrong size, wrong dims, or
    non-finite values.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(HEADER_BYTES)
            if size != FILE_BYTES:
                raise InputError(f"{path}: not a MERL .binary BRDF: {size} bytes, expected {FILE_BYTES} "
                                 f"(12-byte header + 3 x 90 x 90 x 180 float64)")
            dims = tuple(int(d) for d in np.frombuffer(head, "<i4"))
            if dims != RES:
                raise InputError(f"{path}: MERL header dims {dims}, expected {RES} (theta_h, theta_d, phi_d)")
            raw = np.fromfile(fh, "<f8", count=3 * math.prod(RES))
    except OSError as e:
        raise InputError(f"{path}: cannot read MERL file ({e.strerror or e})") from None
    if not np.all(np.isfinite(raw)):
        bad = int(np.sum(~np.isfinite(raw)))
        raise InputError(f"{path}: MERL table has {bad} non-finite (NaN or infinite) values")
    raw = raw.reshape((3,) + RES)
    table = np.moveaxis(raw, 0, -1) * SCALE
    return np.where(table < 0, MISSING, table).astype(np.float32)


def write(path: str | os.PathLike, table) -> None:
    """Write a (90, 90, 180, 3) table [1/sr] (negative = missing) as a MERL `.binary` file, atomically
    (written beside the target and renamed, so no half-written file is left)."""
    path = Path(path)
    t = np.asarray(table, np.float64)
    if t.shape != RES + (3,):
        raise InputError(f"{path}: MERL table must have shape {RES + (3,)}, got {t.shape}")
    raw = np.where(t < 0, MISSING, t / SCALE)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(np.asarray(RES, "<i4").tobytes())
            fh.write(np.ascontiguousarray(np.moveaxis(raw, -1, 0), "<f8").tobytes())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def grid_angles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(θh (90,), θd (90,), φd (180,)) [radians] of the table's samples (float64)."""
    i = np.arange(RES[0], dtype=np.float64)
    return ((i / RES[0]) ** 2 * (math.pi / 2), np.arange(RES[1]) * (math.pi / 2) / RES[1],
            np.arange(RES[2]) * math.pi / RES[2])


def tabulate(model: Model, p: Params, chunk: int = 90) -> np.ndarray:
    """Sample `model` at the MERL grid: (90, 90, 180, 3) float32 [1/sr]; samples whose wi or wo is
    at or below the horizon are marked missing (-1), as a measurement cannot see them."""
    th, td, pd = grid_angles()
    out = np.empty(RES + (3,), np.float32)
    for a in range(0, RES[0], chunk):
        wi, wo = directions(th[a:a + chunk, None, None], td[None, :, None], pd[None, None, :], xp=np)
        f = np.asarray(model.eval(p, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)))
        ok = (wi[..., 2] > 1e-6) & (wo[..., 2] > 1e-6)
        out[a:a + chunk] = np.where(ok[..., None], f, MISSING)
    return out


def _corner_index(x, n: int, periodic: bool):
    """Lower corner, upper corner and fraction of continuous index x on a grid of n samples."""
    if periodic:
        x = jnp.mod(x, n)
        i0 = jnp.clip(jnp.floor(x), 0, n - 1)
        return i0.astype(jnp.int32), ((i0 + 1) % n).astype(jnp.int32), jnp.clip(x - i0, 0.0, 1.0)
    x = jnp.clip(x, 0.0, n - 1.0)
    i0 = jnp.clip(jnp.floor(x), 0, n - 2)
    return i0.astype(jnp.int32), (i0 + 1).astype(jnp.int32), x - i0


def lookup(table: Float[Array, "... 90 90 180 3"], theta_h, theta_d, phi_d) -> Float[Array, "... 3"]:
    """Trilinear interpolation of the table at angles [radians] (missing samples left out; see the
    module docstring). The table's batch dimensions broadcast against the angles'."""
    nh, nd, npd = RES
    xh = C.safe_sqrt(theta_h / (math.pi / 2)) * nh
    xd = theta_d / (math.pi / 2) * nd
    xp = phi_d / math.pi * npd
    (h0, h1, th), (d0, d1, td), (p0, p1, tp) = (_corner_index(xh, nh, False), _corner_index(xd, nd, False),
                                                 _corner_index(xp, npd, True))
    batch_t = table.shape[:-4]
    flat = table.reshape((-1, 3))
    nb = math.prod(batch_t)
    if nb > 1:  # offset of each direction's own table in the flattened stack
        full = jnp.broadcast_shapes(batch_t, jnp.shape(xh))
        mat = jnp.broadcast_to(jnp.arange(nb).reshape(batch_t), full) * (nh * nd * npd)
    else:
        mat = 0
    num = 0.0
    den = 0.0
    for ih, wh in ((h0, 1.0 - th), (h1, th)):
        for idd, wd in ((d0, 1.0 - td), (d1, td)):
            for ip, wp in ((p0, 1.0 - tp), (p1, tp)):
                v = flat[mat + (ih * nd + idd) * npd + ip]  # (..., 3)
                w = (wh * wd * wp)[..., None]
                valid = v >= 0
                num = num + jnp.where(valid, w * v, 0.0)
                den = den + jnp.where(valid, w, 0.0)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    ok = C.upper(wi, wo)
    th, td, pd = angles(wi, wo)
    f = lookup(p["table"], th, td, pd)
    return jnp.where(ok[..., None], f, 0.0)


sample, pdf = S.make(eval)


def from_table(table, where: str = "table") -> Params:
    """The parameter pytree of one material from its (90, 90, 180, 3) table (adds the sampler's table)."""
    t = np.asarray(table, np.float32)
    if t.shape != RES + (3,):
        raise InputError(f"{where}: MERL table must have shape {RES + (3,)}, got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{where}: MERL table has non-finite values")
    p = {"table": jnp.asarray(np.where(t < 0, MISSING, t), jnp.float32)}
    return {**p, **S.build(eval, p)}


def load(path: str | os.PathLike) -> Params:
    """Parameters of the MERL `.binary` file at `path` (InputError for a bad file, see `read`)."""
    return from_table(read(path), str(path))


MODEL = Model(
    name="merl",
    spec=(),
    eval=eval,
    sample=sample,
    pdf=pdf,
    energy_conserving=False,
    reciprocal=True,
    flags=Lobe.REFLECTION | Lobe.GLOSSY,  # no diffuse-colour parameter: diffuse_albedo is 0
    mixture=S.COMPONENTS,
    data_shapes=SHAPES,
    doc=__doc__,
)
