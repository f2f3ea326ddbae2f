"""Importance sampling for measured (tabulated or neural) isotropic BRDFs.

A one-sample mixture (brdfs._common.mixture) of cosine-weighted sampling and a *tabulated half-vector
lobe*: the half vector h is drawn from a table over θh, conditioned on the view angle θo, φh uniform,
and wi = reflect(wo, h). The table is built from the BRDF itself when a material is loaded
(`build`), so it follows whatever lobe shape the measurement has (long tails, off-specular peaks,
Fresnel growth at grazing views) rather than an analytic proxy's.

Table. θh in [0, π/2] is cut into N_H = 64 bins with edges θ_k = (π/2)(k/N_H)² (the square-root
spacing of the MERL tables, Matusik et al. 2003: fine near the normal, where sharp lobes live; the
first edges are 0.02°, 0.09°, 0.2°, 0.35°, ...). Within a bin the density is uniform in solid angle
(uniform in v = 1 - cos θh, which is stored and computed as (hx² + hy²)/(1 + hz) so that it keeps its
relative precision in float32 for tiny θh). At K = 8 view angles θo_j the bin masses are

    P_jb ∝ ∫_bin  g(reflect(wo_j, h)) · 4 (wo_j·h) dω_h,     g(wi) = max(lum f(wi, wo_j) - floor, 0) cos θi

(4 wo·h = dω_i/dω_h), i.e. the density in wi that the table aims for is ∝ the BRDF's "specular part"
times cos θi, with g = 0 below the horizon and where wo·h <= 0. Each bin's integral is a midpoint rule
over 4 sub-bins in v × 16 azimuths over [0, π] (the lobe is mirror-symmetric about the plane of
incidence for an isotropic BRDF). `floor` is a conservative diffuse level: the smallest channel-mean
BRDF value over θo <= 60°, 30° <= θh <= 75°, θi <= 75°. Between view angles the bin probabilities
are interpolated linearly in θo (a convex blend of normalised tables, so still normalised).

Lobe choice. The tabulated lobe is chosen with probability ps = A_s / (A_s + π floor), clipped to
[0.1, 0.9], where A_s is the mean over the K view angles of ∫ g dω_i; the cosine lobe keeps at least
10 % so that the density is positive wherever f > 0.

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

N_H = 64
_TH_EDGES = (math.pi / 2) * (np.arange(N_H + 1, dtype=np.float64) / N_H) ** 2
#: bin edges in v = 1 - cos θh (float64 -> float32 keeps their relative precision)
V_EDGES = (2.0 * np.sin(0.5 * _TH_EDGES) ** 2).astype(np.float32)
#: view angles [radians] at which the tables are built
THETA_O = np.radians([0.0, 30.0, 45.0, 60.0, 70.0, 78.0, 84.0, 89.0]).astype(np.float32)
K = len(THETA_O)
PS_RANGE = (0.1, 0.9)
_SUB_V, _SUB_PHI = 4, 16

#: shapes of the sampler's entries in a measured model's parameter pytree (no batch dimensions)
SHAPES = {"cdf": (K, N_H + 1), "ps": ()}


def _node_weights(wo: Float[Array, "... 3"]) -> Float[Array, "... K"]:
    """Hat-function weights (..., K) of the view angle θo over the nodes THETA_O (clamped at the ends)."""
    th = jnp.arctan2(C.safe_sqrt(wo[..., 0] ** 2 + wo[..., 1] ** 2), wo[..., 2])
    nodes = jnp.asarray(THETA_O)
    th = jnp.clip(th, nodes[0], nodes[-1])[..., None]
    left = jnp.concatenate([nodes[:1] - 1.0, nodes[:-1]])
    right = jnp.concatenate([nodes[1:], nodes[-1:] + 1.0])
    up = (th - left) / (nodes - left)
    down = (right - th) / (right - nodes)
    return jnp.clip(jnp.minimum(up, down), 0.0, 1.0)


def _blended_cdf(p, wo) -> Float[Array, "... N+1"]:
    w = _node_weights(wo)
    return jnp.sum(w[..., :, None] * p["cdf"], axis=-2)


def _v_of(h: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """1 - cos θh of a unit h with h_z > 0, without cancellation."""
    return (h[..., 0] ** 2 + h[..., 1] ** 2) / (1.0 + jnp.maximum(h[..., 2], 0.0))


def lobe_prob(p) -> Float[Array, "..."]:
    return p["ps"]


def spec_sample(p, wo: Float[Array, "... 3"], u: Float[Array, "... 2"]) -> Float[Array, "... 3"]:
    """wi from the tabulated half-vector lobe; (0, 0, -1) (a failed sample) where wo·h <= 0."""
    cdf = _blended_cdf(p, wo)  # (..., N+1)
    u0 = u[..., 0]
    cdf, u0 = jnp.broadcast_arrays(cdf, u0[..., None])
    u0 = u0[..., 0]
    b = jnp.clip(jnp.sum(cdf[..., 1:-1] <= u0[..., None], axis=-1), 0, N_H - 1)
    c0 = jnp.take_along_axis(cdf, b[..., None], axis=-1)[..., 0]
    c1 = jnp.take_along_axis(cdf, b[..., None] + 1, axis=-1)[..., 0]
    frac = jnp.clip(C.safe_div(u0 - c0, c1 - c0), 0.0, 1.0)
    ve = jnp.asarray(V_EDGES)
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
    ve = jnp.asarray(V_EDGES)
    b = jnp.clip(jnp.searchsorted(ve, v, side="right") - 1, 0, N_H - 1)
    cdf = _blended_cdf(p, wo)
    cdf, b = jnp.broadcast_arrays(cdf, b[..., None])
    b = b[..., :1]
    prob = (jnp.take_along_axis(cdf, b + 1, axis=-1) - jnp.take_along_axis(cdf, b, axis=-1))[..., 0]
    b = b[..., 0]
    p_h = prob / (2.0 * math.pi * (ve[b + 1] - ve[b]))
    p_h = jnp.where(h[..., 2] > 0, p_h, 0.0)
    return p_h * C.half_jacobian(wo, h)


def make(eval_fn):
    """(sample, pdf) of the mixture for a measured model with BRDF `eval_fn(p, wi, wo)`."""
    return C.mixture(lobe_prob, spec_sample, spec_pdf, eval_fn)


@functools.partial(jax.jit, static_argnums=0)
def build(eval_fn, p) -> dict:
    """The sampler's table {"cdf": (K, N_H + 1), "ps": ()} for one material (p without batch dims).

    Built from `eval_fn(p, wi, wo)` as the module docstring describes; one compiled function serves
    every material of a model (p is traced).
    """
    ve = jnp.asarray(V_EDGES, jnp.float32)
    dv = ve[1:] - ve[:-1]  # (N,)
    t = (jnp.arange(_SUB_V) + 0.5) / _SUB_V
    v = ve[:-1, None] + dv[:, None] * t  # (N, S)
    sin_h = jnp.sqrt(v * (2.0 - v))
    phi = (jnp.arange(_SUB_PHI) + 0.5) / _SUB_PHI * math.pi  # (M,)
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
    a_s = jnp.mean(tot)
    ps = C.lobe_prob(a_s, math.pi * floor)
    ps = jnp.clip(ps, *PS_RANGE)
    return {"cdf": cdf.astype(jnp.float32), "ps": ps.astype(jnp.float32)}
