"""Instancing: scene build time, device memory and primary-ray throughput for N bunny instances.

    JAXRT_DATA=../shared/data/meshes python benchmarks/instancing.py [--counts 1 100 1000] [--res 128] [--repeats 3]

For each N, N bunnies (random Y rotation, scale 0.8-1.3) on a cubic grid are placed with
[[groups]]/[[instances]] (two-level BVH, `jaxrt.accel.two_level`); the first row is the plain
single-level bunny scene for reference, and N = 1 is one instance with the identity transform (the
same rays and hits as the plain row: the two-level overhead per ray). Prints scene build time (mesh load excluded: cached after the
first row), bytes of the Scene's device arrays, compile time, and primary-ray Mrays/s (camera rays
framing the whole grid, 16x16 tile order; median over --repeats after a warm-up).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

import jax  # noqa: E402

from jaxrt.accel import bvh
from jaxrt.accel import two_level as bvh_instanced
from jaxrt.geometry import instanced as instancing  # noqa: E402
from jaxrt import scene as S  # noqa: E402
from rays import camera_rays, median_time  # noqa: E402

BASE = {"camera": {"position": [0, 0, 30], "look_at": [0, 0, 0], "width": 8, "height": 8},
        "lights": [{"position": [0, 50, 50], "intensity": 10}], "materials": {"m": {"model": "lambert"}}}


def scene_doc(n: int, seed: int = 0) -> dict:
    if n == 0:
        return dict(BASE, objects=[{"mesh": "bunny", "material": "m"}])
    if n == 1:  # one instance, identity transform: the same rays and hits as the plain scene
        return dict(BASE, groups=[{"name": "b", "objects": [{"mesh": "bunny", "material": "m"}]}],
                    instances=[{"group": "b"}])
    rng = np.random.default_rng(seed)
    k = int(np.ceil(n ** (1 / 3)))
    grid = np.stack(np.meshgrid(*[np.arange(float(k))] * 3, indexing="ij"), -1).reshape(-1, 3)[:n] * 0.25
    insts = [{"group": "b", "translate": list(map(float, g)), "rotate": [0.0, float(a), 0.0], "scale": float(s)}
             for g, a, s in zip(grid, rng.uniform(0, 360, n), rng.uniform(0.8, 1.3, n))]
    return dict(BASE, groups=[{"name": "b", "objects": [{"mesh": "bunny", "material": "m"}]}], instances=insts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 100, 1000])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(f"backend {jax.default_backend()}, {args.res}x{args.res} primary rays")
    print("| instances | triangles (instanced) | build s | device MB | compile s | primary Mrays/s | hit % |")
    print("|---|---|---|---|---|---|---|")
    S.load(scene_doc(0))  # load the mesh once so build times exclude file I/O
    for n in [0] + args.counts:
        spec = S.parse(scene_doc(n))
        t0 = time.perf_counter()
        sc = S.build(spec)
        jax.block_until_ready(jax.tree.leaves(sc))
        build = time.perf_counter() - t0
        geo = sc.geometry
        if isinstance(geo, instancing.InstancedGeometry):
            tree = geo.tree
            xf = np.asarray(tree.object_to_world, np.float64)
            v = np.asarray(geo.vertices, np.float64)
            pts = np.concatenate([v[::50] @ m[:, :3].T + m[:, 3] for m in xf])
            fn = jax.jit(bvh_instanced.intersect)
        else:
            tree = geo.tree
            pts = np.asarray(geo.vertices)[::50]  # the same framing as the identity instance
            fn = jax.jit(bvh.intersect)
        o, d, _ = camera_rays(pts, args.res)
        t0 = time.perf_counter()
        hit = jax.block_until_ready(fn(tree, o, d))
        comp = time.perf_counter() - t0
        sec = median_time(lambda: jax.block_until_ready(fn(tree, o, d)), args.repeats)
        print(f"| {n if n else 'plain bunny'} | {geo.triangle_count:,} | {build:.2f} | "
              f"{S.device_bytes(sc) / 1e6:.1f} | {comp:.1f} | {len(o) / sec / 1e6:.3f} | "
              f"{100 * np.mean(np.asarray(hit.prim) >= 0):.0f} |", flush=True)


if __name__ == "__main__":
    main()
