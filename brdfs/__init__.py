"""brdfs: analytic reflectance models as pure, differentiable JAX functions.

    import brdfs
    brdfs.names()        # ('lambert', 'phong', 'blinn_phong', 'cook_torrance', 'ward', 'ashikhmin_shirley', 'glass',
                         #  'disney', 'ward_1992', 'ward_duer')
    model = brdfs.get("cook_torrance")
    p = model.params(rho_d=0.2, rho_s=0.8, m=0.3, eta=1.5)
    f = model.eval(p, wi, wo)           # (..., 3) linear RGB [1/sr]
    brdfs.albedo(model, p, wo)          # (..., 3) directional albedo

Each model module (brdfs/<name>.py) defines `MODEL`, a `brdfs.base.Model`; its docstring gives the
formula, the paper, and the measured energy/reciprocity properties. `model.flags` (a `brdfs.Lobe`
set) says what kind of scattering it has, `model.diffuse_albedo(p)` gives its diffuse colour (for an
albedo AOV) and a delta model (glass) carries its reflection/refraction in `model.dielectric`.
"""

from __future__ import annotations

from brdfs import (
    ashikhmin_shirley, blinn_phong, cook_torrance, disney, glass, lambert, phong, ward, ward_1992, ward_duer,
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
    """The model called `name`; ValueError listing the known names otherwise."""
    try:
        return MODELS[name]
    except (KeyError, TypeError):
        from brdfs.errors import InputError

        raise InputError(f"unknown BRDF model {name!r}; allowed: {', '.join(MODELS)}") from None


__all__ = [
    "Model", "Param", "Params", "Lobe", "Component", "Dielectric", "MODELS", "names", "get",
    "albedo", "lobe_slice", "reciprocity_error", "plot_lobe",
]
