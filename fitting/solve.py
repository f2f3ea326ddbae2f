"""Recover a BRDF's parameters from target images by nonlinear least squares (optimistix).

The renderer-independent core. A fit sees the renderer only through

    shade(params, gbuffer) -> images   (K, H, W, 3) linear RGB

where `gbuffer` is a pytree of everything that does not depend on the fitted parameters (hit
frames, light directions, visibility, ray trees: "trace once, shade many"). The solver works in an
unconstrained space z built from the model's declared bounds and scales (`fitting.transforms`), so
every iterate is a valid parameter set. Several deterministic starts guard against the local minima
of exponent and roughness lobes; the best is kept and its standard errors come from the Jacobian at
the optimum.

Two entry points share one core (the single-start solve, the start points, the choice of the best
start, the standard errors and the report of parameters that end at a bound):

    fit_images(shade, gbuffer, targets, model)       one target set; starts run one after another
    solve_batch(shade, gbuffer, targets[B], model)   B target sets against one gbuffer (e.g. B measured
                                                     materials on one sampling of directions): one
                                                     compiled solve, vmapped over targets and starts
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from brdfs.base import Model, Param, Params
from fitting import metrics
from fitting.transforms import from_unconstrained, normalise, to_unconstrained, typical_point


def _optx():
    """optimistix, imported where a solver is first built: a process whose solver programs are
    already in the cache (`jaxrt.programs`) never traces one, and the import (with lineax) costs
    0.3-0.6 s."""
    import optimistix

    return optimistix


def _lm_normal(rtol: float, atol: float):
    import lineax as lx

    return _optx().LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))


SOLVERS: dict[str, Callable[[float, float], object]] = {
    "lm": lambda rtol, atol: _optx().LevenbergMarquardt(rtol=rtol, atol=atol),
    # Levenberg–Marquardt on the normal equations (JᵀJ + λI) δ = Jᵀr by Cholesky instead of a QR of the
    # stacked [J; √λ I]: for tall Jacobians (residuals ≫ parameters) a step costs about what the
    # residuals and the Jacobian cost (BRDF-space fits on the CPU: 0.9 ms against 16 ms a step with QR,
    # 3826 direction pairs × 3 channels, 8 parameters), at the price of squaring JᵀJ's condition
    # number, which the damping λ bounds; a failed Cholesky gives a rejected step and more damping.
    "lm_normal": _lm_normal,
    "gauss_newton": lambda rtol, atol: _optx().GaussNewton(rtol=rtol, atol=atol),
    "dogleg": lambda rtol, atol: _optx().Dogleg(rtol=rtol, atol=atol),
    "bfgs": lambda rtol, atol: _optx().BFGS(rtol=rtol, atol=atol),
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
    at_bound: dict[str, str] = dataclasses.field(default_factory=dict)  # see `params_at_bound`

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class Solution:
    """The renderer-independent outcome of one fit of `solve_batch` (one target set).

    `loss` is 0.5 Σ r² of the best start with r = (shade − target)·√mask over the compared entries
    (`residual_count` of them); the caller turns it into its own error measure.
    """

    model: str
    params: dict[str, list[float] | float]  # all parameters (fitted and fixed), parameter units
    stderr: dict[str, list[float] | float]  # fitted parameters only
    fixed: list[str]
    loss: float
    residual_count: int
    iterations: int  # solver steps of the best start
    total_iterations: int  # over all starts
    starts: int
    starts_at_best: int
    condition_number: float
    ill_conditioned: bool
    correlated: list[tuple[str, str, float]]
    converged: bool
    at_bound: dict[str, str]
    meaningless: list[str] = dataclasses.field(default_factory=list)  # as `FitResult.meaningless`

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


# A fitted value within this fraction of its range (on the natural scale, `fitting.transforms.normalise`)
# of a bound "ends at the bound": the declared range, not the data, decided it.
AT_BOUND = 1e-3


def params_at_bound(free: tuple[FreeParam, ...], params: Params, tol: float = AT_BOUND) -> dict[str, str]:
    """{label: "lower" | "upper"} for the fitted values that end at a bound of their declared range.

    Labels are parameter names, with [r], [g], [b] for the channels of an RGB fit.
    """
    out = {}
    for fp in free:
        t = np.atleast_1d(np.asarray(normalise(fp.param, _shaped_host(params[fp.param.name], fp)), np.float64))
        labels = [fp.param.name] if t.size == 1 else [f"{fp.param.name}[{c}]" for c in "rgb"]
        for label, v in zip(labels, t):
            if v <= tol:
                out[label] = "lower"
            elif v >= 1.0 - tol:
                out[label] = "upper"
    return out


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


def step_cap(max_steps: int) -> int:
    """The static loop bound a solve with `max_steps` is compiled for: the next power of two, at
    least 64. The user's `max_steps` and tolerances are traced values (`_capped`), so fits that differ
    only in them share one compiled solver; only a `max_steps` beyond the bound compiles a larger one."""
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    return max(64, 1 << (int(max_steps) - 1).bit_length())


def _controls(rtol: float, atol: float, max_steps: int) -> tuple:
    """The traced solver controls passed beside the data: (rtol, atol, max_steps) as device scalars."""
    return (np.float32(rtol), np.float32(atol), np.int32(max_steps))


@functools.cache
def _capped_classes():
    """Solver wrappers that stop after a traced number of steps (built on first use, since they
    subclass optimistix's interfaces): optimistix takes `max_steps` as a static loop bound, so
    passing the user's value there would compile a solver per value. The wrapper counts steps in its
    state and ends the solve with optimistix's own `nonlinear_max_steps_reached` result when the
    count reaches the traced limit, which is what the static bound would have done: same iterates,
    same step count, same result."""
    optx = _optx()
    import equinox as eqx

    class _Capped(eqx.Module):
        inner: object
        limit: object  # int32 scalar, traced

        @property
        def rtol(self):
            return self.inner.rtol

        @property
        def atol(self):
            return self.inner.atol

        @property
        def norm(self):
            return self.inner.norm

        def init(self, fn, y, args, options, f_struct, aux_struct, tags):
            return self.inner.init(fn, y, args, options, f_struct, aux_struct, tags), jnp.array(0, jnp.int32)

        def step(self, fn, y, args, options, state, tags):
            inner, count = state
            y, inner, aux = self.inner.step(fn, y, args, options, inner, tags)
            return y, (inner, count + 1), aux

        def terminate(self, fn, y, args, options, state, tags):
            inner, count = state
            done, result = self.inner.terminate(fn, y, args, options, inner, tags)
            out_of_steps = jnp.logical_and(jnp.invert(done), count >= self.limit)
            result = optx.RESULTS.where(out_of_steps, optx.RESULTS.nonlinear_max_steps_reached, result)
            return jnp.logical_or(done, out_of_steps), result

        def postprocess(self, fn, y, aux, args, options, state, tags, result):
            return self.inner.postprocess(fn, y, aux, args, options, state[0], tags, result)

    class CappedLeastSquares(_Capped, optx.AbstractLeastSquaresSolver):
        pass

    class CappedMinimiser(_Capped, optx.AbstractMinimiser):
        pass

    return CappedLeastSquares, CappedMinimiser


def _capped(inner, limit):
    least_squares, minimiser = _capped_classes()
    return (minimiser if isinstance(inner, _optx().AbstractMinimiser) else least_squares)(inner, limit)


# The solvers that build the residuals' Jacobian each step (optimistix linearises the residuals and the
# damped Gauss-Newton step materialises the linear map); BFGS takes a gradient (one reverse pass) instead.
_JACOBIAN_SOLVERS = frozenset({"lm", "lm_normal", "gauss_newton", "dogleg"})


# Error-free transformations for `_dot_exact`: Knuth's TwoSum and Dekker's TwoProduct with Veltkamp's
# split of a float32 into two 12-bit halves (4097 = 2^12 + 1); see Ogita, Rump & Oishi, "Accurate sum
# and dot product", SIAM J. Sci. Comput. 26(6), 2005.
def _two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _two_product(a, b):
    def split(x):
        c = x * 4097.0
        hi = c - (c - x)
        return hi, x - hi

    p = a * b
    (ah, al), (bh, bl) = split(a), split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _dot_exact(J: Float[Array, "M n"], x: Float[Array, " n"]) -> Float[Array, " M"]:
    """J·x as if computed in twice the working precision and rounded once (Ogita-Rump-Oishi Dot2): the
    products and the running sum carry their rounding errors, added back at the end."""
    s = jnp.zeros(J.shape[:-1], J.dtype)
    err = jnp.zeros(J.shape[:-1], J.dtype)
    for j in range(J.shape[-1]):
        p, e_p = _two_product(J[:, j], x[j])
        s, e_s = _two_sum(s, p)
        err = err + (e_p + e_s)
    return s + err


def _columnwise_jvp(r_of: Callable) -> Callable:
    """`r_of(z, args)` (z pytree -> residual vector) with a JVP in z that forms the Jacobian J column by
    column, one forward-mode pass per flat parameter, and returns J·dz.

    Why: the Gauss-Newton solvers take J from `jax.linearize` and materialise it by vmapping the linear
    map over the basis vectors (as `jax.jacfwd` does), which carries all tangents through every op of
    the shading as one batch. On XLA:CPU that batched tangent program costs far more than separate
    passes: for a 4-parameter Cook-Torrance fit over 12.6k nodes (34k residuals), 6.5 ms a Jacobian
    batched against 2.4 ms column by column, most of an LM step (BENCHMARKS.md, "The CLI fit's solve, the
    runtime's start and the image writers").
    Here J is computed in the primal part of the JVP, so under `jax.linearize` it is evaluated once per
    point, and each use of the linear map (materialising it, the trust region's predicted reduction) is
    a product with J. The columns are what forward mode gives (the same rules, one tangent at a time).

    J·dz is summed error-free (`_dot_exact`): near the optimum the trust region's predicted reduction
    ½(‖r + J·δ‖² − ‖r‖²) cancels almost entirely, and a plain float32 sum of the products J_ij δ_j,
    whose terms cancel for correlated parameters (ρs against η), rounded enough to reject steps the
    chain-rule JVP accepted: 3 of 6 fits ran to max_steps unconverged, where with the exact sum every
    fit converged in about the chain rule's number of steps. For a basis vector the product is J_ij
    itself, so the materialised matrix is exactly J. Tangents of `args` (the solvers take none) go
    through an ordinary JVP of `r_of`, so the rule is right for any caller."""
    from jax.custom_derivatives import SymbolicZero
    from jax.flatten_util import ravel_pytree

    def is_zero(t):
        return isinstance(t, SymbolicZero)

    def instantiate(tree):
        return jax.tree.map(lambda t: np.zeros(t.shape, t.dtype) if is_zero(t) else t, tree, is_leaf=is_zero)

    @jax.custom_jvp
    def r(z, args):
        return r_of(z, args)

    def r_jvp(primals, tangents):
        (z, args), (dz, dargs) = primals, tangents
        flat, unravel = ravel_pytree(z)

        def g(x):
            return r_of(unravel(x), args)

        # one column a loop iteration (`lax.map`): traced and compiled once whatever the parameter count
        J = jax.lax.map(lambda e: jax.jvp(g, (flat,), (e,))[1], jnp.eye(flat.size, dtype=flat.dtype)).T
        out = g(flat)
        if all(map(is_zero, jax.tree.leaves(dz, is_leaf=is_zero))):
            out_dot = jnp.zeros_like(out)
        else:
            out_dot = _dot_exact(J, ravel_pytree(instantiate(dz))[0])
        if not all(map(is_zero, jax.tree.leaves(dargs, is_leaf=is_zero))):
            out_dot = out_dot + jax.jvp(lambda a: r_of(z, a), (args,), (instantiate(dargs),))[1]
        return out, out_dot

    r.defjvp(r_jvp, symbolic_zeros=True)
    return r


def _solve_one(shade: Callable, free: tuple[FreeParam, ...], solver: str, cap: int, columnwise: bool = False):
    """The single-start solve both entry points run: (z0, gbuffer, pixels, fixed, controls) -> (z, loss,
    steps, ok); `controls` = `_controls(rtol, atol, max_steps)`, traced, max_steps ≤ `cap`. `columnwise`:
    the Gauss-Newton solvers' Jacobian by `_columnwise_jvp`, for the unbatched solve only: vmapped over
    starts or targets, its loop of forward passes runs batched too and was measured slower than the
    batched forward mode (the 6 starts of the 256² CLI fit vmapped: 16-21 CPU s with it, 6.1-6.3 without;
    one after another with it, 1.5), so the vmapped solves keep `jax.linearize`'s Jacobian."""

    def r_of(z, args):
        gbuffer, pixels, fixed = args
        return _residuals(shade(_params_from_z(free, z, fixed), gbuffer), pixels)

    residuals = _columnwise_jvp(r_of) if columnwise and solver in _JACOBIAN_SOLVERS else r_of

    def solve(z0, gbuffer, pixels, fixed, controls):
        optx = _optx()
        rtol, atol, max_steps = controls
        sol = optx.least_squares(
            residuals,
            _capped(SOLVERS[solver](rtol, atol), max_steps),
            z0,
            args=(gbuffer, pixels, fixed),
            max_steps=cap,
            throw=False,
        )
        r = residuals(sol.value, (gbuffer, pixels, fixed))
        return sol.value, 0.5 * jnp.sum(r**2), sol.stats["num_steps"], sol.result == optx.RESULTS.successful

    return solve


def _jit(fn: Callable, what: str, shade: Callable, *parts) -> Callable:
    """`jax.jit(fn)`, with its traced program kept across processes (`jaxrt.programs.cached_jit`) where
    `shade` names itself stably (a `program_key` attribute: the shader factories of `fitting.setup`,
    `fitting.compact` and `fitting.brdf_space`); `parts` are the other values `fn` closes over."""
    key = getattr(shade, "program_key", None)
    if key is None:
        return jax.jit(fn)
    from jaxrt.programs import cached_jit

    return cached_jit(fn, name=f"fitting.solve.{what}[{key}|{'|'.join(map(repr, parts))}]")


@functools.lru_cache(maxsize=32)
def _compiled_solver(shade: Callable, free: tuple[FreeParam, ...], solver: str, cap: int):
    """A jitted single-start solve; cached so repeated fits with new targets, starts, tolerances or
    step limits (up to `cap`) never recompile."""
    return _jit(_solve_one(shade, free, solver, cap, columnwise=True), "solve", shade, free, solver, cap)


@functools.lru_cache(maxsize=32)
def _starts_solve(shade: Callable, free: tuple[FreeParam, ...], solver: str, cap: int):
    """The single-start solve vmapped over starts: (z0 leaves (S, ...), gbuffer, pixels, fixed, controls) ->
    (z, loss, steps, ok), each (S, ...); the unjitted function that several devices split
    (`fit_images(devices=...)`), one object per solver configuration."""
    one = _solve_one(shade, free, solver, cap)

    def solve(z0, gbuffer, pixels, fixed, controls):
        return jax.vmap(lambda z: one(z, gbuffer, pixels, fixed, controls))(z0)

    return solve


@functools.lru_cache(maxsize=32)
def _batch_solve(shade: Callable, free: tuple[FreeParam, ...], solver: str, cap: int):
    """The single-start solve vmapped over starts (inner axis) and target sets (outer axis), unjitted:
    z0 leaves are (B, S, ...), targets (B, P, 3); the gbuffer, compared-entry indices, weights, fixed
    values and solver controls are shared. A vmapped while loop runs until its slowest lane stops;
    finished lanes keep their values, so each lane's result is the one the single-start solve gives."""
    one = _solve_one(shade, free, solver, cap)

    def solve(z0, gbuffer, idx, targets, sqrt_w, fixed, controls):
        def per_target(z_s, target):
            return jax.vmap(lambda z: one(z, gbuffer, (idx, target, sqrt_w), fixed, controls))(z_s)

        return jax.vmap(per_target)(z0, targets)

    return solve


@functools.lru_cache(maxsize=32)
def _compiled_batch_solver(shade: Callable, free: tuple[FreeParam, ...], solver: str, cap: int):
    """`_batch_solve` jitted once (its traced program kept across processes where `shade` names itself)."""
    return _jit(_batch_solve(shade, free, solver, cap), "batch_solve", shade, free, solver, cap)


@dataclasses.dataclass(frozen=True)
class _Problem:
    """What every fit of one model with one fix/init/rgb choice shares: the free parameters, the fixed
    values and the start points (init, else each `Param.fit_start`, first, then Halton points over each
    typical range on the natural scale)."""

    free: tuple[FreeParam, ...]
    fixed: Params
    z_starts: list


def _problem(shade: Callable, model: Model, fix, init, rgb: bool, solver: str, starts: int) -> _Problem:
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
    # the first start: init, else each parameter's `Param.fit_start` (its default unless that is on a bound)
    start_vals = model.params(**{**{p.name: p.fit_start for p in model.spec if p.start is not None}, **init})
    z_of, z_of_unit, _, _ = _compiled_helpers(shade, free)
    z_starts = [z_of({fp.param.name: start_vals[fp.param.name] for fp in free})]
    if starts > 1:
        z_starts += [z_of_unit(row) for row in halton(starts - 1, len(free)).astype(np.float32)]
    return _Problem(free, fixed, z_starts)


def _choose(shade: Callable, free, finals: list[tuple[float, dict, int, bool]]):
    """The best start (lowest loss; the first on ties) and how many starts reached it (same loss
    within 0.1 % and the same normalised parameters within 1e-3)."""
    normalised = _compiled_helpers(shade, free)[3]
    k = int(np.argmin([f[0] for f in finals]))
    loss, z = finals[k][:2]
    vals_best = np.asarray(normalised(z))
    at_best = sum(1 for l, zz, _, _ in finals
                  if l <= loss * (1 + 1e-3) + 1e-12 and np.allclose(np.asarray(normalised(zz)), vals_best, atol=1e-3))
    return finals[k], at_best


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
    devices=None,
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
        solver: one of SOLVERS ("lm" Levenberg–Marquardt, "lm_normal" the same on the normal
            equations, "gauss_newton", "dogleg", "bfgs").
        starts: number of starts: the first from `init`, else each `Param.fit_start` (the default
            unless that is on a bound), the rest Halton points spread over each free parameter's
            typical range (`Param.typical_range`) on its natural scale.
        progress: show a progress bar over starts.
        devices: None (default) or 1: the starts run one after another on the default device; an int
            N, "all" or a list of `jax.devices()` (`jaxrt._devices.select`): the starts are split
            over those devices, each running its share as one vmapped solve (`_devices.batched`:
            padded to a multiple of N with copies of the last start, whose results are dropped).
            Each start's solve is the same method either way (on one device the Gauss-Newton
            solvers form their Jacobian column by column, `_columnwise_jvp`; vmapped, by batched
            forward mode), so the result equals the one-device fit up to rounding (see
            `tests/integrators/test_devices_work.py` for the tolerance).

    Returns: FitResult with the best start's parameters, standard errors, error metrics and the
    parameters that end at a bound of their declared range (`at_bound`).
    """
    prob = _problem(shade, model, fix, init, rgb, solver, starts)
    free, fixed = prob.free, prob.fixed
    targets = np.asarray(targets, np.float32)
    if mask is None:
        mask = np.ones(targets.shape[:-1], np.float32)
    pixels = _pixels(targets, mask)

    controls = _controls(rtol, atol, max_steps)
    devs = fit_devices(devices)
    total_steps = 0
    finals = []
    warm = None
    t0 = time.perf_counter()
    bar = _progress(len(prob.z_starts), f"fit {model.name}", progress)
    if devs:  # every start at once, split over the devices
        finals = _starts_on_devices(shade, free, solver, controls, prob.z_starts, gbuffer, pixels, fixed, devs)
        total_steps = sum(f[2] for f in finals)
        bar.update(len(finals))
    else:
        solve = _compiled_solver(shade, free, solver, step_cap(max_steps))
        # the solve's result committed to the device the starts are on, whether the solver is a stored program
        # (committed outputs) or `jax.jit`'s: the programs after the solve see one argument type, which
        # the warm-up compiles them for. A fit buffer split over several devices (`fitting.compact.split`)
        # leaves the result where the solver put it (replicated over those devices) and has no warm-up.
        device = _single_device(gbuffer, prob.z_starts[0])
        warm = (_warm_up_after_solve(shade, free, jax.device_put(prob.z_starts[0], device), fixed, gbuffer, pixels)
                if device is not None else None)
        for z0 in prob.z_starts:
            z, loss, steps, ok = solve(z0, gbuffer, pixels, fixed, controls)
            total_steps += int(steps)
            finals.append((float(loss), z if device is None else jax.device_put(z, device), int(steps), bool(ok)))
            bar.update(1)
            bar.set_postfix(loss=f"{min(f[0] for f in finals):.3e}")
    bar.close()
    wall = time.perf_counter() - t0
    if warm is not None:
        warm.join()

    (_, z, steps, ok), at_best = _choose(shade, free, finals)
    params, fitted = _compiled_helpers(shade, free)[2](z, fixed, gbuffer)

    fitted = np.asarray(fitted)
    tgt = np.asarray(targets)
    m = np.asarray(mask) > 0
    de = metrics.delta_e_2000(fitted, tgt, m)
    se, cond, corr, meaningless = _standard_errors(shade, gbuffer, pixels, free, params)
    names = [fp.param.name for fp in free]
    rmse = metrics.rmse(fitted, tgt, m)
    rms = float(np.sqrt(np.mean(np.asarray(tgt, np.float64)[m] ** 2))) if np.any(m) else 0.0
    relative = rmse / rms if rms > 0 else (0.0 if rmse == 0 else float("inf"))
    warnings = fit_warnings(ok, steps, max_steps, len(prob.z_starts), meaningless, relative)
    return FitResult(
        model=model.name,
        params={k: _tolist(v) for k, v in params.items()},
        stderr={n: _tolist(s) for n, s in zip(names, se)},
        fixed=sorted(fixed),
        rmse=rmse,
        delta_e_mean=float(de.mean()) if de.size else 0.0,
        delta_e_max=float(de.max()) if de.size else 0.0,
        iterations=steps,
        total_iterations=total_steps,
        starts=len(prob.z_starts),
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
        at_bound=params_at_bound(free, params),
    )


def _single_device(gbuffer: PyTree, z0) -> jax.Device | None:
    """The one device a fit's arrays are on (the start's when none is committed), or None when the fit
    buffer is spread over several devices."""
    devices = set()
    for leaf in jax.tree.leaves(gbuffer):
        if isinstance(leaf, jax.Array):
            devices |= set(leaf.devices())
    if len(devices) > 1:
        return None
    return next(iter(devices)) if devices else next(iter(jax.tree.leaves(z0)[0].devices()))


def _warm_up_after_solve(shade: Callable, free: tuple[FreeParam, ...], z, fixed, gbuffer, pixels) -> threading.Thread:
    """Compile what a fit runs after its solve (comparing the starts, the final parameters and image,
    the Jacobian for the standard errors) in a background thread, while the solver compiles and runs:
    XLA compiles with the GIL released, so on a first run the two compilations overlap. Each program
    runs once on a start point, which has the shapes and types of the solver's result, so the later
    calls find it compiled (the same function objects, the same argument types); the values are
    discarded. An exception here only loses the overlap: the later calls compile for themselves."""

    def run():
        try:
            _, _, finish, normalised = _compiled_helpers(shade, free)
            normalised(z)
            params, _ = finish(z, fixed, gbuffer)
            jax.block_until_ready(_compiled_jacobian(shade, free)(_theta(params, free), params, gbuffer, pixels))
        except Exception:  # noqa: BLE001 -- see the docstring
            pass

    t = threading.Thread(target=run, name="fitting-warm-up", daemon=True)
    t.start()
    return t


def fit_warnings(converged: bool, steps: int, max_steps: int, starts: int, meaningless: list[str],
                 relative: float) -> list[str]:
    """The sentences (for people) an image-space fit reports: not converged, standard errors that say
    nothing (`_stderr_from`), a target the model cannot reproduce (relative RMSE above RELATIVE_RMSE_WARN)."""
    warnings = []
    if not converged:
        why = f"it used all {max_steps} steps" if steps >= max_steps else "the solver stopped early"
        warnings.append(f"not converged: the best of {starts} starts did not meet the tolerances ({why}); "
                        "raise max_steps (--max-steps) or starts (--starts)")
    if meaningless:
        warnings.append(f"the standard error of {', '.join(meaningless)} is meaningless: these views do not "
                        "determine it (add views or lights that change with it, or fix it)")
    if relative > RELATIVE_RMSE_WARN:
        warnings.append(f"the model cannot reproduce the target: the fit misses it by {relative:.0%} of its RMS "
                        "(check the scene, lighting, exposure and object)")
    return warnings


def solve_batch(
    shade: Callable[[Params, PyTree], Float[Array, "..."]],
    gbuffer: PyTree,
    targets: Float[Array, "B ... 3"],
    model: Model,
    *,
    mask: Float[Array, "..."] | None = None,
    fix: Mapping[str, object] | None = None,
    init: Mapping[str, object] | None = None,
    rgb: bool = True,
    solver: str = "lm",
    starts: int = 8,
    max_steps: int = 200,
    rtol: float = 1e-7,
    atol: float = 1e-9,
    batch: int | None = None,
    progress: bool = True,
    devices=None,
) -> list[Solution]:
    """Fit `model` to each of B target sets that share one `gbuffer` (and one mask): `fit_images`'s
    solve, starts and standard errors, run as one compiled program vmapped over targets and starts.

    Args:
        shade, gbuffer, mask, fix, init, rgb, solver, starts, max_steps, rtol, atol: as `fit_images`
            (`shade`'s output may have any shape (..., 3); `mask` has that shape without the 3).
        targets: (B, ..., 3), one target set per fit.
        batch: target sets per compiled call (default all B; fewer bound the memory, B × starts
            Jacobians, and shorten the wait for the slowest lane). A last, smaller chunk is padded
            with copies so that every call has one shape (one compilation).
        progress: a progress bar over the chunks.
        devices: None (default) or 1: the default device; an int N, "all" or a list of `jax.devices()`
            (`jaxrt._devices.select`): each chunk's target sets are split over those devices
            (`_devices.batched`: the chunk is rounded up to a multiple of N, padded with copies), each
            device running the vmapped solve and Jacobians of its own share with its own while loops.
            Each lane computes what it computes on one device, so the fits equal the one-device
            fits up to the rounding of a differently compiled program.

    Returns: one `Solution` per target set, in order.
    """
    prob = _problem(shade, model, fix, init, rgb, solver, starts)
    free, fixed = prob.free, prob.fixed
    targets = np.asarray(targets, np.float32)
    if targets.ndim < 2:
        raise ValueError(f"targets must be (B, ..., 3), got shape {targets.shape}")
    n = targets.shape[0]
    if mask is None:
        mask = np.ones(targets.shape[1:-1], np.float32)
    idx, _, sqrt_w = _pixels(targets[0], mask)
    sel = np.asarray(idx)
    flat = targets.reshape(n, -1, 3)[:, sel]  # (B, P, 3): the compared entries only
    b = n if batch is None else max(1, min(int(batch), n))
    s = len(prob.z_starts)
    # the batch's arrays are stacked on the host (numpy): eager jnp.stack / broadcast_to would each compile
    # a small program per shape, several per model
    z_starts = jax.tree.map(lambda *zs: np.stack([np.asarray(z) for z in zs]), *prob.z_starts)  # leaves (S, ...)
    controls = _controls(rtol, atol, max_steps)

    devs = fit_devices(devices)
    if devs:
        from jaxrt import _devices

        b = _devices.padded(b, devs)
        # the shared arrays go to every device once, not with every call
        on_each = _devices.put_each((gbuffer, idx, sqrt_w, fixed, controls), devs)
        batch_solve, batch_jac = _batch_solve(shade, free, solver, step_cap(max_steps)), _batch_jacobian(shade, free)

        def solve(z0, gbuffer_, idx_, targets_, sqrt_w_, fixed_, controls_):
            return _devices.batched(batch_solve, devs, (True, False, False, True, False, False, False), z0, gbuffer_,
                                    idx_, targets_, sqrt_w_, fixed_, controls_, replicated=on_each)

        def jac(theta, params_, gbuffer_, idx_, targets_, sqrt_w_):
            return _devices.batched(batch_jac, devs, (True, True, False, False, True, False), theta, params_,
                                    gbuffer_, idx_, targets_, sqrt_w_, replicated=[c[:3] for c in on_each])
    else:
        solve = _compiled_batch_solver(shade, free, solver, step_cap(max_steps))
        jac = _compiled_batch_jacobian(shade, free)
    finish = _compiled_helpers(shade, free)[2]
    out = []
    bar = _progress(n, f"fit {model.name}", progress)
    for lo in range(0, n, b):
        chunk = flat[lo: lo + b]
        m = chunk.shape[0]
        if m < b:  # pad to the compiled shape
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], b - m, axis=0)])
        z0 = jax.tree.map(lambda v: np.broadcast_to(v, (b,) + v.shape), z_starts)
        zs, losses, steps, oks = solve(z0, gbuffer, idx, jax.device_put(chunk), sqrt_w, fixed, controls)
        losses, steps, oks = np.asarray(losses), np.asarray(steps), np.asarray(oks)
        zs = jax.tree.map(np.asarray, zs)  # one transfer; slicing B × S device arrays would dispatch each
        bests = []
        for i in range(m):
            finals = [(float(losses[i, k]), jax.tree.map(lambda v, i=i, k=k: v[i, k], zs), int(steps[i, k]),
                       bool(oks[i, k])) for k in range(s)]
            bests.append(_choose(shade, free, finals) + (int(steps[i].sum()),))
        params = [finish(best[1], fixed, gbuffer)[0] for (best, _, _) in bests]
        params_b = jax.tree.map(lambda *v: np.stack([np.asarray(x) for x in v]), *(params + [params[-1]] * (b - m)))
        thetas = [np.asarray(_theta(p, free)) for p in params]
        theta = np.stack(thetas + thetas[-1:] * (b - m))
        r, J = jac(theta, params_b, gbuffer, idx, jax.device_put(chunk), sqrt_w)
        r, J = np.asarray(r), np.asarray(J)
        names = [fp.param.name for fp in free]
        for i, ((loss, _, it, ok), at_best, total) in enumerate(bests):
            se, cond, corr, meaningless = _stderr_from(r[i], J[i], free)
            out.append(Solution(
                model=model.name,
                params={k: _tolist(v) for k, v in params[i].items()},
                stderr={nm: _tolist(e) for nm, e in zip(names, se)},
                fixed=sorted(fixed),
                loss=loss,
                residual_count=int(r[i].size),
                iterations=it,
                total_iterations=total,
                starts=s,
                starts_at_best=at_best,
                condition_number=cond,
                ill_conditioned=bool(cond > CONDITION_WARN or corr),
                correlated=corr,
                converged=ok,
                at_bound=params_at_bound(free, params[i]),
                meaningless=meaningless,
            ))
        bar.update(m)
    bar.close()
    return out


def fit_devices(devices) -> tuple:
    """The devices a fit is split over (`jaxrt._devices.select`), or () for the one-device path (None,
    or the default device alone)."""
    if devices is None:
        return ()
    from jaxrt import _devices

    devs = _devices.solver_devices(devices)
    return devs if _devices.sharded(devs) else ()


def _starts_on_devices(shade, free, solver, controls, z_starts, gbuffer, pixels, fixed, devs):
    """(loss, z, steps, ok) of every start, the starts split over `devs` (`_devices.batched` of the
    vmapped single-start solve; padded to a multiple of the device count, the padding dropped)."""
    from jaxrt import _devices

    s = len(z_starts)
    z0 = _devices.pad_rows(jax.tree.map(lambda *zs: np.stack([np.asarray(z) for z in zs]), *z_starts),
                           _devices.padded(s, devs))
    zs, losses, steps, oks = _devices.batched(_starts_solve(shade, free, solver, step_cap(int(controls[2]))), devs,
                                              (True, False, False, False, False), z0, gbuffer, pixels, fixed, controls)
    return [(float(losses[k]), jax.tree.map(lambda v, k=k: jnp.asarray(v[k]), zs), int(steps[k]), bool(oks[k]))
            for k in range(s)]


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
    values for comparing starts): run eagerly they would compile every small op of every call.
    Plain `jax.jit`, not stored programs: programs this small trace faster than a stored one loads
    (deserialize, lower the exported module, read the executable), measured on a warm `fit --demo`."""

    @jax.jit
    def z_of(values):
        return {fp.param.name: to_unconstrained(fp.param, _shaped(values[fp.param.name], fp)) for fp in free}

    @jax.jit
    def z_of_unit(row):
        return {fp.param.name: to_unconstrained(fp.param, _shaped(typical_point(fp.param, t), fp))
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


def _theta(params: Params, free: tuple[FreeParam, ...]):
    """The free parameters' values in their own units as one flat vector (the Jacobian's columns)."""
    return jax.device_put(np.concatenate([np.ravel(_shaped_host(params[fp.param.name], fp)) for fp in free]))


def _resid_theta(shade: Callable, free: tuple[FreeParam, ...]):
    """Residuals as a function of the flat vector θ of free parameters in their own units."""

    def resid(theta, params, gbuffer, pixels):
        p = dict(params)
        i = 0
        for fp in free:
            v = theta[i: i + fp.size]
            p[fp.param.name] = jnp.broadcast_to(v, (3,)) if fp.param.rgb else v[0]
            i += fp.size
        return _residuals(shade(p, gbuffer), pixels)

    return resid


@functools.lru_cache(maxsize=32)
def _compiled_jacobian(shade: Callable, free: tuple[FreeParam, ...]):
    """Residuals and their Jacobian w.r.t. the free parameters in their own units (jitted, cached)."""
    resid = _resid_theta(shade, free)

    def both(theta, params, gbuffer, pixels):
        args = (params, gbuffer, pixels)
        return resid(theta, *args), jax.jacfwd(resid)(theta, *args)

    return _jit(both, "jacobian", shade, free)


@functools.lru_cache(maxsize=32)
def _batch_jacobian(shade: Callable, free: tuple[FreeParam, ...]):
    """Residuals and Jacobians (`_compiled_jacobian`) vmapped over (θ, params, targets) with a shared
    gbuffer, indices and weights, unjitted."""
    resid = _resid_theta(shade, free)

    def both(theta, params, gbuffer, idx, targets, sqrt_w):
        def one(th, p, t):
            args = (p, gbuffer, (idx, t, sqrt_w))
            return resid(th, *args), jax.jacfwd(resid)(th, *args)

        return jax.vmap(one)(theta, params, targets)

    return both


@functools.lru_cache(maxsize=32)
def _compiled_batch_jacobian(shade: Callable, free: tuple[FreeParam, ...]):
    """`_batch_jacobian` jitted once."""
    return _jit(_batch_jacobian(shade, free), "batch_jacobian", shade, free)


def _standard_errors(shade, gbuffer, pixels, free, params):
    """Standard errors at the optimum (`_stderr_from`), with the Jacobian computed here."""
    r, J = _compiled_jacobian(shade, free)(_theta(params, free), params, gbuffer, pixels)
    return _stderr_from(np.asarray(r), np.asarray(J), free)


def _stderr_from(r: np.ndarray, J: np.ndarray, free: tuple[FreeParam, ...]):
    """Standard errors from the Jacobian at the optimum: cov = s² (JᵀJ)⁻¹, s² = RSS / (n − p).

    J is taken with respect to the parameters in their own units (not z), so the errors are in those
    units. Computed in the precision of the render (float32); the condition number is of the
    column-scaled JᵀJ so it reflects parameter trade-offs, not units.

    Returns (errors per free parameter, condition number, strongly correlated pairs, names of the
    parameters whose error is meaningless: a Jacobian column that is (numerically) zero, an error
    that is not finite or wider than the parameter's range, or no more residuals than parameters).
    """
    sizes = [fp.size for fp in free]
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    n = r.size
    p = J.shape[1]
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
