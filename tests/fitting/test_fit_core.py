"""The renderer-independent fitting core: transforms, metrics, least squares, standard errors.

A synthetic G-buffer (random direction pairs) and a small Blinn-Phong-like model declared here keep
these checks independent of the BRDF library and the renderer; the end-to-end bars (bunny scene,
real models) are in test_fit_scene.py.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from brdfs.base import Model, Param
from fitting import fit_images, metrics
from fitting.transforms import from_unconstrained, to_unconstrained


def _eval(p, wi, wo):
    h = wi + wo
    h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
    lobe = (p["s"] + 8) / (8 * jnp.pi) * jnp.clip(h[..., 2], 0.0, 1.0)[..., None] ** p["s"]
    return p["rho_d"] / jnp.pi + p["rho_s"][..., None] * lobe


TOY = Model(
    "toy",
    (
        Param("rho_d", 0.5, 0.0, 1.0, rgb=True),
        Param("rho_s", 0.5, 0.0, 1.0),
        Param("s", 10.0, 1.0, 1000.0, scale="log"),
    ),
    _eval,
    None,
    None,
)


def _dirs(key, n):
    v = jax.random.normal(key, (n, 3))
    v = v.at[:, 2].set(jnp.abs(v[:, 2]) + 0.05)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


@pytest.fixture(scope="module")
def gbuffer():
    k1, k2 = jax.random.split(jax.random.PRNGKey(1))
    n = 64 * 64
    return {"wi": _dirs(k1, n).reshape(1, 64, 64, 3), "wo": _dirs(k2, n).reshape(1, 64, 64, 3)}


def shade(p, g):
    return _eval(p, g["wi"], g["wo"]) * g["wi"][..., 2:3]


@pytest.mark.parametrize("p", TOY.spec, ids=lambda p: p.name)
def test_transform_round_trip_and_bounds(p):
    xs = np.linspace(p.lo, p.hi, 7)[1:-1] if p.scale == "linear" else np.geomspace(p.lo, p.hi, 7)[1:-1]
    back = np.asarray(from_unconstrained(p, to_unconstrained(p, xs)))
    np.testing.assert_allclose(back, xs, rtol=2e-5)
    extreme = np.asarray(from_unconstrained(p, jnp.array([-1e4, -30.0, 30.0, 1e4])))
    assert np.all(extreme >= p.lo) and np.all(extreme <= p.hi) and np.all(np.isfinite(extreme))


def test_delta_e_zero_for_equal_and_grows_with_difference():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.05, 1.0, (50, 3))
    assert metrics.delta_e_2000(a, a).max() == 0.0
    d1 = metrics.delta_e_2000(a * 1.02, a).mean()
    d2 = metrics.delta_e_2000(a * 1.2, a).mean()
    assert 0 < d1 < d2


def test_delta_e_matches_cie_reference_pair():
    # Sharma, Wu & Dalal (2005), Table 1 pair 1: Lab (50, 2.6772, -79.7751) vs (50, 0, -82.7485) -> 2.0425.
    import colour

    lab1 = np.array([50.0, 2.6772, -79.7751])
    lab2 = np.array([50.0, 0.0, -82.7485])
    wp = colour.RGB_COLOURSPACES["sRGB"].whitepoint
    to_rgb = lambda lab: colour.XYZ_to_RGB(colour.Lab_to_XYZ(lab, wp), colour.RGB_COLOURSPACES["sRGB"])
    # The target's 99th-percentile luminance is its white: pad with white pixels so the scale is 1.
    fit = np.concatenate([to_rgb(lab1)[None], np.ones((300, 3))])
    tgt = np.concatenate([to_rgb(lab2)[None], np.ones((300, 3))])
    np.testing.assert_allclose(metrics.delta_e_2000(fit, tgt)[0], 2.0425, atol=2e-3)


def test_delta_e_is_colour_sciences_bit_for_bit():
    """`metrics.delta_e_2000` (numpy only) gives colour-science's values exactly (its RGB -> XYZ with the
    default CAT02 step, CIELAB, CIEDE2000) over colours that reach every branch: greys and black (no
    hue), the lightness function's linear segment, hue differences across 0°/360° and beyond ±180°."""
    colour = pytest.importorskip("colour")
    rng = np.random.default_rng(7)
    n = 6000
    tgt = rng.uniform(0.0, 1.0, (n, 3)) ** 3
    tgt[:200] = tgt[:200, :1]  # greys
    tgt[200:220] = 0.0
    tgt[220:400] *= 1e-3  # below (24/116)^3 of the white
    fit = tgt * rng.uniform(0.7, 1.3, (n, 3))
    fit[400:600] = fit[400:600, ::-1]  # large hue changes
    fit[600:700] = tgt[600:700]
    fit[700:800] = fit[700:800, :1]
    mask = rng.uniform(size=n) > 0.1
    ours = metrics.delta_e_2000(fit, tgt, mask)
    # colour-science, as this module computed it before
    cs = colour.RGB_COLOURSPACES["sRGB"]
    lum = tgt[mask] @ np.array([0.2126, 0.7152, 0.0722])
    white = max(float(np.percentile(lum, metrics.WHITE_PERCENTILE)), 1e-12)
    lab = lambda rgb: colour.XYZ_to_Lab(colour.RGB_to_XYZ(rgb / white, cs, apply_cctf_decoding=False), cs.whitepoint)
    ref = np.asarray(colour.delta_E(lab(fit[mask]), lab(tgt[mask]), method="CIE 2000"))
    assert ours.shape == ref.shape and np.array_equal(ours, ref)
    assert "colour" not in metrics.__dict__


def test_srgb_encoding_of_fit_pictures_is_colour_sciences_bit_for_bit():
    colour = pytest.importorskip("colour")
    from fitting import report

    x = np.concatenate([np.linspace(0.0, 1.0, 200001), np.geomspace(1e-12, 1.0, 20001), [0.0031308, 0.0031309]])
    assert np.array_equal(report.srgb_encode(x), np.asarray(colour.cctf_encoding(x, function="sRGB")))


def test_recovers_parameters_noise_free(gbuffer):
    truth = TOY.params(rho_d=[0.2, 0.5, 0.7], rho_s=0.3, s=120.0)
    target = shade(truth, gbuffer)
    r = fit_images(shade, gbuffer, target, TOY, starts=4, progress=False)
    np.testing.assert_allclose(r.params["rho_d"], [0.2, 0.5, 0.7], rtol=1e-3)
    np.testing.assert_allclose(r.params["rho_s"], 0.3, rtol=1e-3)
    np.testing.assert_allclose(r.params["s"], 120.0, rtol=1e-3)
    assert r.rmse < 1e-4 and r.delta_e_max < 0.05
    assert 1 <= r.starts_at_best <= r.starts == 4


def test_fixed_parameter_is_held_and_validated(gbuffer):
    truth = TOY.params(rho_d=0.4, rho_s=0.6, s=30.0)
    target = shade(truth, gbuffer)
    r = fit_images(shade, gbuffer, target, TOY, fix={"s": 30.0}, rgb=False, starts=1, progress=False)
    assert r.params["s"] == pytest.approx(30.0) and "s" not in r.stderr
    np.testing.assert_allclose(r.params["rho_s"], 0.6, rtol=1e-3)
    with pytest.raises(ValueError, match=r"s.*\[1, 1000\]"):
        fit_images(shade, gbuffer, target, TOY, fix={"s": 5000.0}, progress=False)
    with pytest.raises(ValueError, match="unknown parameter"):
        fit_images(shade, gbuffer, target, TOY, fix={"roughness": 0.1}, progress=False)


def test_mask_ignores_corrupted_pixels(gbuffer):
    truth = TOY.params(rho_d=0.3, rho_s=0.5, s=60.0)
    target = np.array(shade(truth, gbuffer))
    target[0, :8] = 5.0  # garbage rows the mask excludes
    mask = np.ones(target.shape[:-1], np.float32)
    mask[0, :8] = 0.0
    r = fit_images(shade, gbuffer, target, TOY, mask=mask, rgb=False, starts=2, progress=False)
    np.testing.assert_allclose(r.params["s"], 60.0, rtol=1e-3)


def test_standard_errors_cover_truth_under_noise(gbuffer):
    """With Gaussian pixel noise, |estimate - truth| / stderr behaves like a standard normal."""
    truth = TOY.params(rho_d=0.4, rho_s=0.5, s=80.0)
    clean = np.asarray(shade(truth, gbuffer))
    sigma = 0.01 * float(clean.mean())
    rng = np.random.default_rng(3)
    z = []
    for _ in range(12):
        noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
        r = fit_images(shade, gbuffer, noisy, TOY, rgb=False, starts=1, progress=False)
        for name in ("rho_d", "rho_s", "s"):
            est = np.mean(r.params[name])
            z.append((est - float(np.mean(truth[name]))) / float(np.mean(r.stderr[name])))
    z = np.abs(np.array(z))
    # For a correct standard error ~68% of |z| fall below 1 and ~95% below 2; 36 draws, loose bounds.
    assert 0.45 < np.mean(z < 1) and np.mean(z < 2.5) > 0.85, z


def test_parameters_that_end_at_a_bound_are_reported(gbuffer):
    """A target beyond the declared range (s = 3000 > 1000, a red channel with no diffuse term): the fit
    ends at those bounds and says so, naming the channel; the parameters inside the range do not."""
    from fitting import report

    target = _eval({"rho_d": jnp.array([0.0, 0.4, 0.6]), "rho_s": jnp.array(0.3), "s": jnp.array(3000.0)},
                   gbuffer["wi"], gbuffer["wo"]) * gbuffer["wi"][..., 2:3]
    r = fit_images(shade, gbuffer, target, TOY, starts=4, progress=False)
    assert r.at_bound == {"s": "upper", "rho_d[r]": "lower"}, (r.at_bound, r.params)
    assert "at a bound" in report.format_result(r) and "s (upper)" in report.format_result(r)


def _compilations():
    """A counter of XLA compilations (persistent-cache hits excluded) from jax.monitoring events."""
    counts = {"n": 0}

    def on(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            counts["n"] += 1

    jax.monitoring.register_event_duration_secs_listener(on)
    return counts


@pytest.mark.parametrize("solver", ["lm", pytest.param("bfgs", marks=pytest.mark.slow)])
def test_step_limit_and_tolerances_are_traced_and_match_optimistix(gbuffer, solver):
    """The user's max_steps, rtol and atol are traced (one compiled solver for all of them below
    the power-of-two step bound), and a capped solve stops exactly where optimistix's own static
    `max_steps` stops it: same iterate, same step count, same result code."""
    import optimistix as optx

    from fitting import solve as S

    truth = {"rho_d": jnp.array([0.2, 0.3, 0.4]), "rho_s": jnp.asarray(0.4), "s": jnp.asarray(60.0)}
    targets = shade(truth, gbuffer)
    free = S.free_params(TOY, {}, True)
    z0 = {fp.param.name: jnp.zeros((fp.size,) if fp.size > 1 else ()) for fp in free}
    pixels = S._pixels(np.asarray(targets), np.ones(targets.shape[:-1], np.float32))
    one = S._compiled_solver(shade, free, solver, S.step_cap(40))
    counter = _compilations()
    one(z0, gbuffer, pixels, {}, S._controls(1e-7, 1e-9, 3))  # compiles once
    after_first = counter["n"]
    settings = [(3, 1e-7, 1e-9), (7, 1e-5, 1e-8), (40, 1e-6, 1e-10)]
    ours = [one(z0, gbuffer, pixels, {}, S._controls(rtol, atol, max_steps)) for max_steps, rtol, atol in settings]
    assert counter["n"] == after_first  # new limits and tolerances compiled nothing
    for (max_steps, rtol, atol), (z, loss, steps, ok) in zip(settings, ours):

        def plain(z_, args):  # the data as arguments, as the library's solve takes them (same rounding)
            gb, px = args
            return S._residuals(shade(S._params_from_z(free, z_, {}), gb), px)

        # the library's residuals carry its Jacobian rule for the Gauss-Newton solvers (same arithmetic)
        residuals = S._columnwise_jvp(plain) if solver in S._JACOBIAN_SOLVERS else plain

        def reference(z_, gb, px, rtol=rtol, atol=atol, max_steps=max_steps):
            sol = optx.least_squares(residuals, S.SOLVERS[solver](rtol, atol), z_, args=(gb, px), max_steps=max_steps,
                                     throw=False)
            return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful

        value, num_steps, success = jax.jit(reference)(z0, gbuffer, pixels)
        ref_ok = bool(success)
        assert int(steps) == int(num_steps)
        assert bool(ok) == ref_ok
        for k in z:
            np.testing.assert_allclose(np.asarray(z[k]), np.asarray(value[k]), rtol=1e-5, atol=1e-6)
    assert S.step_cap(40) == S.step_cap(64) == 64 and S.step_cap(65) == 128 and S.step_cap(200) == 256


def test_columnwise_jacobian_rule_matches_forward_mode_and_float64(gbuffer):
    """The solvers' Jacobian rule (`fitting.solve._columnwise_jvp`): the materialised Jacobian equals
    `jax.jacfwd`'s to float32 rounding and a float64 central difference to its truncation error, J·dz
    is the float64 product of those columns rounded once, and a tangent of the data (which the
    solvers never take) still gets the ordinary derivative."""
    from jax.flatten_util import ravel_pytree

    from fitting import solve as S

    truth = {"rho_d": jnp.array([0.2, 0.3, 0.4]), "rho_s": jnp.asarray(0.4), "s": jnp.asarray(60.0)}
    targets = shade(truth, gbuffer)
    free = S.free_params(TOY, {}, True)
    pixels = S._pixels(np.asarray(targets), np.ones(targets.shape[:-1], np.float32))
    z = {"rho_d": jnp.array([0.1, -0.3, 0.5]), "rho_s": jnp.asarray(-0.2), "s": jnp.asarray(0.4)}

    def plain(z_, args):
        gb, px = args
        return S._residuals(shade(S._params_from_z(free, z_, {}), gb), px)

    ours = S._columnwise_jvp(plain)
    flat, unravel = ravel_pytree(z)
    args = (gbuffer, pixels)
    J = jax.jit(jax.jacfwd(lambda x: ours(unravel(x), args)))(flat)
    J_ref = jax.jit(jax.jacfwd(lambda x: plain(unravel(x), args)))(flat)
    np.testing.assert_allclose(np.asarray(J), np.asarray(J_ref), rtol=1e-4, atol=1e-6)
    # float64 central differences of the residuals, evaluated in numpy from the float32 renders' inputs
    wi, wo = (np.asarray(gbuffer[k], np.float64) for k in ("wi", "wo"))
    idx, tgt, sqrt_w = (np.asarray(v, np.float64) for v in pixels)

    def r64(x):
        zz = unravel(jnp.asarray(x, jnp.float32))
        p = {k: np.asarray(v, np.float64) for k, v in S._params_from_z(free, zz, {}).items()}
        # the parameters in float64 from the float32 transform, then the toy model in float64
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        lobe = (p["s"] + 8) / (8 * np.pi) * np.clip(h[..., 2], 0.0, 1.0)[..., None] ** p["s"]
        img = (p["rho_d"] / np.pi + p["rho_s"] * lobe) * wi[..., 2:3]
        return ((img.reshape(-1, 3)[idx.astype(int)] - tgt) * sqrt_w).reshape(-1)

    # central differences in x: the transform is evaluated in float32, so step on a float32-exact grid
    h = 2.0**-8
    fd = np.stack([(r64(flat + h * e) - r64(flat - h * e)) / (2 * h) for e in np.eye(flat.size)], axis=-1)
    scale = np.abs(fd).max(axis=0)
    assert np.all(np.abs(np.asarray(J) - fd) <= 2e-3 * scale + 1e-6), np.abs(np.asarray(J) - fd).max(axis=0) / scale
    # J·dz: the columns' float64 product, rounded once
    dz = jnp.asarray(np.random.default_rng(0).normal(size=flat.size), jnp.float32)
    _, tangent = jax.jit(lambda x, t: jax.jvp(lambda y: ours(unravel(y), args), (x,), (t,)))(flat, dz)
    exact = (np.asarray(J, np.float64) @ np.asarray(dz, np.float64)).astype(np.float32)
    np.testing.assert_array_max_ulp(np.asarray(tangent), exact, maxulp=1)
    # a tangent of the data: the ordinary JVP
    dgb = jax.tree.map(lambda v: 0.01 * jnp.ones_like(v), gbuffer)
    got = jax.jvp(lambda g: ours(z, (g, pixels)), (gbuffer,), (dgb,))[1]
    want = jax.jvp(lambda g: plain(z, (g, pixels)), (gbuffer,), (dgb,))[1]
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-7)
