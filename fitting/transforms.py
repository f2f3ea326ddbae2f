"""Smooth maps between a model's bounded parameters and an unconstrained space for the solver.

Built from each `brdfs.Param`'s declared bounds and natural scale (the one source of truth):

    linear  [lo, hi]:  x = lo + (hi - lo) * sigmoid(z)
    log     [lo, hi]:  x = exp(log lo + (log hi - log lo) * sigmoid(z))

so the solver moves in z ∈ R and every iterate is a valid parameter. Log scale makes a step in z a
relative change of an exponent or roughness, which is what the lobes respond to.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from brdfs.base import Param

# Values are kept this far (in the normalised [0, 1] coordinate) from the bounds when mapped to z,
# so a start or fixed value sitting exactly on a bound (ρ = 0, say) still has a finite preimage.
EDGE = 1e-6


def _span(p: Param) -> tuple[float, float]:
    if p.scale == "log":
        return float(np.log(p.lo)), float(np.log(p.hi))
    return float(p.lo), float(p.hi)


def normalise(p: Param, x) -> Float[Array, "..."]:
    """Parameter value -> position in [0, 1] along its natural scale."""
    lo, hi = _span(p)
    x = jnp.asarray(x, jnp.float32)
    v = jnp.log(x) if p.scale == "log" else x
    return (v - lo) / (hi - lo)


def typical_point(p: Param, t) -> Float[Array, "..."]:
    """Position t in [0, 1] along the natural scale of the parameter's typical range
    (`Param.typical_range`) -> parameter value: where multi-start fits put their starts, since a
    start far outside ordinary materials (a Phong exponent of 1e5, say) sits where the image hardly
    changes with any parameter and the solver stalls."""
    lo, hi = p.typical_range
    t = jnp.asarray(t, jnp.float32)
    if p.scale == "log":
        v = jnp.exp(np.log(lo) + (np.log(hi) - np.log(lo)) * t)
    else:
        v = lo + (hi - lo) * t
    return jnp.clip(v, p.lo, p.hi)


def denormalise(p: Param, t) -> Float[Array, "..."]:
    """Position in [0, 1] along the natural scale -> parameter value."""
    lo, hi = _span(p)
    v = lo + (hi - lo) * jnp.asarray(t)
    # exp(log hi) can round past hi in float32; a value outside the declared bounds is never valid.
    return jnp.clip(jnp.exp(v) if p.scale == "log" else v, p.lo, p.hi)


def to_unconstrained(p: Param, x) -> Float[Array, "..."]:
    """Parameter value (within bounds) -> z ∈ R."""
    t = jnp.clip(normalise(p, x), EDGE, 1.0 - EDGE)
    return jnp.log(t) - jnp.log1p(-t)


def from_unconstrained(p: Param, z) -> Float[Array, "..."]:
    """z ∈ R -> parameter value within [lo, hi]."""
    return denormalise(p, jax.nn.sigmoid(z))

