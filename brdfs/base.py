"""Parameter declarations, lobe flags and the `Model` record shared by every BRDF module.

One `Param` per parameter is the single source of truth for its default, bounds, unit and natural
scale; the registry, scene loader, fitting transforms, sliders and CLI help all read it from here.

A parameter pytree is a plain `dict[str, Array]`: RGB parameters (`rgb=True`) have shape (..., 3),
scalar ones shape (...). Leading batch dimensions broadcast against the directions' leading
dimensions, so a per-pixel stack of parameters can be evaluated in one call.

A `Model` says what kind of scattering it has through `flags` (a `Lobe` set, after pbrt-v4's
`BxDFFlags` and Mitsuba 3's `BSDFFlags`) rather than through its parameter names: renderers ask
`Lobe.DELTA in model.flags` (or `model.delta`), read the surface colour for an albedo AOV from
`model.diffuse_albedo(p)` (Mitsuba 3's `eval_diffuse_reflectance`) and reach a delta model's
reflection and refraction through its typed `dielectric` record.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Literal, NamedTuple

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
        typical: (lo, hi) the span of ordinary materials, inside [lo, hi], for synthetic targets and
            demos (hidden parameters of a fitting demo, say) where an extreme draw would be
            unresolvable; None means [lo, hi]. Validation always uses [lo, hi]; see `typical_range`.
        start: where a fit's first start puts the parameter when no initial value is given, strictly
            inside (lo, hi); None means `default`. Needed where the default sits on a bound: the
            fit's bounded transform (`fitting.transforms`) is flat there, so a start on the bound
            cannot move and the other parameters compensate for it in a local minimum.
    """

    name: str
    default: float
    lo: float
    hi: float
    scale: Literal["linear", "log"] = "linear"
    rgb: bool = False
    unit: str = ""
    doc: str = ""
    typical: tuple[float, float] | None = None
    start: float | None = None

    def __post_init__(self):
        t_lo, t_hi = self.typical_range
        if not (self.lo <= t_lo < t_hi <= self.hi and self.lo <= self.default <= self.hi):
            raise ValueError(f"Param {self.name!r}: need lo <= default <= hi and lo <= typical lo < typical hi <= hi")
        if self.start is not None and not self.lo < self.start < self.hi:
            raise ValueError(f"Param {self.name!r}: need lo < start < hi")

    @property
    def fit_start(self) -> float:
        """`start` or, without one, `default`: the value of a fit's first start."""
        return self.default if self.start is None else self.start

    @property
    def typical_range(self) -> tuple[float, float]:
        """`typical` or, without one, (lo, hi)."""
        return self.typical if self.typical is not None else (self.lo, self.hi)

    def check(self, value, model: str = "") -> np.ndarray:
        """Validate a user value and return it as a float32 numpy array of the right shape."""
        where = f"{model}.{self.name}" if model else self.name
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
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
        with np.errstate(over="ignore"):
            out = arr.astype(np.float32)
        if not np.all(np.isfinite(out)):  # finite as float64, beyond float32's 3.4e38
            raise InputError(f"{where}: value {value!r} is not representable in float32 (|x| <= 3.4e38)")
        return out


class Lobe(enum.Flag):
    """The kinds of scattering a model has (pbrt-v4's `BxDFFlags`, Mitsuba 3's `BSDFFlags`).

    REFLECTION    scatters into the hemisphere wo is in
    TRANSMISSION  scatters through the surface into the other hemisphere
    DIFFUSE       has a broad lobe with a diffuse colour: `Model.diffuse_albedo` is that colour
    GLOSSY        has a directional lobe with a finite density (`eval` and `pdf` are meaningful)
    DELTA         scatters into discrete directions only (perfect mirror / refraction): no `eval`,
                  no solid-angle density; the model carries a `dielectric` record instead

    A model is either DELTA or (DIFFUSE and/or GLOSSY); REFLECTION and/or TRANSMISSION says where
    the light goes. `Model` checks these rules when it is built.
    """

    REFLECTION = enum.auto()
    TRANSMISSION = enum.auto()
    DIFFUSE = enum.auto()
    GLOSSY = enum.auto()
    DELTA = enum.auto()


class Component(NamedTuple):
    """One lobe of a model's one-sample mixture: `sample` picks component k with probability
    `prob(p, wo)` (...,) (the analytic models' probabilities ignore wo; a measured model's depend on
    it) and then draws wi = `sample(p, wo, u)` (..., 3) from u in [0,1)^2 (wi may be below the
    horizon: a failed sample). The probabilities of a model's components sum to 1 and `Model.pdf` is
    the matching mixture density. `brdfs.albedo` integrates each component on its own grid with the
    lobe choice integrated out exactly."""

    prob: Callable
    sample: Callable


@dataclasses.dataclass(frozen=True)
class Dielectric:
    """What a ray tracer needs from a smooth dielectric interface (a delta BSDF), as pure functions
    in the local frame (+z the outward normal; leading batch dims broadcast):

        fresnel(p, cos_i, entering, exact=False) -> R (...,)   reflectance in [0, 1]; cos_i >= 0 on the
                                                               arriving side, entering (...,) bool
        reflect(wo) -> wr (..., 3)                             mirror direction (-wo_x, -wo_y, wo_z)
        refract(p, wo) -> (wt (..., 3), valid (...,) bool)     Snell refraction of wo for the side it is on;
                                                               valid is False under total internal reflection
    """

    fresnel: Callable
    reflect: Callable
    refract: Callable

    def split(self, p: Params, wo):
        """(R (...,), wr (..., 3), wt (..., 3), transmits (...,) bool) at local view direction wo: the
        Fresnel reflectance for the side wo is on, the mirror and refracted directions, and whether a
        transmitted ray exists (no total internal reflection and R < 1)."""
        entering = wo[..., 2] > 0
        r = self.fresnel(p, jnp.abs(wo[..., 2]), entering)
        wt, ok = self.refract(p, wo)
        return r, self.reflect(wo), wt, ok & (r < 1.0)


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
        diffuse_albedo(p) -> (..., 3)  the surface's diffuse colour (see the method)

    Fields beyond the functions:
        flags: the model's `Lobe` set. `delta` (a property) is `Lobe.DELTA in flags`.
        energy_conserving, reciprocal: measured properties (each module's docstring says under which
            parameter conditions).
        diffuse: p -> (..., 3), the diffuse colour `diffuse_albedo` returns; required with Lobe.DIFFUSE.
        mixture: the `Component`s `sample` chooses among (empty for delta models and for models
            without a sampler); `brdfs.albedo` needs them.
        dielectric: the `Dielectric` record of a delta model (glass); None otherwise.
        data_shapes: name -> core shape of the parameter pytree's entries that are not `Param`s
            (a measured model's data, whose `spec` is empty); leading dims of those are batch dims.

    Delta models (Lobe.DELTA) have `eval = None`; their `sample` returns the discrete branch
    probability as `pdf` (see brdfs/glass.py).
    """

    name: str
    spec: tuple[Param, ...]
    eval: Callable | None
    sample: Callable | None
    pdf: Callable | None
    flags: Lobe = Lobe.REFLECTION | Lobe.GLOSSY
    energy_conserving: bool = True
    reciprocal: bool = True
    diffuse: Callable | None = dataclasses.field(default=None, compare=False)
    mixture: tuple[Component, ...] = dataclasses.field(default=(), compare=False)
    dielectric: Dielectric | None = dataclasses.field(default=None, compare=False)
    data_shapes: Mapping[str, tuple[int, ...]] = dataclasses.field(default_factory=dict, compare=False)
    doc: str = ""

    def __post_init__(self):
        f = self.flags
        where = f"brdfs model {self.name!r}"
        if not f & (Lobe.REFLECTION | Lobe.TRANSMISSION):
            raise ValueError(f"{where}: flags {f} need REFLECTION and/or TRANSMISSION")
        if Lobe.DELTA in f:
            if f & (Lobe.DIFFUSE | Lobe.GLOSSY):
                raise ValueError(f"{where}: a DELTA model has no DIFFUSE or GLOSSY lobe (flags {f})")
            if self.eval is not None:
                raise ValueError(f"{where}: a DELTA model has no eval")
        else:
            if not f & (Lobe.DIFFUSE | Lobe.GLOSSY):
                raise ValueError(f"{where}: flags {f} need DIFFUSE, GLOSSY or DELTA")
            if self.eval is None:
                raise ValueError(f"{where}: a non-DELTA model needs eval")
        if Lobe.DIFFUSE in f and self.diffuse is None:
            raise ValueError(f"{where}: a DIFFUSE model needs a `diffuse` colour function")

    def __hash__(self) -> int:  # models are used as static jit arguments
        return hash(self.name)

    @property
    def delta(self) -> bool:
        """True for delta models (glass): `Lobe.DELTA in flags`."""
        return Lobe.DELTA in self.flags

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.spec)

    def param(self, name: str) -> Param:
        for p in self.spec:
            if p.name == name:
                return p
        raise InputError(f"{self.name}: unknown parameter {name!r}; allowed: {', '.join(self.param_names)}")

    def batch_shape(self, p: Params) -> tuple[int, ...]:
        """The leading (per-pixel) shape of a parameter pytree: its parameters' shapes without the RGB
        axis (and its data entries' without their core axes), broadcast together."""
        shapes = [jnp.shape(p[s.name])[:-1] if s.rgb else jnp.shape(p[s.name]) for s in self.spec]
        for k, core in self.data_shapes.items():
            shape = jnp.shape(p[k])
            shapes.append(shape[: len(shape) - len(core)])
        return jnp.broadcast_shapes(*shapes) if shapes else ()

    def diffuse_albedo(self, p: Params):
        """The surface's diffuse colour (..., 3), as a renderer writes it to an "albedo" AOV (the
        input denoisers expect) and a viewer shows it: the model's diffuse-colour parameter for
        Lobe.DIFFUSE models (rho_d of the Lambert + lobe models, base_color for Disney), 1 (white) for
        delta models, 0 for models without a diffuse lobe. It is the colour parameter, not the
        diffuse lobe's directional albedo (use `brdfs.albedo` for that; for Ashikhmin-Shirley, for
        instance, the diffuse term reflects (31/32) rho_d (1 - rho_s) at normal incidence)."""
        shape = self.batch_shape(p) + (3,)
        if self.delta:
            return jnp.ones(shape, jnp.result_type(*(p[s.name] for s in self.spec), jnp.float32))
        if self.diffuse is None:
            return jnp.zeros(shape, jnp.float32)
        return jnp.broadcast_to(self.diffuse(p), shape)

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
