"""Neural BRDFs: the per-material MLPs of Sztrajman et al. 2021, evaluated in pure JAX.

A. Sztrajman, G. Rainer, T. Ritschel and T. Weyrich, "Neural BRDF Representation and Importance
Sampling", Computer Graphics Forum 40(6), 2021. Each material of the MERL 100 (Matusik, Pfister, Brand
& McMillan, "A Data-Driven Reflectance Model", SIGGRAPH 2003), RGL-EPFL isotropic (Dupuy & Jakob 2018)
and Nielsen et al. 2015 databases is a 6-21-21-3 network trained on the measurement:

    x = (sin θh, 0, cos θh, dx, dy, dz)        Rusinkiewicz 1998 half/difference coordinates with φh = 0
                                               (brdfs.halfdiff; d is computed from wi, the light side)
    a1 = ReLU(x W1 + b1),  a2 = ReLU(a1 W2 + b2),  z = a2 W3 + b3       W1 (6, 21), W2 (21, 21), W3 (21, 3)
    f(wi, wo) = max(exp(z) - 1, 0)   [1/sr, linear RGB]                 0 unless both wi, wo are above the horizon

The network was trained on directions above the horizon only and approximates the measurement (it is
"the neural stand-in of the measured material", not the measurement). It is reciprocal only
approximately: swapping wi and wo maps φd -> φd + π, a different network input; over directions
within 80° of the normal the median relative difference |f(wi, wo) - f(wo, wi)| / max is 2 % (median
over the 159 materials; 31 % for the worst), so `reciprocal=False`. Its albedo is not bounded by
construction (`energy_conserving=False`): the largest channel albedo over θo = 0°, 30°, 60°, 80° is
1.10 (rgl/satin_rosaline_rgb at 80°), and five RGL materials exceed 1 somewhere.

Parameters. A measured material's parameters are its data, not sliders: the pytree is

    {"W1": (..., 6, 21), "b1": (..., 21), "W2": (..., 21, 21), "b2": (..., 21), "W3": (..., 21, 3),
     "b3": (..., 3), "cdf": (..., 11, 65), "pmf": (..., 11, 64), "ps": (..., 11)}

(the last three are the importance sampler's tables, brdfs._measured_sampling), leading batch
dimensions broadcasting against the directions' as for every model, so one compiled function serves
every material and `jax.vmap` runs over a stack of materials. `load("merl/alum-bronze")` or
`load(path_to_h5)` builds it; `MODEL.spec` is empty (nothing to tune).

Weights come from the `.h5` files (HDF5, read with h5py): exactly the six datasets
`dense_N/dense_N/{kernel,bias}:0` with the shapes above; any other layout is refused. The Keras `.json`
beside each file is never read: its last layer is marshalled Python bytecode, and the architecture
is fixed anyway.

Sampling: cosine-weighted sampling mixed with a half-vector lobe tabulated from the network at load
time (brdfs._measured_sampling).
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs import _measured_sampling as S
from brdfs.base import Lobe, Model, Params
from brdfs.errors import InputError
from brdfs.halfdiff import half_diff

#: (parameter name, dataset in the .h5 file, shape)
LAYOUT = (
    ("W1", "dense_1/dense_1/kernel:0", (6, 21)),
    ("b1", "dense_1/dense_1/bias:0", (21,)),
    ("W2", "dense_2/dense_2/kernel:0", (21, 21)),
    ("b2", "dense_2/dense_2/bias:0", (21,)),
    ("W3", "dense_3/dense_3/kernel:0", (21, 3)),
    ("b3", "dense_3/dense_3/bias:0", (3,)),
)
#: core shape of every parameter-pytree entry (batch dimensions come before these)
SHAPES = {**{k: s for k, _, s in LAYOUT}, **S.SHAPES}


def read_weights(source: str | os.PathLike | bytes, where: str | None = None) -> dict[str, np.ndarray]:
    """The six weight arrays (float32) of a neural-BRDF .h5 file, keyed W1, b1, W2, b2, W3, b3.

    `source` is a path or the file's bytes (e.g. a zip member); `where` names it in errors. Raises
    InputError (one line naming the file) unless the file is HDF5 with exactly the datasets and shapes
    of `LAYOUT`, all finite.
    """
    import h5py

    where = where or str(source)
    try:
        fh = h5py.File(io.BytesIO(source) if isinstance(source, bytes) else source, "r")
    except (OSError, ValueError) as e:
        raise InputError(f"{where}: not a readable HDF5 neural-BRDF file ({e})") from None
    with fh:
        found: dict[str, tuple] = {}
        fh.visititems(lambda n, o: found.__setitem__(n, o.shape) if isinstance(o, h5py.Dataset) else None)
        want = {d: s for _, d, s in LAYOUT}
        if found != want:
            got = ", ".join(f"{k} {v}" for k, v in sorted(found.items())) or "no datasets"
            raise InputError(f"{where}: not the 6-21-21-3 network of Sztrajman et al. 2021 (expected datasets "
                             f"{', '.join(f'{k} {v}' for k, v in want.items())}; found {got})")
        out = {}
        for name, ds, _ in LAYOUT:
            a = np.asarray(fh[ds][()])
            if a.dtype.kind != "f" or not np.all(np.isfinite(a)):
                raise InputError(f"{where}: dataset {ds} is not finite floating point")
            out[name] = a.astype(np.float32)
    return out


def encode(wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 6"]:
    """The network input (sin θh, 0, cos θh, dx, dy, dz) (..., 6)."""
    s, c, d = half_diff(wi, wo)
    return jnp.concatenate([jnp.stack([s, jnp.zeros_like(s), c], axis=-1), d], axis=-1)


def _dense(x, w, b):
    if w.ndim == 2:
        return x @ w + b
    return jnp.matmul(x[..., None, :], w)[..., 0, :] + b


def network(p: Params, x: Float[Array, "... 6"]) -> Float[Array, "... 3"]:
    """max(exp(z) - 1, 0) of the MLP at inputs x (..., 6); weights may carry batch dimensions."""
    a = jax.nn.relu(_dense(x, p["W1"], p["b1"]))
    a = jax.nn.relu(_dense(a, p["W2"], p["b2"]))
    return jnp.maximum(jnp.expm1(_dense(a, p["W3"], p["b3"])), 0.0)


def eval(p: Params, wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """BRDF value [1/sr], (..., 3); 0 when either direction is at or below the horizon."""
    ok = C.upper(wi, wo)
    f = network(p, encode(wi, wo))
    return jnp.where(ok[..., None], f, 0.0)


sample, pdf = S.make(eval)


def from_weights(weights: dict) -> Params:
    """The parameter pytree of one material from its six weight arrays (adds the sampler's table)."""
    p = {k: jnp.asarray(weights[k], jnp.float32) for k, _, _ in LAYOUT}
    return {**p, **S.build(eval, p)}


def load(source: str | os.PathLike) -> Params:
    """Parameters of a neural BRDF: a name "merl/alum-bronze" (found through brdfs.measured_data) or
    the path of a file ending in .h5. InputError for an unknown name, a missing or corrupt archive or file."""
    from brdfs import measured_data

    s = os.fspath(source)
    if not s.endswith(".h5"):
        m = measured_data.find_material(s)
        return from_weights(read_weights(m.read_bytes(), f"{m.archive}:{m.member}"))
    if not Path(s).is_file():
        raise InputError(f"{s}: neural-BRDF file not found")
    return from_weights(read_weights(s))


MODEL = Model(
    name="nbrdf",
    spec=(),
    eval=eval,
    sample=sample,
    pdf=pdf,
    energy_conserving=False,
    reciprocal=False,
    flags=Lobe.REFLECTION | Lobe.GLOSSY,  # no diffuse-colour parameter: diffuse_albedo is 0
    mixture=S.COMPONENTS,
    data_shapes=SHAPES,
    doc=__doc__,
)
