"""Parameter declarations and the `Model` record shared by every BRDF module.

One `Param` per parameter is the single source of truth for its default, bounds, unit and natural
scale; the registry, scene loader, fitting transforms, sliders and CLI help all read it from here.

A parameter pytree is a plain `dict[str, Array]`: RGB parameters (`rgb=True`) have shape (..., 3),
scalar ones shape (...). Leading batch dimensions broadcast against the directions' leading
dimensions, so a per-pixel stack of parameters can be evaluated in one call.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Literal

import jax.numpy as jnp
import numpy as np

from brdfs.errors import InputError

Params = dict  # dict[str, jax.Array]; see module docstring


@dataclasses.dataclass(frozen=True)
class Param:
    """Declaration of one BRDF parameter.

    Attributes:
        name: the parameter's name as used in scene files, the CLI and `Model.params`.
        default: default value (a scalar; RGB parameters broadcast it to 3 channels).
        lo, hi: inclusive bounds.
        scale: "linear" or "log": the natural scale for sliders, sweeps and the fit's transform.
        rgb: whether the parameter is an RGB triple (a scalar input is broadcast).
        unit: physical unit or "" for dimensionless.
        doc: one-line description.
    """

    name: str
    default: float
    lo: float
    hi: float
    scale: Literal["linear", "log"] = "linear"
    rgb: bool = False
    unit: str = ""
    doc: str = ""

    def check(self, value, model: str = "") -> np.ndarray:
        """Validate a user value and return it as a float32 numpy array of the right shape."""
        where = f"{model}.{self.name}" if model else self.name
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}: expected a number{' or RGB triple' if self.rgb else ''}, got {value!r}")
        if self.rgb:
            if arr.shape == ():
                arr = np.broadcast_to(arr, (3,))
            elif arr.shape[-1:] != (3,):
                raise InputError(f"{where}: expected a scalar or an RGB triple, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{where}: value {value!r} is not finite; allowed range is [{self.lo:g}, {self.hi:g}]")
        if np.any(arr < self.lo) or np.any(arr > self.hi):
            raise InputError(f"{where}: value {value!r} is outside the allowed range [{self.lo:g}, {self.hi:g}]")
        return arr.astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Model:
    """A reflectance model: a named set of pure functions over a parameter pytree.

    Every function works in the local shading frame (normal +z, tangent +x) on unit vectors
    pointing away from the surface (wi towards the light, wo towards the viewer):

        eval(p, wi, wo) -> f        (..., 3) BRDF value [1/sr], 0 when either direction is below the horizon
        sample(p, wo, u) -> (wi, weight, pdf)
                                    u: (..., 2) uniform in [0,1)^2; weight = f * cos(theta_i) / pdf (..., 3);
                                    pdf [1/sr] (...,); a failed sample has weight 0 and pdf 0
        pdf(p, wo, wi) -> (...,)    the density `sample` draws wi with [1/sr]

    Delta models (`delta=True`, glass) have no `eval`; they expose what a ray tracer needs
    through `extras` (e.g. reflectance, reflect, refract).
    """

    name: str
    spec: tuple[Param, ...]
    eval: Callable | None
    sample: Callable | None
    pdf: Callable | None
    delta: bool = False
    energy_conserving: bool = True
    reciprocal: bool = True
    extras: Mapping[str, Callable] = dataclasses.field(default_factory=dict, compare=False, hash=False)
    doc: str = ""

    def __hash__(self) -> int:  # models are used as static jit arguments
        return hash(self.name)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.spec)

    def param(self, name: str) -> Param:
        for p in self.spec:
            if p.name == name:
                return p
        raise InputError(f"{self.name}: unknown parameter {name!r}; allowed: {', '.join(self.param_names)}")

    def params(self, **values) -> Params:
        """Build a validated parameter pytree; unset fields take their defaults.

        Raises InputError (a ValueError) naming the parameter and its allowed range for an unknown name or an
        out-of-bounds value.
        """
        unknown = set(values) - set(self.param_names)
        if unknown:
            raise InputError(
                f"{self.name}: unknown parameter(s) {', '.join(sorted(unknown))}; allowed: {', '.join(self.param_names)}"
            )
        out = {}
        for p in self.spec:
            out[p.name] = jnp.asarray(p.check(values.get(p.name, p.default), self.name))
        return out

    def defaults(self) -> Params:
        return self.params()

    def stack(self, params: Sequence[Params]) -> Params:
        """Stack several parameter pytrees along a new leading axis (e.g. one row per material)."""
        return {k: jnp.stack([jnp.asarray(p[k]) for p in params]) for k in self.param_names}


def log_or_linear_grid(p: Param, n: int) -> np.ndarray:
    """n values spanning [lo, hi] on the parameter's natural scale (for sweeps and sliders)."""
    if p.scale == "log":
        return np.exp(np.linspace(math.log(p.lo), math.log(p.hi), n))
    return np.linspace(p.lo, p.hi, n)
