"""The GPU kernel's node layouts (`jaxrt.accel.traverse_pallas`) side by side, in Mrays/s: brute force
against the tree for small scenes (the Cornell box and copies of it with every triangle split into 4
and 16), and the binary tree's rows against the four-wide tree's, also on a mesh (--scene dragon).

    JAXRT_DATA=... python benchmarks/brute_force.py                 # on a GPU
    JAXRT_DATA=... python benchmarks/brute_force.py --scene dragon --splits 0 --variants tree wide
    JAXRT_DATA=... python benchmarks/brute_force.py --interpret --rays 4096   # anywhere (slow; a check)
    JAXRT_DATA=... python benchmarks/brute_force.py --scene dragon --splits 0 --variants tree wide \
        --interpret --rays 2048 --res 64 --count                    # steps a ray (the interpreter: any machine)

Rays, like a path tracer's (4M of each kind unless --rays): "camera" a pinhole's primary rays, tile
order (coherent); "bounce" rays leaving random points of the surfaces in uniform directions
(incoherent: the later bounces), closest hit; "to light" segments from random surface points to
the ceiling light's quad, "shadow" between random pairs of surface points, any hit. For a mesh (--scene NAME, a data name), the
camera looks at it along +z from 2.5 radii and the light is a small square 2 radii above it.
Variants: "tree" (the binary child-box node table), "wide" (the four-wide tree's rows; "wide trail 0"
without its trail; "tree vec", "wide vec": rows read as 4-word vector loads, the default; "tree scalar": one gather a word; "tree 2 steps": two
steps between checks of the loop's predicate; "tree postponed" / "tree immediate": leaves postponed
(tested by the warp together) or tested where reached), "brute"
(every ray against every triangle; triangles read as gathers whose lanes share one address),
"brute unroll k" (k triangles written out per loop iteration; default 4), "brute scalar"
(read as scalars), and brute force with wider programs (block rays, warps). Each
line: the median of --repeats launches (the tables are arguments, as in a renderer's program) and
how many rays agree with the tree's result (same hit or miss; for closest hits also the same
triangle). `traverse_pallas.BRUTE_FORCE_MAX_TRIANGLES` decides from such tables which scenes go
brute force by default.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxrt import accel  # noqa: E402
from jaxrt import scene as S  # noqa: E402
from jaxrt.accel import bvh  # noqa: E402
from jaxrt.accel import traverse_pallas as TP  # noqa: E402

VARIANTS = {
    "tree": dict(layout="childbox"),
    "wide": dict(layout="wide"),
    "wide trail 0": dict(layout="wide", trail=0),
    "tree vec": dict(layout="childbox", vector_loads=True),
    "wide vec": dict(layout="wide", vector_loads=True),
    "tree scalar": dict(layout="childbox", vector_loads=False),
    "tree 2 steps": dict(layout="childbox", steps_per_iter=2),
    "tree block64 warps2": dict(layout="childbox", block=64, num_warps=2),
    "tree postponed": dict(layout="childbox", postpone=True),
    "tree immediate": dict(layout="childbox", postpone=False),
    "brute": dict(layout="brute"),
    "brute unroll 1": dict(layout="brute", unroll=1),
    "brute unroll 8": dict(layout="brute", unroll=8),
    "brute scalar": dict(layout="brute", scalar_loads=True),
    "brute block64 warps2": dict(layout="brute", block=64, num_warps=2),
}


def split4(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle split into 4 at its edges' midpoints (the same surface, 4x the triangles)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    tris = np.stack([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], 1).reshape(-1, 3, 3)
    return tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3)


def surface_points(tri: np.ndarray, n: int, rng) -> np.ndarray:
    """n points uniformly distributed (by area) over the triangles (F, 3, 3)."""
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return np.einsum("nk,nkj->nj", w, tri[k])


def ray_sets(tri: np.ndarray, cam, n: int, rng) -> dict:
    eye, fwd, right, up, res, _, tan_half = cam
    ys, xs = np.mgrid[0:res, 0:res]
    # tile order (16x16 tiles), as the renderer's camera rays are made
    order = np.lexsort((xs.ravel() % 16, ys.ravel() % 16, xs.ravel() // 16, ys.ravel() // 16))
    sx = ((xs.ravel() + 0.5) / res * 2 - 1)[order] * tan_half
    sy = (1 - (ys.ravel() + 0.5) / res * 2)[order] * tan_half
    d = fwd + sx[:, None] * right + sy[:, None] * up
    cam_o = np.broadcast_to(eye, d.shape)
    p = surface_points(tri, n, rng)
    w = rng.normal(size=(n, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    q = surface_points(tri, n, rng)
    f32 = lambda x: jnp.asarray(np.ascontiguousarray(x), jnp.float32)  # noqa: E731
    m = len(d)
    lamp = cam[5](n)
    return {
        "camera": (False, (f32(cam_o), f32(d), jnp.zeros(m), jnp.full(m, jnp.inf))),
        "to light": (True, (f32(p), f32(lamp - p), jnp.full(n, 1e-4), jnp.full(n, 1 - 1e-4))),
        "bounce": (False, (f32(p), f32(w), jnp.full(n, 1e-4), jnp.full(n, jnp.inf))),
        "shadow": (True, (f32(p), f32(q - p), jnp.full(n, 1e-4), jnp.full(n, 1 - 1e-4))),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rays", type=int, default=1 << 22, help="rays of each incoherent kind")
    ap.add_argument("--res", type=int, default=2048, help="camera rays: res x res")
    ap.add_argument("--splits", type=int, nargs="+", default=[0, 1], help="times each triangle is split in 4")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--interpret", action="store_true", help="the Pallas interpreter (any backend; for a check)")
    ap.add_argument("--scene", default="cornell", help="cornell (the built-in Cornell box) or a mesh's data name")
    ap.add_argument("--count", action="store_true",
                    help="tree layouts: print steps a ray, loop iterations a program and the share of them that run "
                         "the triangle test (`traverse(..., count_steps=True)`) instead of timing")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    if args.scene == "cornell":
        tri0 = np.asarray(S.load("cornell_area").geometry.tree.triangles, np.float64).reshape(-1, 3, 3)
        top = tri0[..., 1].max()

        def lamp(n):  # the ceiling light's quad, 0.5 mm below the ceiling
            return np.stack([rng.uniform(0.213, 0.343, n), np.full(n, top - 0.0005), rng.uniform(0.227, 0.332, n)], 1)

        cam = (np.array([0.278, 0.273, -0.8]), np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.0, 0.0]),
               np.array([0.0, 1.0, 0.0]), args.res, lamp, np.tan(np.radians(19.65)))
    else:
        from jaxrt.geometry import data, mesh

        m = mesh.load(data.find(args.scene))
        tri0 = np.asarray(m.vertices, np.float64)[np.asarray(m.faces)]
        lo, hi = tri0.reshape(-1, 3).min(0), tri0.reshape(-1, 3).max(0)
        c, r = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2

        def lamp(n):
            return c + np.stack([rng.uniform(-0.05, 0.05, n) * r, np.full(n, 2 * r), rng.uniform(-0.05, 0.05, n) * r], 1)

        cam = (c - np.array([0.0, 0.0, 2.5 * r]), np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.0, 0.0]),
               np.array([0.0, 1.0, 0.0]), args.res, lamp, 0.45)
    print(f"# {jax.devices()[0].device_kind}, jax {jax.__version__}; Mrays/s, medians of {args.repeats}"
          f"{' (interpreter)' if args.interpret else ''}", flush=True)
    for k in args.splits:
        v, f = tri0.reshape(-1, 3), np.arange(3 * len(tri0)).reshape(-1, 3)
        for _ in range(k):
            v, f = split4(v, f)
        tree = bvh.build(v.astype(np.float32), f, **accel.RENDER_TREE)
        arrays = dict(node_box=tree.node_box, node_leaf=tree.node_leaf, links=tree.links, triangles=tree.triangles)
        if tree.rows is not None:  # (a CPU process builds no GPU node table; the kernel packs one per call)
            arrays["rows"], arrays["skips"] = tree.rows, tree.skips
        tri = np.asarray(tree.triangles, np.float64).reshape(-1, 3, 3)
        sets = ray_sets(tri, cam, args.rays, rng)
        ref = {}
        for name in args.variants:
            var = dict(VARIANTS[name])
            if args.interpret:
                var.update(interpret=True, block=1024)
                var.pop("num_warps", None)
            line = f"{len(f):5d} triangles  {name:24s}"
            for kind, (any_hit, rays) in sets.items():
                if args.count:
                    if var.get("layout") not in ("childbox", "wide") or var.get("steps_per_iter", 1) != 1:
                        continue
                    # the GPU's programs (the variant's block, not the interpreter's wider one)
                    block = VARIANTS[name].get("block", 32)
                    out = TP.traverse(arrays, *rays, any_hit=any_hit, leaf_size=1, count_steps=True,
                                      **dict(var, block=block))
                    n_steps, n_iter, n_leaf = (np.asarray(x, np.float64) for x in out[5:])
                    line += (f"  {kind}: {n_steps.mean():.1f} steps a ray, {n_iter[::block].mean():.1f} iterations a "
                             f"program, {n_leaf.sum() / n_iter.sum():.0%} with the triangle test")
                    continue
                fn = jax.jit(lambda arr, *a, ah=any_hit, var=var: TP.traverse(arr, *a, any_hit=ah, leaf_size=1, **var))
                try:
                    t0 = time.perf_counter()
                    r = [np.asarray(x) for x in fn(arrays, *rays)]
                    tc = time.perf_counter() - t0
                    ts = []
                    for _ in range(args.repeats):
                        t0 = time.perf_counter()
                        jax.block_until_ready(fn(arrays, *rays))
                        ts.append(time.perf_counter() - t0)
                    dt = statistics.median(ts)
                except Exception as e:  # a variant Triton cannot compile is reported, not fatal
                    line += f"  {kind}: FAILED {type(e).__name__}: {str(e).splitlines()[0][:200]}"
                    continue
                if kind not in ref:
                    ref[kind] = r
                a = ref[kind]
                agree = np.mean((a[0] == r[0]) & (any_hit | ~a[0] | (a[2] == r[2])))
                line += f"  {kind} {len(rays[0]) / dt / 1e6:8.1f} (hit {r[0].mean():.2f}, agree {agree:.6f}, first {tc:.1f} s)"
            print(line, flush=True)


if __name__ == "__main__":
    main()
