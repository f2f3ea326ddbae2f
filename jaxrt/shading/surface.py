"""Shared shading state: the `Surface` at a hit, local frames, ray offsets, oriented normals.

Everything an integrator, the AOVs and the fitting code need to describe a hit point, in the role
of pbrt-v4's `SurfaceInteraction`. Geometry (`jaxrt.geometry`) builds a `Surface` from a hit's
(prim, u, v); integrators never compute one themselves.

Ray offsets: secondary and shadow rays start at the hit point moved along the geometric normal to
the side they leave towards, by 2^-16·(1 + max|p|) (`offset_scale`): far above float32 rounding of
the barycentric hit point (≈ 2^-23·max|p|) and far below any feature size, so there is no
self-intersection acne and objects that touch or interpenetrate still occlude and reflect each
other. Hit points are recomputed from barycentrics rather than o + t·d for the same reason.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

OFFSET = 2.0**-16



class Surface(eqx.Module):
    """Differentiable re-evaluation of hit points (B,): position, geometric and shading normals
    (outward, as the mesh is wound), tangent, material id."""

    p: Float[Array, "B 3"]
    ng: Float[Array, "B 3"]
    ns: Float[Array, "B 3"]
    tangent: Float[Array, "B 3"]
    material: Int[Array, "B"]
    uv: Float[Array, "B 2"] | None = None  # interpolated texture coordinates



def dot(a, b):
    # Written out rather than jnp.sum(a * b, axis=-1): XLA:CPU hands reductions to library (YNNPACK)
    # fusions, which over a minor axis of 3 are far slower than the elementwise loop this fuses into
    # (the Whitted frame on the CPU: BENCHMARKS.md, "jaxrt beside Mitsuba 3"). Results may differ from
    # the reduction's in the last bits (its summation order is the library's).
    if jnp.shape(a)[-1] != 3 or jnp.shape(b)[-1] != 3:
        return jnp.sum(a * b, axis=-1)
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]



def normalize(v):
    n2 = dot(v, v)
    ok = n2 > 1e-30
    return jnp.where(ok[..., None], v * jax.lax.rsqrt(jnp.where(ok, n2, 1.0))[..., None], 0.0)



def local_frame(n: Float[Array, "B 3"], t: Float[Array, "B 3"]):
    """Orthonormal (t, b, n) with t as close to the mesh tangent as possible."""
    t = t - dot(t, n)[..., None] * n
    ok = dot(t, t) > 1e-12
    # fallback basis (Duff et al. 2017) where the interpolated tangent degenerates
    sign = jnp.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t_fb = jnp.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], axis=-1)
    t = jnp.where(ok[..., None], normalize(t), t_fb)
    return t, jnp.cross(n, t), n



def to_local(w, frame):
    t, b, n = frame
    return jnp.stack([dot(w, t), dot(w, b), dot(w, n)], axis=-1)



def from_local(w, frame):
    t, b, n = frame
    return w[..., :1] * t + w[..., 1:2] * b + w[..., 2:] * n



def offset_scale(p):
    # written out: XLA:CPU runs a reduction over an axis of 3 as a slow library (YNNPACK) fusion
    a = jnp.abs(p)
    return OFFSET * (1.0 + jnp.maximum(jnp.maximum(a[..., 0], a[..., 1]), a[..., 2])[..., None])



def oriented(s: Surface, d: Float[Array, "B 3"]):
    """Normals flipped to the side the ray arrives from (two-sided opaque surfaces)."""
    back = dot(d, s.ng) > 0
    sign = jnp.where(back, -1.0, 1.0)[:, None]
    ng = s.ng * sign
    ns = s.ns * sign
    ns = jnp.where((dot(ns, ng) > 0)[:, None], ns, ng)  # shading normal never past the horizon
    return ng, ns, back



def glass_frame(s: Surface, d):
    """Local frame with +z the outward normal, as brdfs.glass expects; geometric normal wherever the
    interpolated one disagrees about which side the ray is on."""
    wo = -d
    agree = jnp.sign(dot(wo, s.ns)) == jnp.sign(dot(wo, s.ng))
    n = jnp.where(agree[:, None], s.ns, s.ng)
    return local_frame(n, s.tangent)



def mirror_dir(d, ng, ns):
    r = d - 2.0 * dot(d, ns)[:, None] * ns
    r_geo = d - 2.0 * dot(d, ng)[:, None] * ng
    return jnp.where((dot(r, ng) > 0)[:, None], r, r_geo)


def interpolate(attr: Float[Array, "V C"], faces: Int[Array, "B 3"], u: Float[Array, " B"],
                v: Float[Array, " B"]) -> Float[Array, "B C"]:
    """Per-vertex `attr` of faces `faces` interpolated at barycentrics (u, v)."""
    w = (1.0 - u - v)[:, None]
    return w * attr[faces[:, 0]] + u[:, None] * attr[faces[:, 1]] + v[:, None] * attr[faces[:, 2]]


def make_surface(v0, v1, v2, ns, tangent, material, u, v, uv=None) -> Surface:
    """The `Surface` at barycentrics (u, v) of world-space triangles (v0, v1, v2), each (B, 3), with
    the interpolated (unnormalised) shading normal `ns` and tangent; the geometric normal is used
    where the interpolated one degenerates. uv None gives zeros."""
    w = (1.0 - u - v)[:, None]
    p = w * v0 + u[:, None] * v1 + v[:, None] * v2
    ng = normalize(jnp.cross(v1 - v0, v2 - v0))
    return surface_at(p, ng, ns, tangent, material, uv)


def surface_at(p, ng, ns, tangent, material, uv=None) -> Surface:
    """The `Surface` at points p (B, 3) with unit geometric normals ng, the interpolated
    (unnormalised) shading normal `ns` and tangent (`make_surface` once it has p and ng; the
    traversal may return them: `jaxrt.accel.intersect_points`). uv None gives zeros."""
    ns = normalize(ns)
    ns = jnp.where((dot(ns, ns) > 0.5)[:, None], ns, ng)
    if uv is None:
        uv = jnp.zeros(p.shape[:1] + (2,), p.dtype)
    return Surface(p, ng, ns, tangent, material, uv)
