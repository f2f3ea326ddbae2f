"""Fitting analytic BRDFs to measured ones directly in BRDF space (Ngan, Durand & Matusik 2005).

A. Ngan, F. Durand and W. Matusik, "Experimental Analysis of BRDF Models", Eurographics Symposium on
Rendering 2005, fitted analytic models to the 100 MERL materials (Matusik, Pfister, Brand & McMillan,
"A Data-Driven Reflectance Model", SIGGRAPH 2003) by minimising a cosine-weighted L2 distance between
the model and the measurement over the measured (wi, wo) pairs, each sample weighted by its solid
angle, ignoring directions more than 80° from the normal (grazing measurements are unreliable). This
module does the same against any measured model (`brdfs.measured`: the neural stand-ins of Sztrajman
et al. 2021 or MERL tables), through the shared least-squares core `fitting.solve.solve_batch`
(Levenberg–Marquardt, deterministic multi-start, standard errors, parameters that end at a bound).

Sampling of directions (`sampling`). Ngan et al. summed over the MERL table's own samples. MERL
tabulates an isotropic BRDF in Rusinkiewicz's half/difference angles (`brdfs.halfdiff`) with φh = 0:
90 θh bins on a square-root scale (bin index = 90 √(θh / (π/2))), 90 θd bins on [0, π/2) and 180 φd
bins on [0, π) (the other half of φd holds the reciprocal pairs (wo, wi)). `sampling` takes the cell
centres of the same grid at a chosen resolution:

    θh_j = (π/2) ((j + ½) / n_h)²,  θd_k = (π/2) (k + ½) / n_d,  φd_l = π (l + ½) / n_p,   φh = 0

and weights each sample by the solid-angle measure of its cell, from dωi dωo = 4 cos θd dωh dωd
(Rusinkiewicz 1998; the 2π of φh and the factor 2 of the reciprocal half are constant and included):

    w = 4 cos θd sin θh sin θd Δθh_j Δθd Δφd · 2π · 2,     Δθh_j = (π/2) · 2 (j + ½) / n_h²

so Σ w approximates ∫∫ dωi dωo over the compared pairs ((2π)² over both hemispheres; the tests
check this and Σ w cos θi cos θo ≈ π² against the closed forms). Pairs with θi or θo above the
cutoff (80°, `CUTOFF_DEG`) or below the horizon are dropped. The square-root θh scale puts samples
where specular lobes are: the first θh nodes of the fit's default 24 lie at 0.04°, 0.35°, 1.0°, 1.9°.

Error metrics (`METRICS`), the study's units. With c = cos θi (wi towards the light), channels
ch = R, G, B, the fit f̂ and the measurement f:

    ngan      E = sqrt( Σ w Σ_ch (f̂ c − f c)² / (3 Σ w) )                          [1/sr]
    cuberoot  E = sqrt( Σ w Σ_ch (∛(f̂ c + ε) − ∛(f c + ε))² / (3 Σ w) )            [sr^-1/3]
    log       E = sqrt( Σ w Σ_ch (ln(1 + f̂ c) − ln(1 + f c))² / (3 Σ w) )          [1: ln of (1 + f c/(1/sr))]

"ngan" is Ngan et al.'s cosine-weighted L2, reported as a root-mean-square over the compared pairs
(solid-angle weighted) and the three channels. "cuberoot" applies Ngan's weighting to the cube root of
f cos θi, which Forés, Ferwerda & Gu ("Toward a Perceptually Based Metric for BRDF Modeling", Color and
Imaging Conference 2012) found best matched perceived differences; ε = 1e-6 /sr (`CBRT_EPS`) keeps the
derivative finite where f c = 0 and changes E by less than 0.1 % wherever f c ≥ 1e-3 /sr.
"log" is the ln(1 + f cos θi) metric of Löw, Kronander, Ynnerman & Unger ("BRDF Models for Accurate and
Efficient Rendering of Glossy Surfaces", ACM TOG 31(1), 2012). The fit minimises E² of the chosen
metric (every residual (g(f̂ c) − g(f c)) √(w / mean w) over the kept samples); every fit also reports
E under all three metrics at its parameters (`BrdfFit.errors`), so fits under different metrics
compare on one scale.

Isotropy. Every measured material here is isotropic, so the anisotropic models fit one roughness:
`ISOTROPIC_TIES` sets α_y = α_x (Ward) and n_v = n_u (Ashikhmin–Shirley) inside the fitted function,
as Ngan et al. fitted the isotropic forms; the tied parameter is reported equal to its source with
the same standard error.

Batching. One fixed sampling serves every material, so each material is only a (N, 3) target array:
`fit_samples` fits one model to B of them with a single compiled solve vmapped over materials and
starts (`fitting.solve.solve_batch`); `fit_measured` loads named materials and calls it.

Standard errors are the least-squares formal errors s² (JᵀJ)⁻¹ with s² = RSS / (n − p); in BRDF space
the residual is the model's misfit, not measurement noise, so they say how well the data pin a
parameter for this model, not how repeatable a measurement is.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float

import brdfs
from brdfs.base import Model, Params
from brdfs.errors import InputError
from brdfs.halfdiff import directions
from fitting.record import FitRecord
from fitting.solve import solve_batch

__all__ = [
    "CBRT_EPS", "CUTOFF_DEG", "EVAL_RESOLUTION", "FIT_RESOLUTION", "ISOTROPIC_TIES", "METRICS", "METRIC_DOC",
    "SOLVER", "SPHERE_LIGHT", "UNITS", "BrdfFit", "Sampling", "as_params", "check_metric", "device_data",
    "errors", "evaluate", "fit_measured", "fit_model", "fit_samples", "measured_samples", "sampling", "shader",
    "sphere_directions", "sphere_image", "ties", "transform",
]

METRICS = ("ngan", "cuberoot", "log")
UNITS = {"ngan": "1/sr", "cuberoot": "sr^-1/3", "log": "1"}
METRIC_DOC = {
    "ngan": "cosine-weighted L2 of f cos θi (Ngan et al. 2005)",
    "cuberoot": "cosine-weighted L2 of the cube root of f cos θi (Forés et al. 2012)",
    "log": "cosine-weighted L2 of ln(1 + f cos θi) (Löw et al. 2012)",
}
CUTOFF_DEG = 80.0
CBRT_EPS = 1e-6
# anisotropic parameter -> the parameter it equals for an isotropic material
ISOTROPIC_TIES = {"alpha_y": "alpha_x", "n_v": "n_u"}
# (n_theta_h, n_theta_d, n_phi_d) of the fit's grid and of the finer grid errors are reported on
FIT_RESOLUTION = (24, 16, 16)
EVAL_RESOLUTION = (64, 48, 48)
# Levenberg–Marquardt on the normal equations (fitting.solve.SOLVERS): ~15x faster a step than the QR
# form for these tall Jacobians (thousands of residuals, at most 8 parameters)
SOLVER = "lm_normal"
# Matrix products (the neural BRDFs' layers, the normal equations) in full float32: on NVIDIA GPUs JAX
# would otherwise use TF32 (10-bit mantissa), and the GPU's fits would differ from the CPU's
MATMUL_PRECISION = "float32"


@dataclasses.dataclass(frozen=True, eq=False)
class Sampling:
    """A fixed set of direction pairs with solid-angle weights (see the module docstring).

    wi, wo: (N, 3) float64 unit vectors in the local frame (wi towards the light); weight (N,) [sr²];
    resolution: (n_theta_h, n_theta_d, n_phi_d); cutoff_deg: the largest θi, θo kept.
    """

    wi: np.ndarray
    wo: np.ndarray
    weight: np.ndarray
    resolution: tuple[int, int, int]
    cutoff_deg: float

    @property
    def size(self) -> int:
        return int(self.weight.size)

    def describe(self) -> dict:
        n_h, n_d, n_p = self.resolution
        return {"grid": "MERL half/difference cells (theta_h square-root scale, theta_d, phi_d in [0, pi))",
                "n_theta_h": n_h, "n_theta_d": n_d, "n_phi_d": n_p, "cutoff_deg": self.cutoff_deg,
                "samples": self.size}


@functools.lru_cache(maxsize=8)
def sampling(n_theta_h: int = FIT_RESOLUTION[0], n_theta_d: int = FIT_RESOLUTION[1],
             n_phi_d: int = FIT_RESOLUTION[2], cutoff_deg: float = CUTOFF_DEG) -> Sampling:
    """The MERL-style grid of direction pairs and their solid-angle weights (module docstring)."""
    if min(n_theta_h, n_theta_d, n_phi_d) < 1:
        raise InputError(f"sampling resolution must be positive, got {(n_theta_h, n_theta_d, n_phi_d)}")
    if not 0.0 < cutoff_deg <= 90.0:
        raise InputError(f"cutoff {cutoff_deg}° must be in (0, 90]")
    j = (np.arange(n_theta_h) + 0.5) / n_theta_h
    th, dth = 0.5 * math.pi * j**2, 0.5 * math.pi * 2.0 * j / n_theta_h
    td = (np.arange(n_theta_d) + 0.5) / n_theta_d * 0.5 * math.pi
    pd = (np.arange(n_phi_d) + 0.5) / n_phi_d * math.pi
    dtd, dpd = 0.5 * math.pi / n_theta_d, math.pi / n_phi_d
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    DTH = np.broadcast_to(dth[:, None, None], TH.shape)
    wi, wo = directions(TH, TD, PD, xp=np)
    w = 4.0 * np.cos(TD) * np.sin(TH) * np.sin(TD) * DTH * dtd * dpd * (2.0 * math.pi) * 2.0
    c = math.cos(math.radians(cutoff_deg)) if cutoff_deg < 90.0 else 0.0
    keep = (wi[..., 2] > c) & (wo[..., 2] > c)
    # normalise exactly (the directions are unit up to rounding)
    wi = wi[keep] / np.linalg.norm(wi[keep], axis=-1, keepdims=True)
    wo = wo[keep] / np.linalg.norm(wo[keep], axis=-1, keepdims=True)
    return Sampling(wi, wo, w[keep], (n_theta_h, n_theta_d, n_phi_d), float(cutoff_deg))


def check_metric(metric: str) -> str:
    if metric not in METRICS:
        raise InputError(f"unknown metric {metric!r}; allowed: {', '.join(METRICS)}")
    return metric


def transform(metric: str, x, xp=jnp):
    """The metric's map g of f cos θi [1/sr] (numpy with xp=np, for float64 references)."""
    x = xp.maximum(x, 0.0)
    if metric == "ngan":
        return x
    if metric == "cuberoot":
        return xp.cbrt(x + CBRT_EPS)
    if metric == "log":
        return xp.log1p(x)
    raise InputError(f"unknown metric {metric!r}; allowed: {', '.join(METRICS)}")


def errors(f_fit: Float[np.ndarray, "*B N 3"], f_meas: Float[np.ndarray, "*B N 3"],
           samp: Sampling) -> dict[str, Float[np.ndarray, "*B"]]:
    """E of every metric (float64) between BRDF values (..., N, 3) [1/sr] on the sampling `samp`."""
    c = samp.wi[:, 2][:, None]
    a = np.asarray(f_fit, np.float64) * c
    b = np.asarray(f_meas, np.float64) * c
    w = samp.weight[:, None]
    return {m: np.sqrt(np.sum(w * (transform(m, a, np) - transform(m, b, np)) ** 2, axis=(-2, -1))
                       / (3.0 * samp.weight.sum())) for m in METRICS}


@dataclasses.dataclass
class BrdfFit(FitRecord):
    """One analytic model fitted to one measured material in BRDF space (`error`/`errors` on the
    evaluation sampling, if one was given); `to_json()` for files."""

    samples: int  # direction pairs of the fit's sampling
    eval_samples: int  # ... of the sampling `error` was evaluated on


def fit_model(name) -> Model:
    """A model that can be fitted in BRDF space: registered, with an eval and at least one parameter."""
    model = brdfs.get(name) if isinstance(name, str) else name
    if model.delta or model.eval is None or not model.spec:
        raise InputError(f"model {model.name}: a delta or parameterless model cannot be fitted in BRDF space")
    return model


def ties(model: Model, isotropic: bool = True) -> tuple[tuple[str, str], ...]:
    """The (tied, source) pairs applied to `model` (ISOTROPIC_TIES present in its parameters)."""
    if not isotropic:
        return ()
    names = set(model.param_names)
    return tuple((t, s) for t, s in ISOTROPIC_TIES.items() if t in names and s in names)


@functools.lru_cache(maxsize=64)
def shader(model: Model, metric: str, tie: tuple[tuple[str, str], ...] = ()):
    """shade(params, data) -> g(f(params) cos θi) (N, 3) on data = {"wi", "wo", "cos"}; one Python
    object per (model, metric, ties) so the compiled solver is reused."""
    check_metric(metric)

    def shade(p, d):
        p = {**p, **{t: p[s] for t, s in tie}}
        return transform(metric, model.eval(p, d["wi"], d["wo"]) * d["cos"])

    shade.program_key = f"fitting.brdf_space.shader({model.name!r}, {metric!r}, {tie!r})"  # stable across processes
    return shade


def device_data(samp: Sampling) -> dict:
    """The sampling as float32 device arrays: the parameter-independent 'gbuffer' of a BRDF-space fit."""
    wi = np.asarray(samp.wi, np.float32)
    return jax.device_put({"wi": wi, "wo": np.asarray(samp.wo, np.float32), "cos": wi[:, 2:3].copy()})


@functools.lru_cache(maxsize=16)
def _evaluator(model: Model):
    @jax.jit
    def ev(p, wi, wo):
        return jax.vmap(lambda q: model.eval(q, wi, wo))(p)

    return ev


def evaluate(model: Model, params: Params | Sequence[Params], samp: Sampling,
             batch: int = 16) -> Float[np.ndarray, "B N 3"]:
    """BRDF values (B, N, 3) [1/sr] of B parameter sets (a list, or a pytree with a leading axis) on the
    sampling, in chunks of `batch` (one compilation per model and chunk size)."""
    if not isinstance(params, Mapping):
        params = {k: jnp.stack([jnp.asarray(p[k]) for p in params]) for k in params[0]}
    d = device_data(samp)
    n = next(iter(params.values())).shape[0]
    ev = _evaluator(model)
    out = []
    with jax.default_matmul_precision(MATMUL_PRECISION):
        for lo in range(0, n, batch):
            chunk = {k: v[lo: lo + batch] for k, v in params.items()}
            m = next(iter(chunk.values())).shape[0]
            if m < batch:  # pad to the compiled shape
                chunk = {k: jnp.concatenate([v, jnp.repeat(v[-1:], batch - m, axis=0)]) for k, v in chunk.items()}
            out.append(np.asarray(ev(chunk, d["wi"], d["wo"]))[:m])
    return np.concatenate(out)


def measured_samples(names: Sequence[str], samp: Sampling, batch: int = 16) -> Float[np.ndarray, "B N 3"]:
    """(B, N, 3) values [1/sr] of measured materials (names or files, `brdfs.measured.load`) on `samp`."""
    from brdfs import measured

    loaded = [measured.load(n) for n in names]
    out = np.empty((len(names), samp.size, 3), np.float32)
    kinds = {}
    for i, (m, p) in enumerate(loaded):
        kinds.setdefault(m, []).append(i)
    for m, idx in kinds.items():
        out[idx] = evaluate(m, measured.stack([loaded[i][1] for i in idx]), samp, batch)
    if not np.all(np.isfinite(out)):
        bad = [names[i] for i in range(len(names)) if not np.all(np.isfinite(out[i]))]
        raise InputError(f"measured material(s) {', '.join(bad)}: non-finite BRDF values on the sampling")
    return out


def fit_samples(
    f_meas: Float[np.ndarray, "B N 3"],
    model: Model | str,
    *,
    names: Sequence[str] | None = None,
    metric: str = "ngan",
    samp: Sampling | None = None,
    isotropic: bool = True,
    fix: Mapping[str, object] | None = None,
    init: Mapping[str, object] | None = None,
    starts: int = 8,
    max_steps: int = 100,
    solver: str = SOLVER,
    rtol: float = 1e-5,
    atol: float = 1e-8,
    batch: int | None = None,
    f_eval: Float[np.ndarray, "B M 3"] | None = None,
    eval_samp: Sampling | None = None,
    progress: bool = False,
    devices=None,
) -> list[BrdfFit]:
    """Fit `model` to B measured BRDFs given as values f_meas (B, N, 3) [1/sr] on the sampling `samp`.

    One compiled Levenberg–Marquardt solve (fitting.solve.solve_batch) runs vmapped over the B
    materials and the `starts` deterministic starts; `batch` materials per call (default all).
    With `f_eval` (B, M, 3), the same materials on a (finer) sampling `eval_samp`, the reported errors
    are evaluated there; otherwise on `samp`. `devices` (None: the default device) splits the
    materials of each call over several devices (`fitting.solve.solve_batch`). Returns one BrdfFit
    per material (named by `names`, default "0", "1", ...).
    """
    model = fit_model(model)
    check_metric(metric)
    samp = samp or sampling()
    f_meas = np.asarray(f_meas, np.float32)
    if f_meas.ndim != 3 or f_meas.shape[1:] != (samp.size, 3):
        raise ValueError(f"f_meas must be (B, {samp.size}, 3) on the sampling, got {f_meas.shape}")
    names = list(names) if names is not None else [str(i) for i in range(len(f_meas))]
    tie = ties(model, isotropic)
    fix = dict(fix or {})
    for t, s in tie:
        if t in fix or t in (init or {}):
            raise InputError(f"{model.name}.{t} is tied to {s} for isotropic materials; fix or start {s} instead")
        fix[t] = model.param(t).default  # not fitted: the shader overwrites it with its source
    shade = shader(model, metric, tie)
    data = device_data(samp)
    c = np.asarray(data["cos"])
    targets = np.asarray(transform(metric, jnp.asarray(f_meas * c)))
    mask = (samp.weight / samp.weight.mean()).astype(np.float32)
    with jax.default_matmul_precision(MATMUL_PRECISION):
        sols = solve_batch(shade, data, targets, model, mask=mask, fix=fix, init=init, rgb=True, solver=solver,
                           starts=starts, max_steps=max_steps, rtol=rtol, atol=atol, batch=batch, progress=progress,
                           devices=devices)
    for sol in sols:
        for t, s in tie:
            sol.params[t] = sol.params[s]
            sol.stderr[t] = sol.stderr[s]
            sol.fixed.remove(t)
            if s in sol.at_bound:
                sol.at_bound[t] = sol.at_bound[s]
    fitted_params = [{k: jnp.asarray(v, jnp.float32) for k, v in s.params.items()} for s in sols]
    fit_errs = errors(evaluate(model, fitted_params, samp), f_meas, samp)[metric]
    if f_eval is not None:
        if eval_samp is None or np.shape(f_eval) != (len(f_meas), eval_samp.size, 3):
            raise ValueError("f_eval must be (B, M, 3) values on eval_samp")
        errs = errors(evaluate(model, fitted_params, eval_samp), f_eval, eval_samp)
    else:
        eval_samp, errs = samp, errors(evaluate(model, fitted_params, samp), f_meas, samp)
    out = []
    for i, (name, sol) in enumerate(zip(names, sols)):
        e = {m: float(errs[m][i]) for m in METRICS}
        out.append(BrdfFit.from_solution(
            sol, material=name, model=model.name, metric=metric, unit=UNITS[metric], error=e[metric], errors=e,
            fit_error=float(fit_errs[i]), tied=dict(tie), samples=samp.size, eval_samples=eval_samp.size))
    return out


def fit_measured(materials: Sequence[str] | str, model: Model | str, *, samp: Sampling | None = None,
                 eval_samp: Sampling | None = None, **kwargs) -> list[BrdfFit]:
    """Load measured materials by name or file (`brdfs.measured.load`) and fit `model` to each
    (`fit_samples`; keyword arguments as there); errors on `eval_samp` when given."""
    materials = [materials] if isinstance(materials, str) else list(materials)
    samp = samp or sampling()
    f_eval = measured_samples(materials, eval_samp) if eval_samp is not None else None
    return fit_samples(measured_samples(materials, samp), model, names=materials, samp=samp, f_eval=f_eval,
                       eval_samp=eval_samp, **kwargs)


def as_params(fit: BrdfFit) -> Params:
    """The fitted parameters as a float32 parameter pytree for `model.eval`."""
    return {k: jnp.asarray(v, jnp.float32) for k, v in fit.params.items()}


# --- pictures of a material: closed-form sphere shading -------------------------------------------------

#: the sphere pictures' light: a distant light from this direction (normalised; 27° from the view
#: direction +z, up and to the left), so that most of the visible disc is lit
SPHERE_LIGHT = (-0.30, 0.35, 0.89)


def sphere_directions(size: int, light=SPHERE_LIGHT):
    """Per-pixel local (wi, wo) (P, 3), the pixels' flat indices (P,) and cos θi of a size×size image of
    a unit sphere seen orthographically along −z, lit by a distant light from direction `light`.

    Each pixel's normal is n = (x, y, √(1 − x² − y²)); the local frame is (t, b, n) with t ⟂ n chosen
    from the world x or y axis (the materials are isotropic, so any tangent gives the same image).
    """
    t = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(t, -t)  # image row 0 at the top (+y)
    r2 = x**2 + y**2
    inside = r2 < 1.0
    n = np.stack([x[inside], y[inside], np.sqrt(1.0 - r2[inside])], -1)
    ref = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    tg = ref - np.sum(ref * n, -1, keepdims=True) * n
    tg /= np.linalg.norm(tg, axis=-1, keepdims=True)
    bt = np.cross(n, tg)
    lt = np.asarray(light, np.float64) / np.linalg.norm(light)
    v = np.array([0.0, 0.0, 1.0])
    local = lambda w: np.stack([tg @ w, bt @ w, n @ w], -1)
    return local(lt), local(v), np.nonzero(inside.reshape(-1))[0], n @ lt


def sphere_image(model: Model, params: Params, size: int = 96,
                 light=SPHERE_LIGHT) -> Float[np.ndarray, "size size 3"]:
    """(size, size, 3) radiance of a unit sphere of this material under a unit-irradiance distant light,
    shaded in closed form per pixel: L = f(wi, wo) max(cos θi, 0) (no shadows, no interreflection);
    0 outside the sphere."""
    wi, wo, idx, cos_i = sphere_directions(size, light)
    f = np.asarray(model.eval(params, jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)))
    img = np.zeros((size * size, 3), np.float32)
    img[idx] = f * np.maximum(cos_i, 0.0)[:, None]
    return img.reshape(size, size, 3)
