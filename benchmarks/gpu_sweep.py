"""Sweep the traversal's speed knobs (lanes in flight, steps per loop iteration, leaf size) on one
model at one resolution, primary rays; prints Mrays/s per variant (median of --repeats).

    JAXRT_DATA=... python benchmarks/gpu_sweep.py --model dragon --res 1024
    JAXRT_DATA=... python benchmarks/gpu_sweep.py --pallas      # the Pallas kernel's knobs, primary + shadow

The first form sweeps the XLA loop (impl="xla"); --pallas sweeps jaxrt.accel.traverse_pallas.traverse (rays per
program, Triton warps, steps per predicate check, node-row layout) on primary rays and on shadow rays
between their hits and a point light, traced from the hits and from the light (kernel time only;
bvh.intersect adds the t refinement); --builder picks the tree.
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

from jaxrt.accel import bvh
from jaxrt.accel import traverse_pallas as bvh_pallas
from jaxrt.geometry import data
from jaxrt.geometry import mesh  # noqa: E402
from rays import camera_rays, median_time  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default="dragon")
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--lanes", type=int, nargs="+", default=[1 << 18, 1 << 20])
    ap.add_argument("--steps", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--leaf", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--pallas", action="store_true")
    ap.add_argument("--variants", type=int, nargs="*", default=None, help="indices into PALLAS_VARIANTS")
    ap.add_argument("--builder", default=None, help="--pallas: bvh.build builder[/layout], e.g. sah/dfs")
    args = ap.parse_args()
    if args.pallas:
        return sweep_pallas(args)
    print(f"# {jax.devices()[0].device_kind}, jax {jax.__version__}")
    m = mesh.load(data.find(args.model))
    o, d, _ = camera_rays(m.vertices, args.res)
    od, dd = jnp.asarray(o), jnp.asarray(d)
    ref = None
    for leaf in args.leaf:
        tree = bvh.build(m.vertices, m.faces, leaf_size=leaf)
        for lanes, steps in itertools.product(args.lanes, args.steps):
            f = jax.jit(lambda tr, o, d: bvh.intersect(tr, o, d, lanes=lanes, steps_per_iter=steps, impl="xla"))
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


PALLAS_VARIANTS = [  # bvh_pallas.traverse keyword arguments; BENCHMARKS.md has the earlier variants' numbers
    dict(steps_per_iter=2, layout="inline", skip_tri=False),  # the kernel before child-box rows
    dict(layout="childbox", trail=0),  # child-box rows without the bit trail (the default before the bit trail)
    dict(layout="childbox"),
    dict(layout="childbox", steps_per_iter=2),
]


def sweep_pallas(args):
    m = mesh.load(data.find(args.model))
    kw = dict(zip(("builder", "layout"), args.builder.split("/"))) if args.builder else {}
    tree = bvh.build(m.vertices, m.faces, **kw)
    arrays = dict(node_box=tree.node_box, node_leaf=tree.node_leaf, links=tree.links, triangles=tree.triangles)
    arrays["rows"], arrays["skips"] = jax.jit(bvh_pallas.pack_tables)(**arrays)
    o, d, light = camera_rays(m.vertices, args.res)
    n = len(o)
    od, dd = jnp.asarray(o), jnp.asarray(d)
    lo, hi = jnp.zeros(n, jnp.float32), jnp.full(n, jnp.inf, jnp.float32)
    h = bvh.intersect(tree, od, dd, impl="xla")
    ok = np.asarray(h.prim) >= 0
    p = o[ok] + np.asarray(h.t)[ok, None] * d[ok]
    so, sd = jnp.asarray(p, jnp.float32), jnp.asarray(light[None] - p, jnp.float32)
    slo, shi = jnp.full(len(p), 1e-4, jnp.float32), jnp.full(len(p), 1 - 1e-4, jnp.float32)
    # the same segments from the light end (what the Whitted integrator traces: bvh.occluded(from_end=True))
    lo_o, lo_d = so + shi[:, None] * sd, -sd
    l_lo, l_hi = jnp.zeros(len(p), jnp.float32), shi - slo
    ref_occ = np.asarray(bvh.occluded(tree, so, sd, shi, slo, impl="xla"))
    ref_prim = np.asarray(h.prim)
    print(f"# {jax.devices()[0].device_kind}, {args.model} ({args.builder or 'default tree'}) {args.res}², "
          f"{n} primary, {len(p)} shadow rays", flush=True)
    # The same shadow rays in launches of 1/4, 2 and 4 times the size: time = fixed + per-ray part?
    rep = lambda x, k: jnp.concatenate([x] * k) if k >= 1 else x[: int(len(x) * k)]  # noqa: E731
    light_rays = (lo_o, lo_d, l_lo, l_hi)
    kinds = (("primary", False, (od, dd, lo, hi)), ("shadow", True, (so, sd, slo, shi)),
             ("from-light", True, light_rays),
             *((f"from-light x{k}", True, tuple(rep(x, k) for x in light_rays)) for k in (0.25, 2, 4)),
             ("primary any-hit", True, (od, dd, lo, hi)))
    for k in args.variants if args.variants else range(len(PALLAS_VARIANTS)):
        var = PALLAS_VARIANTS[k]
        line = " ".join(f"{a}={b}" for a, b in var.items()) + ":"
        try:
            for kind, any_hit, args_ in kinds:
                # The tables are arguments, not constants, as in a renderer's jitted frame.
                f = jax.jit(lambda arr, *a, ah=any_hit, var=var: bvh_pallas.traverse(
                    arr, *a, any_hit=ah, leaf_size=1, **var))
                t = time.perf_counter()
                r = jax.block_until_ready(f(arrays, *args_))
                tc = time.perf_counter() - t
                dt = median_time(lambda: jax.block_until_ready(f(arrays, *args_)), args.repeats)
                if kind == "primary any-hit":
                    agree = np.mean(np.asarray(r[0]) == (ref_prim >= 0))
                elif any_hit:
                    ref = np.tile(ref_occ, -(-len(r[0]) // len(ref_occ)))[: len(r[0])]
                    agree = np.mean(np.asarray(r[0]) == ref)
                else:
                    agree = np.mean(np.where(np.asarray(r[0]), np.asarray(tree.prim_ids)[np.asarray(r[2])], -1)
                                    == ref_prim)
                line += (f" {kind} {len(args_[0]) / dt / 1e6:7.1f} Mrays/s "
                         f"(compile {tc:.1f} s, agree {agree:.5f})")
        except Exception as e:  # a variant Triton cannot compile is reported, not fatal
            line += f" FAILED {type(e).__name__}: {str(e)[:300]}"
        print(line, flush=True)


if __name__ == "__main__":
    main()
