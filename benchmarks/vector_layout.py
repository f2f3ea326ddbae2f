"""How XLA lays out 3-vector glue: one chain of a path tracer's shading arithmetic (normalize, dot,
reflect, scale by a per-path scalar, select) over B paths, with the vectors as (B, 3) arrays and a
reduction for the dot product, as (B, 3) arrays with the dot written out per component (what
`jaxrt.shading.surface.dot` does), as (3, B) arrays, and as three separate (B,) arrays per vector.

    python benchmarks/vector_layout.py                 # 131,072 paths, medians of 50 calls, 3 rounds
    python benchmarks/vector_layout.py --paths 1048576

Prints each layout's median wall time per call; the results are checked equal to float32 rounding.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


def aos_reduce(a, b, s):
    n = a * jax.lax.rsqrt(jnp.sum(a * a, -1, keepdims=True))
    d = jnp.sum(n * b, -1, keepdims=True)
    r = (b - 2.0 * d * n) * s[:, None]
    return jnp.where(d > 0, r, -r), jnp.sum(r * n, -1)


def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def aos_written(a, b, s):
    n = a * jax.lax.rsqrt(_dot(a, a))[:, None]
    d = _dot(n, b)[:, None]
    r = (b - 2.0 * d * n) * s[:, None]
    return jnp.where(d > 0, r, -r), _dot(r, n)


def transposed(a, b, s):
    n = a * jax.lax.rsqrt(jnp.sum(a * a, 0, keepdims=True))
    d = jnp.sum(n * b, 0, keepdims=True)
    r = (b - 2.0 * d * n) * s[None, :]
    return jnp.where(d > 0, r, -r).T, jnp.sum(r * n, 0)


def separate(ax, ay, az, bx, by, bz, s):
    inv = jax.lax.rsqrt(ax * ax + ay * ay + az * az)
    nx, ny, nz = ax * inv, ay * inv, az * inv
    d = nx * bx + ny * by + nz * bz
    rx, ry, rz = (bx - 2 * d * nx) * s, (by - 2 * d * ny) * s, (bz - 2 * d * nz) * s
    sg = jnp.where(d > 0, 1.0, -1.0)
    return jnp.stack([rx * sg, ry * sg, rz * sg], -1), rx * nx + ry * ny + rz * nz


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--paths", type=int, default=131072)
    ap.add_argument("--calls", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.normal(size=(args.paths, 3)), jnp.float32)
    b = jnp.asarray(rng.normal(size=(args.paths, 3)), jnp.float32)
    s = jnp.asarray(rng.random(args.paths), jnp.float32)
    cols = [jnp.array(a[:, i]) for i in range(3)] + [jnp.array(b[:, i]) for i in range(3)] + [s]
    layouts = {"(B, 3), reduction": (jax.jit(aos_reduce), (a, b, s)),
               "(B, 3), dot written out": (jax.jit(aos_written), (a, b, s)),
               "(3, B)": (jax.jit(transposed), (jnp.array(a.T), jnp.array(b.T), s)),
               "x, y, z separate": (jax.jit(separate), tuple(cols))}
    ref = None
    for name, (f, xs) in layouts.items():
        out = jax.block_until_ready(f(*xs))
        if ref is None:
            ref = out
        for u, v in zip(ref, out, strict=True):
            np.testing.assert_allclose(np.asarray(v), np.asarray(u), rtol=1e-4, atol=1e-5)
    dev = jax.devices()[0]
    print(f"{getattr(dev, 'device_kind', dev.platform)}, jax {jax.__version__}; {args.paths} paths, "
          f"medians of {args.calls} calls")
    for r in range(args.rounds):
        for name, (f, xs) in layouts.items():
            ts = []
            for _ in range(args.calls):
                t = time.perf_counter()
                jax.block_until_ready(f(*xs))
                ts.append(time.perf_counter() - t)
            print(f"round {r}  {name:26s} {statistics.median(ts) * 1e6:8.0f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
