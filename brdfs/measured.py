"""Measured materials as models: one entry point for scene files, the CLI and studies.

    import brdfs.measured as measured
    model, p = measured.load("merl/gold-metallic-paint")   # neural stand-in (brdfs.nbrdf)
    model, p = measured.load("scans/alum-bronze.binary")   # a MERL table (brdfs.merl)
    f = model.eval(p, wi, wo); brdfs.albedo(model, p, wo)  # like any model
    names = measured.names()                              # all 159 neural materials
    stacked = measured.stack([measured.load(n)[1] for n in names[:100]])   # vmap over materials

Design. A measured material is a *parameter pytree* of a fixed model, not a model of its own: the
model (`brdfs.nbrdf.MODEL`, `brdfs.merl.MODEL`) holds the pure functions, and the pytree holds the
material's data (network weights or the MERL table, plus the importance sampler's table), with
leading batch dimensions broadcasting like any model's parameters. So one compiled function serves
every material of a kind, `jax.vmap` runs over a stack of them (the measured-material study fits 100
materials in one batched call), and the models stay hashable static jit arguments. The models'
`spec` is empty: there is nothing to tune, so loaders, sliders and fits that walk `spec` see no
parameters; `Model.data_shapes` gives the core shape of each data entry (brdfs.analysis uses it
to insert batch axes).

`load(data, base=None)`: `data` is a material name "COLLECTION/NAME" (brdfs.measured_data) or a file
path, relative to `base` (e.g. a scene file's folder) when not absolute: `.binary` -> MERL table,
`.h5` -> neural-BRDF weights. It is `complete(*read(data, base))`: `read` checks and reads the
material's raw data (numpy only, no JAX: a scene parser validates with it) and `complete` adds the
importance sampler's tables (computed in JAX).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from brdfs import merl, nbrdf
from brdfs.base import Model, Params
from brdfs.errors import InputError
from brdfs.measured_data import material_names

MODELS: dict[str, Model] = {m.name: m for m in (nbrdf.MODEL, merl.MODEL)}
SUFFIXES = {".binary": merl, ".h5": nbrdf}


__all__ = ["MODELS", "SUFFIXES", "names", "read", "complete", "load", "stack"]


def names(collection: str | None = None) -> tuple[str, ...]:
    """Names of the neural measured materials ("merl/alum-bronze", ...): all 159, or one collection's."""
    return material_names(collection)


def read(data: str | os.PathLike, base: str | os.PathLike | None = None) -> tuple[Model, dict[str, np.ndarray]]:
    """(model, raw data) of a measured material without JAX: the network's six weight arrays
    (`brdfs.nbrdf.LAYOUT`) or {"table": (90, 90, 180, 3)} (`brdfs.merl.read`), float32 numpy.

    Raises InputError for an unknown name (with close matches), a missing or corrupt file or archive,
    or a file of an unknown kind (see the module docstring for `data`).
    """
    s = os.fspath(data)
    suffix = Path(s).suffix.lower()
    if suffix in SUFFIXES:
        path = Path(s) if base is None or Path(s).is_absolute() else Path(base) / s
        if not path.is_file():
            raise InputError(f"{path}: measured BRDF file not found")
        if SUFFIXES[suffix] is merl:
            return merl.MODEL, {"table": merl.read(path)}
        return nbrdf.MODEL, nbrdf.read_weights(path)
    if suffix == ".json":
        raise InputError(f"{s}: the Keras .json files are not read (their last layer is marshalled Python "
                         f"code); give the .h5 weights file beside it or the material's name")
    if s.count("/") == 1 and suffix == "":
        from brdfs import measured_data

        m = measured_data.find_material(s)
        return nbrdf.MODEL, nbrdf.read_weights(m.read_bytes(), f"{m.archive}:{m.member}")
    raise InputError(f"measured material {s!r}: expected 'COLLECTION/NAME' (e.g. 'merl/alum-bronze') or a "
                     f"file NAME.binary (MERL) or NAME.h5 (neural BRDF)")


def complete(model: Model, raw: dict) -> Params:
    """The parameter pytree of one material of `model` from its raw data (`read`): the data as JAX
    arrays plus the importance sampler's tables (brdfs._measured_sampling)."""
    if model is merl.MODEL:
        return merl.from_table(raw["table"])
    if model is nbrdf.MODEL:
        return nbrdf.from_weights(raw)
    raise InputError(f"{model.name}: not a measured model; measured: {', '.join(MODELS)}")


def load(data: str | os.PathLike, base: str | os.PathLike | None = None) -> tuple[Model, Params]:
    """(model, parameter pytree) of a measured material; see the module docstring for `data`.

    Raises InputError for an unknown name (with close matches), a missing or corrupt file or archive,
    or a file of an unknown kind.
    """
    model, raw = read(data, base)
    return model, complete(model, raw)


def stack(params: Sequence[Params]) -> Params:
    """Stack the parameter pytrees of several materials of one model along a new leading axis."""
    keys = set(params[0])
    if any(set(p) != keys for p in params):
        raise InputError("cannot stack measured materials of different kinds (neural and MERL)")
    return {k: jnp.stack([jnp.asarray(p[k]) for p in params]) for k in params[0]}
