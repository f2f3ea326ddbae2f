"""Sweep the traversal's speed knobs (lanes in flight, steps per loop iteration, leaf size) on one
model at one resolution, primary rays; prints Mrays/s per variant (median of --repeats).

    JAXRT_DATA=... python benchmarks/gpu_sweep.py --model dragon --res 1024
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxrt import bvh, data, mesh  # noqa: E402
from rays import camera_rays, median_time  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default="dragon")
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--lanes", type=int, nargs="+", default=[1 << 18, 1 << 20])
    ap.add_argument("--steps", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--leaf", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    print(f"# {jax.devices()[0].device_kind}, jax {jax.__version__}")
    m = mesh.load(data.find(args.model))
    o, d, _ = camera_rays(m.vertices, args.res)
    od, dd = jnp.asarray(o), jnp.asarray(d)
    ref = None
    for leaf in args.leaf:
        tree = bvh.build(m.vertices, m.faces, leaf_size=leaf)
        for lanes, steps in itertools.product(args.lanes, args.steps):
            f = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, lanes=lanes, steps_per_iter=steps))
            t = time.perf_counter()
            h = jax.block_until_ready(f(tree, od, dd))
            tc = time.perf_counter() - t
            dt = median_time(lambda: jax.block_until_ready(f(tree, od, dd)), args.repeats)
            prim = np.asarray(h.prim)
            if ref is None:
                ref = prim
            agree = np.mean(prim == ref)
            print(f"leaf {leaf} lanes {lanes:>8} steps {steps:>2}: {len(o) / dt / 1e6:8.1f} Mrays/s "
                  f"({dt * 1e3:.2f} ms, compile {tc:.1f} s, agree {agree:.5f})", flush=True)


if __name__ == "__main__":
    main()
