"""brdfs: analytic reflectance models as pure, differentiable JAX functions.

    import brdfs
    brdfs.names()        # ('lambert', 'phong', 'blinn_phong', 'cook_torrance', 'ward', 'ashikhmin_shirley', 'glass',
                         #  'disney', 'ward_1992', 'ward_duer')
    model = brdfs.get("cook_torrance")
    p = model.params(rho_d=0.2, rho_s=0.8, m=0.3, eta=1.5)
    f = model.eval(p, wi, wo)           # (..., 3) linear RGB [1/sr]
    brdfs.albedo(model, p, wo)          # (..., 3) directional albedo
    model, p = brdfs.measured.load("merl/gold-metallic-paint")   # a measured material (data as params)

Each model module (brdfs/<name>.py) defines `MODEL`, a `brdfs.base.Model`; its docstring gives the
formula, the paper, and the measured energy/reciprocity properties. `model.flags` (a `brdfs.Lobe`
set) says what kind of scattering it has, `model.diffuse_albedo(p)` gives its diffuse colour (for an
albedo AOV) and a delta model (glass) carries its reflection/refraction in `model.dielectric`.

`names()` lists the analytic models: the ones with parameters to set, sweep and fit. The measured
models (`brdfs.measured.MODELS`: "nbrdf", "merl") are a second, separate list, because their
parameter pytrees are data (network weights, a MERL table) loaded from a file or a material name,
not values a user types: `get` resolves a name from either list, so a renderer holding a model name
finds either kind, and `is_measured` tells them apart.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from brdfs import lazy as _lazy

if TYPE_CHECKING:
    from brdfs.base import Model

# Registry order: the seven models of Größler & Zettwitz ("An interactive ray tracing system based
# on Nvidia OptiX", 2015) and Disney, then the two Ward normalisations that Ngan, Durand & Matusik
# ("Experimental analysis of BRDF models", EGSR 2005) fitted.
_MODULES = ("lambert", "phong", "blinn_phong", "cook_torrance", "ward", "ashikhmin_shirley", "glass", "disney",
            "ward_1992", "ward_duer")

# `import brdfs` loads neither JAX nor a model: each public name is imported on first use (PEP 562),
# so the `jaxrt` command (whose errors are `brdfs.errors.InputError`) starts without JAX.
# public name -> the module that defines it
_LAZY = {
    "albedo": "brdfs.analysis", "lobe_slice": "brdfs.analysis", "plot_lobe": "brdfs.analysis",
    "reciprocity_error": "brdfs.analysis",
    "Component": "brdfs.base", "Dielectric": "brdfs.base", "Lobe": "brdfs.base", "Model": "brdfs.base",
    "Param": "brdfs.base", "Params": "brdfs.base",
}


def _registry() -> dict[str, Model]:
    """name -> Model of the analytic models, in registry order (imports them on the first call)."""
    models = globals().get("MODELS")
    if models is None:
        mods = [importlib.import_module(f"{__name__}.{m}") for m in _MODULES]
        models = globals().setdefault("MODELS", {m.MODEL.name: m.MODEL for m in mods})
    return models


def __getattr__(name: str):
    if name == "MODELS":
        return _registry()
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    # any other name: a submodule (the model modules, `measured`, `analysis`, ...)
    return _lazy.submodule(__name__, __file__, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__) | set(_MODULES))


def names() -> tuple[str, ...]:
    """The registered model names, in registry order (see `_MODULES`)."""
    return tuple(_registry())


def get(name: str) -> Model:
    """The model called `name`: an analytic model (`MODELS`) or a measured one (`measured.MODELS`);
    InputError (a ValueError) listing the analytic names otherwise."""
    models = _registry()
    try:
        return models[name]
    except (KeyError, TypeError):
        pass
    from brdfs import measured

    try:
        return measured.MODELS[name]
    except (KeyError, TypeError):
        from brdfs.errors import InputError

        raise InputError(f"unknown BRDF model {name!r}; allowed: {', '.join(models)}") from None


def is_measured(model: Model | str) -> bool:
    """Whether `model` (or the model called so) is a measured model, whose parameter pytree is data
    (`Model.data_shapes`) rather than declared `Param`s."""
    m = get(model) if isinstance(model, str) else model
    return bool(m.data_shapes)


__all__ = [
    "Model", "Param", "Params", "Lobe", "Component", "Dielectric", "MODELS", "names", "get", "is_measured",
    "measured",
    "albedo", "lobe_slice", "reciprocity_error", "plot_lobe",
]
