"""Threefry-2x32 written out round by round, and what is made from it: JAX's `fold_in` and uniform
floats, bit for bit, without JAX's rolled loop on the CPU.

Threefry-2x32 (Salmon et al., "Parallel random numbers: as easy as 1, 2, 3", SC 2011) is the block
function of JAX's default PRNG (20 rounds). JAX lowers its primitive on the CPU as a loop of 5
iterations (a `while` whose every iteration copies its state through memory) to keep compile times
short, and a path-tracing pass draws its camera jitter and its paths' keys over every path of the
pass at once, so each iteration copies the whole pass's state. Written out, the hash and what
consumes it fuse into one loop over the batch: the same uint32 arithmetic, so the same bits.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt32

# the rotation constants of Threefry-2x32, one per round, repeating every 8 rounds (Salmon et al. 2011)
_ROTATIONS = (13, 15, 26, 6, 17, 29, 16, 24)


def _rotl(x, r: int):
    return (x << np.uint32(r)) | (x >> np.uint32(32 - r))


def threefry2x32(k1, k2, x1, x2, rounds: int = 20):
    """The Threefry-2x32 block of key (k1, k2) and counter (x1, x2) (uint32 arrays that broadcast):
    its two output words. The key is injected after every fourth round; 20 rounds is JAX's."""
    ks = (k1, k2, k1 ^ k2 ^ np.uint32(0x1BD11BDA))
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for n in range(rounds):
        x1 = x1 + x2
        x2 = _rotl(x2, _ROTATIONS[n % 8]) ^ x1
        if n % 4 == 3:
            s = (n + 1) // 4
            x1 = x1 + ks[s % 3]
            x2 = x2 + ks[(s + 1) % 3] + np.uint32(s)
    return x1, x2


def fold_in(keys, data: UInt32[Array, "..."]):
    """``jax.random.fold_in`` of typed Threefry keys and uint32 data whose shapes broadcast (one key
    and many data, or a key per datum), bit for bit: each result's key data is the block of its key
    with counter (0, datum). Other key types go through `jax.random.fold_in`."""
    data = jnp.asarray(data, jnp.uint32)
    impl = jax.random.key_impl(keys)
    if str(impl) != "threefry2x32":
        shape = jnp.broadcast_shapes(jnp.shape(keys), data.shape)
        flat = jax.vmap(jax.random.fold_in)(jnp.broadcast_to(keys, shape).reshape(-1),
                                            jnp.broadcast_to(data, shape).reshape(-1))
        return flat.reshape(shape)
    kd = jax.random.key_data(keys)
    y1, y2 = threefry2x32(kd[..., 0], kd[..., 1], jnp.zeros_like(data), data)
    return jax.random.wrap_key_data(jnp.stack([y1, y2], axis=-1), impl=impl)


def unit_float(bits: UInt32[Array, "..."]) -> Float[Array, "..."]:
    """float32 in [0, 1) from the top 23 bits of each word, as `jax.random.uniform` makes them (a
    mantissa under the exponent of 1.0, minus 1)."""
    one = np.array(1.0, np.float32).view(np.uint32)
    return jax.lax.bitcast_convert_type((bits >> np.uint32(9)) | one, jnp.float32) - jnp.float32(1.0)
