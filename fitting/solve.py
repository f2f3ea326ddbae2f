"""Recover a BRDF's parameters from target images by nonlinear least squares (optimistix).

The renderer-independent core. A fit sees the renderer only through

    shade(params, gbuffer) -> images   (K, H, W, 3) linear RGB

where `gbuffer` is a pytree of everything that does not depend on the fitted parameters (hit
frames, light directions, visibility, ray trees: "trace once, shade many"). The solver works in an
unconstrained space z built from the model's declared bounds and scales (`fitting.transforms`), so
every iterate is a valid parameter set. Several deterministic starts guard against the local minima
of exponent and roughness lobes; the best is kept and its standard errors come from the Jacobian at
the optimum.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, PyTree

from brdfs.base import Model, Param, Params
from fitting import metrics
from fitting.transforms import from_unconstrained, normalise, to_unconstrained, denormalise

SOLVERS: dict[str, Callable[[float, float], object]] = {
    "lm": lambda rtol, atol: optx.LevenbergMarquardt(rtol=rtol, atol=atol),
    "gauss_newton": lambda rtol, atol: optx.GaussNewton(rtol=rtol, atol=atol),
    "dogleg": lambda rtol, atol: optx.Dogleg(rtol=rtol, atol=atol),
    "bfgs": lambda rtol, atol: optx.BFGS(rtol=rtol, atol=atol),
}

# A fit is "ill-conditioned" when the column-scaled Gauss-Newton matrix JᵀJ has a condition number
# above this, or two parameters' estimates correlate beyond CORRELATION_WARN (e.g. ρs against s: a
# brighter, wider lobe looks like a dimmer, sharper one at the pixels that see it).
CONDITION_WARN = 1e8
CORRELATION_WARN = 0.99
# A fit "cannot reproduce" its target when the residual RMS exceeds this fraction of the target's
# RMS over the compared pixels (a wrong scene, lighting, exposure or object, or a model too simple).
RELATIVE_RMSE_WARN = 0.5


@dataclasses.dataclass(frozen=True)
class FreeParam:
    """One fitted parameter: its declaration and how many values it has (1, or 3 for an RGB fit)."""

    param: Param
    size: int


@dataclasses.dataclass
class FitResult:
    """Outcome of a fit; `to_json()` gives a JSON-serialisable dict."""

    model: str
    params: dict[str, list[float] | float]  # all parameters (fitted and fixed), parameter units
    stderr: dict[str, list[float] | float]  # fitted parameters only
    fixed: list[str]
    rmse: float
    delta_e_mean: float
    delta_e_max: float
    iterations: int  # solver steps of the best start
    total_iterations: int  # over all starts
    starts: int
    starts_at_best: int
    wall_time_s: float
    us_per_iteration: float
    condition_number: float
    ill_conditioned: bool
    correlated: list[tuple[str, str, float]]
    converged: bool
    relative_rmse: float = float("nan")  # rmse / RMS of the target over the compared pixels
    # fitted parameters whose standard error says nothing: the views do not determine them (the
    # image does not change with them, the error exceeds the parameter's whole range, it is not
    # finite, or there are no more residuals than parameters)
    meaningless: list[str] = dataclasses.field(default_factory=list)
    warnings: list[str] = dataclasses.field(default_factory=list)  # one sentence each, for people

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def free_params(model: Model, fix: Mapping[str, object], rgb: bool) -> tuple[FreeParam, ...]:
    """The parameters a fit solves for: all of `model`'s except those in `fix`."""
    for name in fix:
        model.param(name)  # raises a ValueError naming the allowed parameters
    return tuple(
        FreeParam(p, 3 if (p.rgb and rgb) else 1) for p in model.spec if p.name not in fix
    )


def halton(n: int, dim: int) -> np.ndarray:
    """First n points (after the origin) of the Halton sequence in [0, 1)^dim: deterministic starts."""
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47][:dim]
    out = np.empty((n, dim))
    for j, b in enumerate(primes):
        for i in range(n):
            f, r, k = 1.0, 0.0, i + 1
            while k > 0:
                f /= b
                r += f * (k % b)
                k //= b
            out[i, j] = r
    return out


def _params_from_z(free: tuple[FreeParam, ...], z: dict, fixed: Params) -> Params:
    out = dict(fixed)
    for fp in free:
        v = from_unconstrained(fp.param, z[fp.param.name])
        out[fp.param.name] = jnp.broadcast_to(v, (3,)) if fp.param.rgb else v.reshape(())
    return out


@functools.lru_cache(maxsize=32)
def _compiled_solver(shade: Callable, free: tuple[FreeParam, ...], solver: str, rtol: float, atol: float, max_steps: int):
    """A jitted single-start solve; cached so repeated fits with new targets/starts never recompile."""

    def residuals(z, args):
        gbuffer, pixels, fixed = args
        return _residuals(shade(_params_from_z(free, z, fixed), gbuffer), pixels)

    @jax.jit
    def solve(z0, gbuffer, pixels, fixed):
        sol = optx.least_squares(
            residuals,
            SOLVERS[solver](rtol, atol),
            z0,
            args=(gbuffer, pixels, fixed),
            max_steps=max_steps,
            throw=False,
        )
        r = residuals(sol.value, (gbuffer, pixels, fixed))
        return sol.value, 0.5 * jnp.sum(r**2), sol.stats["num_steps"], sol.result == optx.RESULTS.successful

    return solve


def fit_images(
    shade: Callable[[Params, PyTree], Float[Array, "K H W 3"]],
    gbuffer: PyTree,
    targets: Float[Array, "K H W 3"],
    model: Model,
    *,
    mask: Float[Array, "K H W"] | None = None,
    fix: Mapping[str, object] | None = None,
    init: Mapping[str, object] | None = None,
    rgb: bool = True,
    solver: str = "lm",
    starts: int = 8,
    max_steps: int = 200,
    rtol: float = 1e-7,
    atol: float = 1e-9,
    progress: bool = True,
) -> FitResult:
    """Fit `model`'s free parameters so that `shade(params, gbuffer)` matches `targets`.

    Args:
        shade: pure function of (parameter pytree, gbuffer) -> (K, H, W, 3) images; must be the same
            Python object across calls for the compiled solver to be reused.
        gbuffer: pytree of parameter-independent arrays passed to `shade`.
        targets: (K, H, W, 3) linear RGB target images.
        mask: (K, H, W) pixel weights (1 = fit this pixel, 0 = ignore); default all ones.
        fix: parameters held at given values (validated against their bounds).
        init: starting values for the first start (default: the model's defaults).
        rgb: fit RGB parameters per channel (True) or as one grey value (False).
        solver: one of SOLVERS ("lm" Levenberg–Marquardt, "gauss_newton", "dogleg", "bfgs").
        starts: number of starts: the first from `init`/defaults, the rest Halton points spread
            over each free parameter's natural scale.
        progress: show a progress bar over starts.

    Returns: FitResult with the best start's parameters, standard errors and error metrics.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver {solver!r} is not one of {', '.join(SOLVERS)}")
    if starts < 1:
        raise ValueError(f"starts must be >= 1, got {starts}")
    fix = dict(fix or {})
    init = dict(init or {})
    free = free_params(model, fix, rgb)
    if not free:
        raise ValueError(f"{model.name}: every parameter is fixed; nothing to fit")
    for name in init:
        if name in fix:
            raise ValueError(f"{model.name}.{name}: given both --fix and --init")
    fixed = {k: v for k, v in model.params(**{**fix, **init}).items() if k in fix}
    start_vals = model.params(**{k: v for k, v in init.items()})

    targets = np.asarray(targets, np.float32)
    if mask is None:
        mask = np.ones(targets.shape[:-1], np.float32)
    pixels = _pixels(targets, mask)
    z_of, z_of_unit, finish, normalised = _compiled_helpers(shade, free)

    # Start points: init/defaults first, then Halton points on the natural scale.
    z_starts = [z_of({fp.param.name: start_vals[fp.param.name] for fp in free})]
    if starts > 1:
        z_starts += [z_of_unit(row) for row in halton(starts - 1, len(free)).astype(np.float32)]

    solve = _compiled_solver(shade, free, solver, float(rtol), float(atol), int(max_steps))
    best = None
    total_steps = 0
    finals = []
    t0 = time.perf_counter()
    bar = _progress(len(z_starts), f"fit {model.name}", progress)
    for z0 in z_starts:
        z, loss, steps, ok = solve(z0, gbuffer, pixels, fixed)
        loss = float(loss)
        total_steps += int(steps)
        finals.append((loss, z))
        if best is None or loss < best[0]:
            best = (loss, z, int(steps), bool(ok))
        bar.update(1)
        bar.set_postfix(loss=f"{best[0]:.3e}")
    bar.close()
    wall = time.perf_counter() - t0

    loss, z, steps, ok = best
    params, fitted = finish(z, fixed, gbuffer)
    vals_best = np.asarray(normalised(z))
    at_best = sum(1 for l, zz in finals
                  if l <= loss * (1 + 1e-3) + 1e-12 and np.allclose(np.asarray(normalised(zz)), vals_best, atol=1e-3))

    fitted = np.asarray(fitted)
    tgt = np.asarray(targets)
    m = np.asarray(mask) > 0
    de = metrics.delta_e_2000(fitted, tgt, m)
    se, cond, corr, meaningless = _standard_errors(shade, gbuffer, pixels, free, params)
    names = [fp.param.name for fp in free]
    rmse = metrics.rmse(fitted, tgt, m)
    rms = float(np.sqrt(np.mean(np.asarray(tgt, np.float64)[m] ** 2))) if np.any(m) else 0.0
    relative = rmse / rms if rms > 0 else (0.0 if rmse == 0 else float("inf"))
    warnings = []
    if not ok:
        why = f"it used all {max_steps} steps" if steps >= max_steps else "the solver stopped early"
        warnings.append(f"not converged: the best of {len(z_starts)} starts did not meet the tolerances ({why}); "
                        "raise max_steps (--max-steps) or starts (--starts)")
    if meaningless:
        warnings.append(f"the standard error of {', '.join(meaningless)} is meaningless: these views do not "
                        "determine it (add views or lights that change with it, or fix it)")
    if relative > RELATIVE_RMSE_WARN:
        warnings.append(f"the model cannot reproduce the target: the fit misses it by {relative:.0%} of its RMS "
                        "(check the scene, lighting, exposure and object)")
    return FitResult(
        model=model.name,
        params={k: _tolist(v) for k, v in params.items()},
        stderr={n: _tolist(s) for n, s in zip(names, se)},
        fixed=sorted(fix),
        rmse=rmse,
        delta_e_mean=float(de.mean()) if de.size else 0.0,
        delta_e_max=float(de.max()) if de.size else 0.0,
        iterations=steps,
        total_iterations=total_steps,
        starts=len(z_starts),
        starts_at_best=at_best,
        wall_time_s=wall,
        us_per_iteration=1e6 * wall / max(total_steps, 1),
        condition_number=cond,
        ill_conditioned=bool(cond > CONDITION_WARN or corr),
        correlated=corr,
        converged=ok,
        relative_rmse=relative,
        meaningless=meaningless,
        warnings=warnings,
    )


def _pixels(targets, mask):
    """The compared pixels only: (flat indices (P,), targets (P, 3), √weights (P, 1)).

    Residuals over just these keep the Jacobian (P·3 × parameters) and its QR small when the
    fitted object covers part of the frame.
    """
    m = np.asarray(mask, np.float32).reshape(-1)
    idx = np.nonzero(m > 0)[0]
    if idx.size == 0:
        raise ValueError("the mask selects no pixels; nothing to fit")
    t = np.asarray(targets, np.float32).reshape(-1, 3)[idx]
    return tuple(jax.device_put(x) for x in (idx.astype(np.int32), t, np.sqrt(m[idx])[:, None]))


def _residuals(images, pixels):
    idx, target, sqrt_w = pixels
    return ((images.reshape(-1, 3)[idx] - target) * sqrt_w).reshape(-1)


def _shaped_host(v, fp: FreeParam) -> np.ndarray:
    """`_shaped` on the host (numpy)."""
    v = np.asarray(v, np.float32)
    if fp.size == 1:
        return np.float32(v.mean()) if v.ndim else v
    return np.broadcast_to(v, (3,))


@functools.lru_cache(maxsize=32)
def _compiled_helpers(shade: Callable, free: tuple[FreeParam, ...]):
    """Jitted conversions around the solve (start points, the final parameters and image, normalised
    values for comparing starts): run eagerly they would compile every small op of every call."""

    @jax.jit
    def z_of(values):
        return {fp.param.name: to_unconstrained(fp.param, _shaped(values[fp.param.name], fp)) for fp in free}

    @jax.jit
    def z_of_unit(row):
        return {fp.param.name: to_unconstrained(fp.param, _shaped(denormalise(fp.param, t), fp))
                for fp, t in zip(free, row)}

    @jax.jit
    def finish(z, fixed, gbuffer):
        params = _params_from_z(free, z, fixed)
        return params, shade(params, gbuffer)

    @jax.jit
    def normalised(z):
        return jnp.concatenate([jnp.ravel(normalise(fp.param, from_unconstrained(fp.param, z[fp.param.name])))
                                for fp in free])

    return z_of, z_of_unit, finish, normalised


def _shaped(v, fp: FreeParam):
    v = jnp.asarray(v, jnp.float32)
    if fp.size == 1:
        return jnp.mean(v) if v.ndim else v
    return jnp.broadcast_to(v, (3,))


@functools.lru_cache(maxsize=32)
def _compiled_jacobian(shade: Callable, free: tuple[FreeParam, ...]):
    """Residuals and their Jacobian w.r.t. the free parameters in their own units (jitted, cached)."""
    sizes = [fp.size for fp in free]

    def resid(theta, params, gbuffer, pixels):
        p = dict(params)
        i = 0
        for fp, n in zip(free, sizes):
            v = theta[i : i + n]
            p[fp.param.name] = jnp.broadcast_to(v, (3,)) if fp.param.rgb else v[0]
            i += n
        return _residuals(shade(p, gbuffer), pixels)

    @jax.jit
    def both(theta, params, gbuffer, pixels):
        args = (params, gbuffer, pixels)
        return resid(theta, *args), jax.jacfwd(resid)(theta, *args)

    return both


def _standard_errors(shade, gbuffer, pixels, free, params):
    """Standard errors from the Jacobian at the optimum: cov = s² (JᵀJ)⁻¹, s² = RSS / (n − p).

    J is taken with respect to the parameters in their own units (not z), so the errors are in those
    units. Computed in the precision of the render (float32); the condition number is of the
    column-scaled JᵀJ so it reflects parameter trade-offs, not units.

    Returns (errors per free parameter, condition number, strongly correlated pairs, names of the
    parameters whose error is meaningless: a Jacobian column that is (numerically) zero, an error
    that is not finite or wider than the parameter's range, or no more residuals than parameters).
    """
    sizes = [fp.size for fp in free]
    theta0 = jax.device_put(np.concatenate([np.ravel(_shaped_host(params[fp.param.name], fp)) for fp in free]))
    r, J = _compiled_jacobian(shade, free)(theta0, params, gbuffer, pixels)
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    n = r.size
    p = theta0.size
    s2 = float(r @ r) / max(n - p, 1)
    jtj = J.T @ J
    scale = np.sqrt(np.clip(np.diag(jtj), 1e-300, None))
    jtj_s = jtj / np.outer(scale, scale)
    cond = float(np.linalg.cond(jtj_s)) if np.all(np.isfinite(jtj_s)) else float("inf")
    cov = s2 * np.linalg.pinv(jtj_s) / np.outer(scale, scale)
    var = np.clip(np.diag(cov), 0.0, None)
    sd = np.sqrt(var)
    labels = []
    for fp in free:
        labels += [fp.param.name] if fp.size == 1 else [f"{fp.param.name}[{c}]" for c in "rgb"]
    corr = []
    with np.errstate(invalid="ignore", divide="ignore"):
        cc = cov / np.outer(sd, sd)
    for i in range(p):
        for j in range(i + 1, p):
            if np.isfinite(cc[i, j]) and abs(cc[i, j]) > CORRELATION_WARN:
                corr.append((labels[i], labels[j], float(cc[i, j])))
    col = np.diag(jtj)
    flat = ~(col > 1e-20 * max(float(col.max()), 1e-300))  # the image does not change with it
    out, meaningless, i = [], [], 0
    for fp, n_ in zip(free, sizes):
        s_ = sd[i : i + n_]
        span = fp.param.hi - fp.param.lo
        if n <= p or np.any(flat[i : i + n_]) or not np.all(np.isfinite(s_)) or np.any(s_ > span):
            meaningless.append(fp.param.name)
        out.append(s_ if n_ > 1 else sd[i])
        i += n_
    return out, cond, corr, meaningless


def _tolist(v):
    a = np.asarray(v, np.float64)
    return a.tolist() if a.ndim else float(a)


def _progress(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, leave=False)
