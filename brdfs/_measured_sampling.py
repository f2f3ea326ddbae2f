"""Importance sampling for measured (tabulated or neural) isotropic BRDFs.

A one-sample mixture (as in brdfs._common.mixture, with a view-dependent lobe probability) of
cosine-weighted sampling and a *tabulated half-vector lobe*: the half vector h is drawn from a table over θh, conditioned on the view angle θo, φh uniform,
and wi = reflect(wo, h). The table is built from the BRDF itself when a material is loaded
(`build`), so it follows whatever lobe shape the measurement has (long tails, off-specular peaks,
Fresnel growth at grazing views) rather than an analytic proxy's. benchmarks/measured_sampling.py
measures the variance against cosine sampling.

Table. θh in [0, π/2] is cut into N_H = 64 bins with edges θ_k = (π/2)(k/N_H)² (the square-root
spacing of the MERL tables, Matusik et al. 2003: fine near the normal, where sharp lobes live; the
first edges are 0.02°, 0.09°, 0.2°, 0.35°, ...). Within a bin the density is uniform in solid angle
(uniform in v = 1 - cos θh, which is stored and computed as (hx² + hy²)/(1 + hz) so that it keeps its
relative precision in float32 for tiny θh). At K = 11 view angles θo_j (0°, 10°, ..., 70°, 78°, 84°,
89°) the bin masses are

    P_jb ∝ ∫_bin  g(reflect(wo_j, h)) · 4 (wo_j·h) dω_h,     g(wi) = max(lum f(wi, wo_j) - floor, 0) cos θi

(4 wo·h = dω_i/dω_h), i.e. the density in wi that the table aims for is ∝ the BRDF's "specular part"
times cos θi, with g = 0 below the horizon and where wo·h <= 0. Each bin's integral is a midpoint rule
over 4 sub-bins in v × 16 azimuths over [0, π] (the lobe is mirror-symmetric about the plane of
incidence for an isotropic BRDF). `floor` is a conservative diffuse level: the smallest channel-mean
BRDF value over θo <= 60°, 30° <= θh <= 75°, θi <= 75°. Between view angles the bin probabilities
are interpolated linearly in θo (a convex blend of normalised tables, so still normalised).

Lobe choice. The tabulated lobe is chosen with a view-dependent probability ps(θo), interpolated
linearly in θo between per-node values. At each node the value is the one among 0, 0.02, 0.04, ...,
0.98 that minimises the relative variance of the one-sample albedo estimator f cos θi / pdf, its
second moment ∫ (f cos θi)² / pdf dω_i computed by the same quadrature as the table (so a nearly
Lambertian material gets ps = 0, plain cosine sampling, and a near-mirror one 0.98). The cosine lobe
keeps at least 2 %, so the density is positive wherever f > 0.

The densities are exact: `pdf` is the density `sample` draws from (tested by chi-square against the
samples), and weights are f cos / pdf.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from brdfs import _common as C
from brdfs.base import Component

N_H = 64
_TH_EDGES = (math.pi / 2) * (np.arange(N_H + 1, dtype=np.float64) / N_H) ** 2
#: bin edges in v = 1 - cos θh (float64 -> float32 keeps their relative precision)
V_EDGES = (2.0 * np.sin(0.5 * _TH_EDGES) ** 2).astype(np.float32)
#: view angles [radians] at which the tables are built
THETA_O = np.radians([0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 78.0, 84.0, 89.0]).astype(np.float32)
K = len(THETA_O)
#: candidate lobe probabilities (0: cosine sampling only; the cosine lobe keeps at least 2 %)
PS_CANDIDATES = np.concatenate([[0.0], np.linspace(0.02, 0.98, 49)]).astype(np.float32)
_SUB_V, _SUB_PHI = 4, 16

#: shapes of the sampler's entries in a measured model's parameter pytree (no batch dimensions)
SHAPES = {"cdf": (K, N_H + 1), "pmf": (K, N_H), "ps": (K,)}


def _node_weights(wo: Float[Array, "... 3"]) -> Float[Array, "... K"]:
    """Hat-function weights (..., K) of the view angle θo over the nodes THETA_O (clamped at the ends)."""
    th = jnp.arctan2(C.safe_sqrt(wo[..., 0] ** 2 + wo[..., 1] ** 2), wo[..., 2])
    nodes = jnp.asarray(THETA_O, th.dtype)
    th = jnp.clip(th, nodes[0], nodes[-1])[..., None]
    left = jnp.concatenate([nodes[:1] - 1.0, nodes[:-1]])
    right = jnp.concatenate([nodes[1:], nodes[-1:] + 1.0])
    up = (th - left) / (nodes - left)
    down = (right - th) / (right - nodes)
    return jnp.clip(jnp.minimum(up, down), 0.0, 1.0)


def _blend(table, wo):
    """Σ_j w_j(θo) table_j: (..., K, n) -> (..., n)."""
    w = _node_weights(wo)
    return jnp.sum(w[..., :, None] * jnp.asarray(table, w.dtype), axis=-2)


def _v_of(h: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """1 - cos θh of a unit h with h_z > 0, without cancellation."""
    return (h[..., 0] ** 2 + h[..., 1] ** 2) / (1.0 + jnp.maximum(h[..., 2], 0.0))


def lobe_prob(p, wo: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Probability of the tabulated lobe at view direction wo (interpolated in θo between the nodes)."""
    return jnp.sum(_node_weights(wo) * p["ps"], axis=-1)


def spec_sample(p, wo: Float[Array, "... 3"], u: Float[Array, "... 2"]) -> Float[Array, "... 3"]:
    """wi from the tabulated half-vector lobe; (0, 0, -1) (a failed sample) where wo·h <= 0."""
    cdf = _blend(p["cdf"], wo)  # (..., N+1)
    u0 = u[..., 0]
    cdf, u0 = jnp.broadcast_arrays(cdf, u0[..., None])
    u0 = u0[..., 0]
    b = jnp.clip(jnp.sum(cdf[..., 1:-1] <= u0[..., None], axis=-1), 0, N_H - 1)
    c0 = jnp.take_along_axis(cdf, b[..., None], axis=-1)[..., 0]
    c1 = jnp.take_along_axis(cdf, b[..., None] + 1, axis=-1)[..., 0]
    frac = jnp.clip(C.safe_div(u0 - c0, c1 - c0), 0.0, 1.0)
    ve = jnp.asarray(V_EDGES, frac.dtype)
    v = ve[b] + frac * (ve[b + 1] - ve[b])
    # sin θh from v directly (sqrt(1 - cos²θh) would lose it in float32 for tiny θh)
    sin_h = C.safe_sqrt(v * (2.0 - v))
    phi = 2.0 * math.pi * u[..., 1]
    h = jnp.stack([sin_h * jnp.cos(phi), sin_h * jnp.sin(phi), 1.0 - v], axis=-1)
    wi = C.reflect_about(wo, h)
    ok = C.dot(wo, h) > 0
    return jnp.where(ok[..., None], wi, jnp.array([0.0, 0.0, -1.0], wi.dtype))


def spec_pdf(p, wo: Float[Array, "... 3"], wi: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Density [1/sr] of `spec_sample` at wi (also > 0 for some wi below the horizon)."""
    h = C.normalize(wi + wo)
    v = _v_of(h)
    ve = jnp.asarray(V_EDGES, v.dtype)
    b = jnp.clip(jnp.searchsorted(ve, v, side="right") - 1, 0, N_H - 1)
    # the bin probabilities from "pmf", not from differences of "cdf" (which lose relative precision
    # for small bins); both tables hold the same distribution
    pmf = _blend(p["pmf"], wo)
    pmf, b = jnp.broadcast_arrays(pmf, b[..., None])
    b = b[..., :1]
    prob = jnp.take_along_axis(pmf, b, axis=-1)[..., 0]
    b = b[..., 0]
    p_h = prob / (2.0 * math.pi * (ve[b + 1] - ve[b]))
    p_h = jnp.where(h[..., 2] > 0, p_h, 0.0)
    return p_h * C.half_vector_jacobian(wi, wo)


def _diffuse_prob(p, wo):
    return 1.0 - lobe_prob(p, wo)


#: The mixture's `Component`s (cosine-weighted diffuse, tabulated lobe) with their view-dependent
#: probabilities, for `Model.mixture`.
COMPONENTS = (Component(_diffuse_prob, C.diffuse_component), Component(lobe_prob, spec_sample))


def make(eval_fn):
    """(sample, pdf) of the mixture for a measured model with BRDF `eval_fn(p, wi, wo)`: the one-sample
    mixture of brdfs._common.mixture (lobe chosen by u0 < ps, u0 rescaled), with a view-dependent ps."""

    def pdf(p, wo, wi):
        ps = lobe_prob(p, wo)
        d = (1.0 - ps) * C.cosine_pdf(wi) + ps * spec_pdf(p, wo, wi)
        return jnp.where(C.upper(wi, wo), d, 0.0)

    def sample(p, wo, u):
        ps = lobe_prob(p, wo)
        u0, u1 = u[..., 0], u[..., 1]
        pick = u0 < ps
        us = jnp.clip(C.safe_div(u0, ps), 0.0, 1.0 - 1e-7)
        ud = jnp.clip(C.safe_div(u0 - ps, 1.0 - ps), 0.0, 1.0 - 1e-7)
        us, ud, u1 = jnp.broadcast_arrays(us, ud, u1)
        wi_s = spec_sample(p, wo, jnp.stack([us, u1], axis=-1))
        wi_d = C.cosine_sample(jnp.stack([ud, u1], axis=-1))
        wi = jnp.where(pick[..., None], wi_s, wi_d)
        pd = pdf(p, wo, wi)
        f = eval_fn(p, wi, wo)
        ok = pd > 0
        weight = jnp.where(ok[..., None], f * C.safe_div(jnp.maximum(wi[..., 2], 0.0), pd)[..., None], 0.0)
        return wi, weight, pd

    return sample, pdf


@functools.partial(jax.jit, static_argnums=0)
def build(eval_fn, p) -> dict:
    """The sampler's tables {"cdf": (K, N_H + 1), "pmf": (K, N_H), "ps": (K,)} for one material (p
    without batch dimensions): per view-angle node the bin probabilities, their running sums and the
    lobe probability.

    Built from `eval_fn(p, wi, wo)` as the module docstring describes; one compiled function serves
    every material of a model (p is traced).
    """
    ve = jnp.asarray(V_EDGES, jnp.float32)
    dv = ve[1:] - ve[:-1]  # (N,)
    t = (jnp.arange(_SUB_V, dtype=jnp.float32) + 0.5) / _SUB_V
    v = ve[:-1, None] + dv[:, None] * t  # (N, S)
    sin_h = jnp.sqrt(v * (2.0 - v))
    phi = (jnp.arange(_SUB_PHI, dtype=jnp.float32) + 0.5) / _SUB_PHI * math.pi  # (M,)
    h = jnp.stack(jnp.broadcast_arrays(sin_h[..., None] * jnp.cos(phi), sin_h[..., None] * jnp.sin(phi),
                                       (1.0 - v)[..., None]), axis=-1)  # (N, S, M, 3)
    tho = jnp.asarray(THETA_O)
    wo = jnp.stack([jnp.sin(tho), jnp.zeros_like(tho), jnp.cos(tho)], -1)[:, None, None, None, :]  # (K,1,1,1,3)
    wi = C.reflect_about(wo, h)  # (K, N, S, M, 3)
    oh = C.dot(wo, h)
    f = C.lum(eval_fn(p, wi, wo))  # (K, N, S, M)
    ci = wi[..., 2]
    # diffuse floor: min f over theta_o <= 60 deg, 30 <= theta_h <= 75 deg, theta_i <= 75 deg
    th_mid = jnp.arccos(1.0 - v)[None, :, :, None]
    region = ((tho <= math.radians(60.0) + 1e-6)[:, None, None, None] & (th_mid >= math.radians(30.0))
              & (th_mid <= math.radians(75.0)) & (ci >= math.cos(math.radians(75.0))) & (oh > 0))
    floor = jnp.maximum(jnp.min(jnp.where(region, f, jnp.inf)), 0.0)
    floor = jnp.where(jnp.isfinite(floor), floor, 0.0)
    g = jnp.where((ci > 0) & (oh > 0), jnp.maximum(f - floor, 0.0) * ci * 4.0 * oh, 0.0)
    mass = jnp.mean(g, axis=(-1, -2)) * (2.0 * math.pi) * dv  # (K, N): ∫_bin g dω_i
    tot = jnp.sum(mass, axis=-1, keepdims=True)
    # a table with no specular mass (a diffuse material) falls back to h uniform in solid angle
    prob = jnp.where(tot > 0, mass / jnp.where(tot > 0, tot, 1.0), dv / jnp.sum(dv))
    cdf = jnp.concatenate([jnp.zeros((K, 1)), jnp.cumsum(prob, axis=-1)], axis=-1)
    cdf = cdf / cdf[:, -1:]
    # lobe probability per node: the candidate minimising the relative variance of f cos / pdf,
    # with the second moment ∫ (f cos)² / pdf dω_i by the same quadrature (dω_i = 4 (wo·h) dω_h)
    valid = (ci > 0) & (oh > 0)
    dw = 4.0 * oh * (2.0 * math.pi) * (dv[:, None, None] / (_SUB_V * _SUB_PHI))  # (K, N, S, M)
    fc = jnp.where(valid, f * ci, 0.0)
    a = jnp.sum(fc * dw, axis=(1, 2, 3))  # (K,) albedo (channel mean)
    p_cos = jnp.maximum(ci, 0.0) / math.pi
    p_spec = (prob / (2.0 * math.pi * dv))[:, :, None, None] * C.safe_div(1.0, 4.0 * oh)
    cand = jnp.asarray(PS_CANDIDATES)[:, None, None, None, None]
    den = (1.0 - cand) * p_cos + cand * p_spec
    m2 = jnp.sum(jnp.where(valid, C.safe_div(fc * fc, den), 0.0) * dw, axis=(2, 3, 4))  # (C, K)
    rel = C.safe_div(m2, a * a) - 1.0
    ps = jnp.asarray(PS_CANDIDATES)[jnp.argmin(rel, axis=0)]
    ps = jnp.where(a > 0, ps, PS_CANDIDATES[0])
    return {"cdf": cdf.astype(jnp.float32), "pmf": prob.astype(jnp.float32), "ps": ps.astype(jnp.float32)}
