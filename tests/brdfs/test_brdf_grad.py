"""Gradients against float64 central finite differences, and NaN/Inf sweeps of values and
gradients at the edge cases (grazing, below the horizon, n·h -> 1, wi = wo, extreme parameters)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfs

MODELS = [n for n in brdfs.names() if n != "glass"]
RNG_SEED = 3

# Interior parameter values (away from kinks), moderately sharp so the lobes are well above 0.
GRAD_PARAMS = {
    "lambert": dict(rho_d=[0.3, 0.5, 0.7]),
    "phong": dict(rho_d=[0.3, 0.5, 0.7], rho_s=[0.4, 0.2, 0.6], s=15.0),
    "blinn_phong": dict(rho_d=[0.3, 0.5, 0.7], rho_s=[0.4, 0.2, 0.6], s=25.0),
    "cook_torrance": dict(rho_d=[0.3, 0.5, 0.7], rho_s=[0.4, 0.2, 0.6], m=0.35, eta=1.7),
    "ward": dict(rho_d=[0.3, 0.5, 0.7], rho_s=[0.4, 0.2, 0.6], alpha_x=0.3, alpha_y=0.15),
    "ashikhmin_shirley": dict(rho_d=[0.3, 0.5, 0.7], rho_s=[0.4, 0.2, 0.6], n_u=40.0, n_v=8.0),
    "disney": dict(base_color=[0.3, 0.5, 0.7], metallic=0.4, subsurface=0.3, specular=0.6, specular_tint=0.4,
                   roughness=0.45, anisotropic=0.5, sheen=0.7, sheen_tint=0.3, clearcoat=0.8, clearcoat_gloss=0.4),
}


def _dirs(rng, n):
    """wo in the upper hemisphere (cos >= 0.25) and wi near wo's mirror direction (inside the lobes)."""
    ct = rng.uniform(0.25, 0.95, n)
    ph = rng.uniform(0, 2 * math.pi, n)
    st = np.sqrt(1 - ct**2)
    wo = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1)
    wi = wo * np.array([-1, -1, 1]) + 0.25 * rng.normal(size=(n, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.2
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    return wi, wo


def _fd_check(g, fd):
    g, fd = np.asarray(g), np.asarray(fd)
    scale = max(np.abs(fd).max(), 1e-12)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7 * scale)


@pytest.mark.parametrize("name", MODELS)
def test_grad_matches_float64_central_differences(name):
    m = brdfs.get(name)
    rng = np.random.default_rng(RNG_SEED)
    wi_np, wo_np = _dirs(rng, 6)
    c_np = rng.uniform(0.5, 1.5, (6, 3))
    with jax.enable_x64(True):
        p = {k: jnp.asarray(np.asarray(v), jnp.float64) for k, v in m.params(**GRAD_PARAMS[name]).items()}
        wi, wo, c = jnp.asarray(wi_np), jnp.asarray(wo_np), jnp.asarray(c_np)

        def per_pair(p, wi, wo):
            return jnp.sum(m.eval(p, wi, wo) * c, axis=-1)  # (6,)

        def loss(p, wi, wo):
            return jnp.sum(per_pair(p, wi, wo))

        gp, gwi, gwo = jax.grad(loss, argnums=(0, 1, 2))(p, wi, wo)
        assert float(loss(p, wi, wo)) > 0
        # every parameter, element by element (RGB channels separately)
        for k, v in p.items():
            v = np.asarray(v)
            fd = np.zeros_like(v)
            for idx in np.ndindex(v.shape or (1,)):
                idx = idx if v.shape else ()
                h = 1e-6 * max(1.0, abs(float(v[idx])))
                vp, vm = v.copy(), v.copy()
                vp[idx] += h
                vm[idx] -= h
                fd[idx] = (float(loss({**p, k: jnp.asarray(vp)}, wi, wo)) - float(loss({**p, k: jnp.asarray(vm)}, wi, wo))) / (2 * h)
            _fd_check(gp[k], fd)
            assert np.abs(fd).max() > 0 or k == "eta" and name != "cook_torrance"
        # wi and wo: each pair's value depends only on its own directions, so perturbing one
        # component of all pairs at once gives every pair's partial derivative.
        h = 1e-6
        for arr_name, g in (("wi", gwi), ("wo", gwo)):
            fd = np.zeros((6, 3))
            for j in range(3):
                e = np.zeros((6, 3))
                e[:, j] = h
                if arr_name == "wi":
                    fp, fm = per_pair(p, wi + e, wo), per_pair(p, wi - e, wo)
                else:
                    fp, fm = per_pair(p, wi, wo + e), per_pair(p, wi, wo - e)
                fd[:, j] = (np.asarray(fp) - np.asarray(fm)) / (2 * h)
            _fd_check(g, fd)


def test_glass_grads_match_float64_central_differences():
    g = brdfs.get("glass")
    fres, refract = g.extras["fresnel"], g.extras["refract"]
    with jax.enable_x64(True):
        n_t = jnp.float64(1.6)
        cos_i = jnp.asarray([0.9, 0.5, 0.2, 0.95, 0.9])
        entering = jnp.asarray([True, True, True, False, False])  # leaving at cos 0.95, 0.9: no TIR
        wo = jnp.asarray([[0.3, 0.1, 0.9], [0.6, -0.5, 0.5], [0.2, 0.1, -0.95]])
        wo = wo / jnp.linalg.norm(wo, axis=-1, keepdims=True)
        h = 1e-6
        for exact in (False, True):
            fn = lambda n, c: jnp.sum(fres({"n_t": n}, c, entering, exact=exact))
            gn, gc = jax.grad(fn, argnums=(0, 1))(n_t, cos_i)
            fd_n = (fn(n_t + h, cos_i) - fn(n_t - h, cos_i)) / (2 * h)
            _fd_check(gn, fd_n)
            per = lambda c: fres({"n_t": n_t}, c, entering, exact=exact)
            _fd_check(gc, (per(cos_i + h) - per(cos_i - h)) / (2 * h))
        w = jnp.asarray([0.3, -0.7, 1.1])
        fn = lambda n, o: jnp.sum(refract({"n_t": n}, o)[0] * w)
        gn, go = jax.grad(fn, argnums=(0, 1))(n_t, wo)
        assert bool(jnp.all(refract({"n_t": n_t}, wo)[1]))
        _fd_check(gn, (fn(n_t + h, wo) - fn(n_t - h, wo)) / (2 * h))
        per = lambda o: jnp.sum(refract({"n_t": n_t}, o)[0] * w, axis=-1)
        fd = np.stack([(per(wo + h * e) - per(wo - h * e)) / (2 * h) for e in np.eye(3)], -1)
        _fd_check(go, fd)


# ---- NaN / Inf sweeps (float32, as the renderer runs) ---------------------------------------

def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _edge_pairs():
    pairs = []
    z = np.array([0.0, 0.0, 1.0])
    for th in (0.0, 30.0, 60.0, 89.9, 90.0):  # wi = mirror(wo) exactly: n·h = 1
        t = math.radians(th)
        wo = np.array([math.sin(t), 0.0, math.cos(t)])
        pairs += [(wo * [-1, -1, 1], wo), (wo, wo)]  # n·h = 1; wi = wo
    for gz in (0.0, 1e-8, 1e-4, -1e-8):  # grazing
        g = _unit([1.0, 0.2, gz])
        pairs += [(g, z), (z, g), (g, g), (g, g * [-1, -1, 1]), (g, _unit([0.0, 1.0, gz]))]
    below = _unit([0.3, 0.2, -0.5])
    pairs += [(below, z), (z, below), (below, below), (-z, z), (z, -z)]
    w = _unit([0.4, -0.3, 0.6])
    pairs += [(-w, w), (w, -w), (np.array([1.0, 0, 0]), np.array([-1.0, 0, 0])), (np.array([0, 1.0, 0]), z)]
    wi, wo = zip(*pairs)
    return np.stack(wi).astype(np.float32), np.stack(wo).astype(np.float32)


def _extreme_params(m):
    """Defaults, then every parameter at each of its bounds, plus all-sharp and all-rough corners."""
    out = [{}]
    for s in m.spec:
        out += [{s.name: s.lo}, {s.name: s.hi}]
    out.append({s.name: (s.hi if s.name in ("s", "n_u", "n_v") else s.lo) for s in m.spec if not s.rgb})
    out.append({s.name: (s.lo if s.name in ("s", "n_u", "n_v") else s.hi) for s in m.spec if not s.rgb})
    if m.name == "ashikhmin_shirley":
        out += [dict(n_u=1.0, n_v=10000.0), dict(n_u=10000.0, n_v=1.0)]
    if m.name == "ward":
        out += [dict(alpha_x=0.01, alpha_y=1.0)]
    return m.stack([m.params(**kw) for kw in out])


@pytest.mark.parametrize("name", MODELS)
def test_no_nan_or_inf_in_values_and_grads_at_edge_cases(name):
    m = brdfs.get(name)
    p = _extreme_params(m)
    p = {k: v[:, None, None] if v.ndim == 1 else v[:, None, None, :] for k, v in p.items()}  # (P, 1, 1[, 3])
    wi, wo = _edge_pairs()
    wi, wo = jnp.asarray(wi)[None, :, None], jnp.asarray(wo)[None, :, None]  # (1, D, 1, 3)
    # u at 0 and 1-eps included; (1, 1, U, 2)
    u = jnp.asarray(np.array([[0.0, 0.0], [1 - 2**-24, 1 - 2**-24], [0.5, 0.25], [1e-7, 0.999], [0.999, 1e-7]], np.float32))[None, None]

    def total(p, wi, wo):
        f = m.eval(p, wi, wo)
        pd = m.pdf(p, wo, wi)
        ws, weight, spdf = m.sample(p, wo, u)  # (P, D, U, ...): every edge-case wo with every u
        return jnp.sum(f) + jnp.sum(pd) + jnp.sum(weight) + jnp.sum(spdf) + jnp.sum(ws), (f, pd, ws, weight, spdf)

    (val, aux), grads = jax.jit(jax.value_and_grad(total, argnums=(0, 1, 2), has_aux=True))(p, wi, wo)
    f, pd, ws, weight, spdf = aux
    for a in (val, f, pd, ws, weight, spdf):
        assert np.all(np.isfinite(np.asarray(a)))
    assert np.all(np.asarray(f) >= 0) and np.all(np.asarray(pd) >= 0) and np.all(np.asarray(weight) >= 0)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(ws), axis=-1), 1.0, atol=1e-4)
    below = (np.asarray(wi)[..., 2] <= 0) | (np.asarray(wo)[..., 2] <= 0)
    assert np.all(np.asarray(f)[np.broadcast_to(below, f.shape[:-1])] == 0)
    for g in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(np.asarray(g)))


def test_glass_no_nan_at_edge_cases():
    g = brdfs.get("glass")
    p = g.stack([g.params(n_t=v) for v in (1.0, 1.5, 3.0)])["n_t"][:, None]
    wi, wo = _edge_pairs()
    wo = jnp.asarray(np.concatenate([wo, wo * np.array([1, 1, -1], np.float32)]))[None]
    u = jnp.full(wo.shape[:-1] + (2,), 0.5)

    def total(n_t, wo):
        pp = {"n_t": n_t}
        wt, ok = g.extras["refract"](pp, wo)
        r = g.extras["fresnel"](pp, jnp.abs(wo[..., 2]), wo[..., 2] > 0)
        re = g.extras["fresnel"](pp, jnp.abs(wo[..., 2]), wo[..., 2] > 0, exact=True)
        wi_s, weight, prob = g.sample(pp, wo, u)
        return jnp.sum(wt) + jnp.sum(r) + jnp.sum(re) + jnp.sum(wi_s) + jnp.sum(prob), (wt, r, re, prob)

    (val, (wt, r, re, prob)), grads = jax.jit(jax.value_and_grad(total, argnums=(0, 1), has_aux=True))(p, wo)
    for a in (val, wt, r, re, prob, *grads):
        assert np.all(np.isfinite(np.asarray(a)))
    for a in (r, re, prob):
        assert np.all((np.asarray(a) >= 0) & (np.asarray(a) <= 1 + 1e-6))
