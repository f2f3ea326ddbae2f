"""Exact predicates shared by every traversal back end: the watertight ray/triangle edge signs, the
slab test's widening, error-free float32 transforms and double-float arithmetic.

The XLA loop (`traverse_xla`), the Pallas kernel (`traverse_pallas`) and the two-level traversal
(`two_level`) all call these functions, so a ray hits the same triangle on every back end: each
rounded product is made opaque to the compiler (`opaque`) so no fusion contracts it into an FMA,
ties of rounded products fall back to Dekker's exact TwoProduct (`product_error`), and integer
bit operations use int32 (which Triton and XLA treat alike). Woop, Benthin & Wald 2013,
"Watertight Ray/Triangle Intersection"; Dekker 1971, "A floating-point technique for extending
the available precision"; Ize 2013, "Robust BVH Ray Traversal".
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax


# Widening of the slab test's far distance (Ize 2013: 1 + 2*gamma(3) suffices; this is ~2x that).
FAR_SCALE = 1.0 + 2.0**-20
_HI_MASK = -4096  # 0xFFFFF000 as int32: keeps sign, exponent and the top 11 mantissa bits


def opaque_zero(k):
    """A traced int32 0 that the compiler cannot prove is 0, from any int32 array k in [0, 255]."""
    return lax.shift_right_logical(k.astype(jnp.int32), jnp.int32(8))


def _sign3(pos, neg):
    # float32 +1 / -1 / 0 by selects: the same in an XLA fusion and in a Triton kernel
    return jnp.where(pos, 1.0, jnp.where(neg, -1.0, 0.0)).astype(jnp.float32)



def opaque(x, zero):
    """x, unchanged, but as a value the compiler cannot fuse into a later add (no FMA contraction).

    `zero` is a traced int32 0 the compiler cannot prove is 0 (`opaque_zero`). XLA's CPU and GPU backends may
    contract a*b+c into one FMA in one fusion and not in another; exact predicates need every
    rounded product to be the same number everywhere it is used.
    """
    return lax.bitcast_convert_type(lax.bitcast_convert_type(x, jnp.int32) ^ zero, jnp.float32)



def split(a):
    """a = hi + lo exactly, each with at most 12 significant bits (float32)."""
    hi = lax.bitcast_convert_type(lax.bitcast_convert_type(a, jnp.int32) & jnp.int32(_HI_MASK), jnp.float32)
    return hi, a - hi



def product_error(a, b, p):
    """Exact a*b - p for p = fl(a*b) (Dekker's TwoProduct), barring underflow."""
    ah, al = split(a)
    bh, bl = split(b)
    return ((ah * bh - p) + ah * bl + al * bh) + al * bl



def two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)



def fast_two_sum(a, b):
    s = a + b
    return s, b - (s - a)



def df_add(x, y):
    s, e = two_sum(x[0], y[0])
    return fast_two_sum(s, e + (x[1] + y[1]))



def df_neg(x):
    return -x[0], -x[1]



def df_mul(x, y, zero):
    p = opaque(x[0] * y[0], zero)
    e = product_error(x[0], y[0], p)
    return fast_two_sum(p, e + (x[0] * y[1] + x[1] * y[0]))



def edge_products(ax, ay, bx, by, zero):
    """Rounded products (p1, p2) of the edge function ax*by - ay*bx (opaque: see `opaque`)."""
    return opaque(ax * by, zero), opaque(ay * bx, zero)



def edge_sign(ax, ay, bx, by, p1, p2, exact: bool):
    """Sign of ax*by - ay*bx: exact (see module docstring) or from the rounded products only."""
    s = _sign3(p1 > p2, p1 < p2)
    if exact:
        e = product_error(ax, by, p1) - product_error(ay, bx, p2)
        s = jnp.where(p1 == p2, _sign3(e > 0, e < 0), s)
    return s



def pick3(k, x, y, z):
    """x, y or z where k is 0, 1 or 2 (elementwise, by exact selects)."""
    return jnp.where(k == 0, x, jnp.where(k == 1, y, z))



def ray_constants(dx, dy, dz):
    """Per-ray constants from direction components (arrays of any one shape), by elementwise ops only
    so that the Pallas kernel computes them in registers with the same bits: slab inverse directions
    (3), the Woop shear (3), the axis permutation kx, ky, kz and the ray class."""
    d = (dx, dy, dz)
    tiny, m_tiny = jnp.float32(1e-20), jnp.float32(-1e-20)
    neg = [lax.bitcast_convert_type(x, jnp.int32) < 0 for x in d]  # signbit
    inv = [1.0 / jnp.where(jnp.abs(x) < tiny, jnp.where(sg, m_tiny, tiny), x) for x, sg in zip(d, neg)]
    ad = [jnp.abs(x) for x in d]
    kz = jnp.where((ad[0] >= ad[1]) & (ad[0] >= ad[2]), 0, jnp.where(ad[1] >= ad[2], 1, 2)).astype(jnp.int32)  # argmax
    d_z = pick3(kz, *d)
    kx = jnp.where(kz == 2, 0, kz + 1)
    ky = jnp.where(kx == 2, 0, kx + 1)
    flip = d_z < 0  # swap kx and ky to preserve the winding
    kx, ky = jnp.where(flip, ky, kx), jnp.where(flip, kx, ky)
    shear = [pick3(kx, *d) / d_z, pick3(ky, *d) / d_z, 1.0 / d_z]
    return inv, shear, kx, ky, kz, 2 * kz + flip.astype(jnp.int32)
