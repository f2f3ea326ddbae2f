"""Rusinkiewicz's half/difference coordinates for isotropic BRDFs.

S. Rusinkiewicz, "A New Change of Variables for Efficient BRDF Representation", Eurographics Workshop on
Rendering, 1998. For a pair (wi, wo) of unit directions in the local frame (normal +z, tangent +x):

    h = normalize(wi + wo)                     half vector, spherical angles (θh, φh)
    d = R_y(-θh) R_z(-φh) wi                   difference vector: wi in a frame where h is the pole,
                                               spherical angles (θd, φd)

R_a(t) is the right-handed rotation by t about axis a. cos θd = wi·h = wo·h. An isotropic BRDF depends
only on (θh, θd, φd); swapping wi and wo (reciprocity) keeps (θh, θd) and maps φd -> φd + π (d -> its
mirror image (-dx, -dy, dz) about the pole h), so a reciprocal isotropic BRDF is π-periodic in φd, which
is why the MERL tables (Matusik et al. 2003) store φd in [0, π) only.

The JAX functions here are batched over leading dimensions, differentiable everywhere (guarded at
θh = 0, where φh is undefined and taken as 0) and used by the measured models (`brdfs.nbrdf`,
`brdfs.merl`). `directions` is the inverse map, used to tabulate a BRDF on a grid of angles.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from brdfs import _common as C

# sin²θh below this is treated as θh = 0 (φh = 0): the rotation R_z(-φh) is then the identity.
_S2_EPS = 1e-24


def half_diff(wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]):
    """(sin θh, cos θh, d): the half vector's polar angle and the difference vector d (..., 3)."""
    h = C.normalize(wi + wo)
    s2 = h[..., 0] ** 2 + h[..., 1] ** 2
    ok = s2 > _S2_EPS
    s = C.safe_sqrt(s2)  # sin θh >= 0
    s_safe = jnp.where(ok, s, 1.0)
    cph = jnp.where(ok, h[..., 0] / s_safe, 1.0)  # cos φh
    sph = jnp.where(ok, h[..., 1] / s_safe, 0.0)  # sin φh
    c = h[..., 2]  # cos θh
    # R_z(-φh): (x, y) -> (cos φh x + sin φh y, -sin φh x + cos φh y)
    x1 = cph * wi[..., 0] + sph * wi[..., 1]
    y1 = -sph * wi[..., 0] + cph * wi[..., 1]
    z1 = wi[..., 2]
    # R_y(-θh): (x, z) -> (cos θh x - sin θh z, sin θh x + cos θh z)
    d = jnp.stack([c * x1 - s * z1, y1, s * x1 + c * z1], axis=-1)
    return s, c, d


def angles(wi: Float[Array, "... 3"], wo: Float[Array, "... 3"]):
    """(θh, θd, φd) in radians: θh, θd in [0, π], φd in (-π, π]."""
    s, c, d = half_diff(wi, wo)
    th = jnp.arctan2(s, c)
    r2 = d[..., 0] ** 2 + d[..., 1] ** 2
    td = jnp.arctan2(C.safe_sqrt(r2), d[..., 2])
    ok = r2 > _S2_EPS  # φd is undefined at θd = 0: 0 there, with a zero gradient
    pd = jnp.where(ok, jnp.arctan2(jnp.where(ok, d[..., 1], 0.0), jnp.where(ok, d[..., 0], 1.0)), 0.0)
    return th, td, pd


def directions(theta_h, theta_d, phi_d, phi_h=0.0, xp=jnp):
    """Inverse map: (wi, wo) (..., 3) from half/difference angles [radians]; `xp` = numpy for float64.

    wi = R_z(φh) R_y(θh) d(θd, φd), wo = 2 (wi·h) h - wi.
    """
    th, td, pd, ph = (xp.asarray(a) for a in (theta_h, theta_d, phi_d, phi_h))
    th, td, pd, ph = xp.broadcast_arrays(th, td, pd, ph)
    dx, dy, dz = xp.sin(td) * xp.cos(pd), xp.sin(td) * xp.sin(pd), xp.cos(td)
    ct, st, cp, sp = xp.cos(th), xp.sin(th), xp.cos(ph), xp.sin(ph)
    x1, z1 = ct * dx + st * dz, -st * dx + ct * dz  # R_y(θh)
    wi = xp.stack([cp * x1 - sp * dy, sp * x1 + cp * dy, z1], axis=-1)  # R_z(φh)
    h = xp.stack([st * cp, st * sp, ct], axis=-1)
    wo = 2.0 * xp.sum(wi * h, axis=-1)[..., None] * h - wi
    return wi, wo
