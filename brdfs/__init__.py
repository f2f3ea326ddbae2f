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

from brdfs import (
    ashikhmin_shirley, blinn_phong, cook_torrance, disney, glass, lambert, measured, phong, ward, ward_1992, ward_duer,
)
from brdfs.analysis import albedo, lobe_slice, plot_lobe, reciprocity_error
from brdfs.base import Component, Dielectric, Lobe, Model, Param, Params

# Registry order: the seven models of Größler & Zettwitz ("An interactive ray tracing system based
# on Nvidia OptiX", 2015) and Disney, then the two Ward normalisations that Ngan, Durand & Matusik
# ("Experimental analysis of BRDF models", EGSR 2005) fitted.
_MODULES = (lambert, phong, blinn_phong, cook_torrance, ward, ashikhmin_shirley, glass, disney, ward_1992, ward_duer)
MODELS: dict[str, Model] = {m.MODEL.name: m.MODEL for m in _MODULES}


def names() -> tuple[str, ...]:
    """The registered model names, in registry order (see `_MODULES`)."""
    return tuple(MODELS)


def get(name: str) -> Model:
    """The model called `name`: an analytic model (`MODELS`) or a measured one (`measured.MODELS`);
    InputError (a ValueError) listing the analytic names otherwise."""
    try:
        return MODELS[name]
    except (KeyError, TypeError):
        pass
    try:
        return measured.MODELS[name]
    except (KeyError, TypeError):
        from brdfs.errors import InputError

        raise InputError(f"unknown BRDF model {name!r}; allowed: {', '.join(MODELS)}") from None


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
