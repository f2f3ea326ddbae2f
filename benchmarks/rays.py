"""Ray-tracing throughput of jaxrt's BVH (and Embree on CPU, same rays, same run).

    JAXRT_DATA=../shared/data/meshes python benchmarks/rays.py [--models bunny dragon] [--res 512 1024]
        [--repeats 5] [--no-embree] [--check]

Prints, per model and resolution: build time, compile time, primary (closest hit) Mrays/s, shadow
(any hit towards a point light) Mrays/s, incoherent (random directions from the primary hit points)
Mrays/s, and mean / max traversal steps per ray; on CPU also Embree's Mrays/s on the same rays and
jaxrt/Embree ratios. Times are medians over --repeats runs after one warm-up; Mrays/s counts rays
traced (shadow and incoherent rays start at the primary hits, so there are fewer than pixels).
--check compares a sample of rays with a float64 brute-force intersector.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from jaxrt.accel import bvh
from jaxrt.geometry import data
from jaxrt.geometry import mesh  # noqa: E402


def camera_rays(vertices: np.ndarray, res: int, tile: int = 16):
    """Pinhole camera framing the model (bounding sphere fills the frame), rays in tile order."""
    lo, hi = vertices.min(0), vertices.max(0)
    c = (lo + hi) / 2
    r = np.linalg.norm(hi - lo) / 2
    fov = np.radians(40.0)
    eye = c + np.array([0.3, 0.25, 1.0]) / np.linalg.norm([0.3, 0.25, 1.0]) * (r / np.sin(fov / 2))
    fwd = (c - eye) / np.linalg.norm(c - eye)
    right = np.cross(fwd, [0, 1, 0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    ys, xs = np.mgrid[0:res, 0:res]
    # tile order: tiles of tile x tile pixels, row-major within a tile
    ty, tx = ys // tile, xs // tile
    key = ((ty * (res // tile) + tx) * tile + ys % tile) * tile + xs % tile
    perm = np.argsort(key.ravel())
    px = (xs.ravel()[perm] + 0.5) / res * 2 - 1
    py = 1 - (ys.ravel()[perm] + 0.5) / res * 2
    s = np.tan(fov / 2)
    d = fwd[None] + px[:, None] * s * right[None] + py[:, None] * s * up[None]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape)
    light = c + np.array([-1.0, 2.0, 1.5]) * r * 2
    return o.astype(np.float32), d.astype(np.float32), light


def median_time(fn, repeats):
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def embree_scene(vertices: np.ndarray, faces: np.ndarray):
    """An Embree scene of the mesh (built now; Embree builds lazily) and its build time [s]."""
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    t = time.perf_counter()
    esc = rtcs.EmbreeScene()
    TriangleMesh(esc, vertices.astype(np.float32), faces.astype(np.int32))
    esc.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # Embree builds lazily
    return esc, time.perf_counter() - t


def brute_force(tri: np.ndarray, o: np.ndarray, d: np.ndarray, tmin: np.ndarray):
    """Closest hit in float64 (Moller-Trumbore, all rays x all triangles)."""
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    bt = np.full(len(o), np.inf)
    bp = np.full(len(o), -1)
    for i in range(len(o)):
        p = np.cross(d[i], e2)
        det = np.einsum("ij,ij->i", e1, p)
        s = o[i] - v0
        inv = 1.0 / np.where(det == 0, 1e-300, det)
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = q @ d[i] * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        t = np.where((det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= tmin[i]), t, np.inf)
        j = int(np.argmin(t))
        if np.isfinite(t[j]):
            bt[i], bp[i] = t[j], j
    return bt, bp


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="+", default=["bunny", "dragon"])
    ap.add_argument("--res", nargs="+", type=int, default=[512, 1024])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-embree", action="store_true")
    ap.add_argument("--check", type=int, default=0, help="rays to check against float64 brute force")
    ap.add_argument("--lanes", type=int, default=None)
    ap.add_argument("--steps", type=int, default=None)
    args = ap.parse_args(argv)
    backend = jax.default_backend()
    dev = jax.devices()[0]
    print(f"# backend {backend}, device {getattr(dev, 'device_kind', dev)}, jax {jax.__version__}, "
          f"cpus {os.cpu_count()}, lanes {args.lanes or 'default'}, steps/iter {args.steps or 'default'}")
    use_embree = backend == "cpu" and not args.no_embree
    rows = []
    kw = dict(lanes=args.lanes, steps_per_iter=args.steps)
    f_hit = jax.jit(lambda tr, o, d, tmin: bvh.intersect(tr, o, d, tmin, jnp.inf, **kw))
    f_occ = jax.jit(lambda tr, o, d, tmin, tmax: bvh.occluded(tr, o, d, tmax, tmin, **kw))
    f_vis = jax.jit(lambda tr, o, d, tmin, tmax, a: bvh.node_visits(tr, o, d, tmin, tmax, any_hit=a, **kw),
                    static_argnums=5)
    for name in args.models:
        t = time.perf_counter()
        m = mesh.load(data.find(name))
        t_load = time.perf_counter() - t
        t = time.perf_counter()
        tree = bvh.build(m.vertices, m.faces)
        jax.block_until_ready(tree)
        t_build = time.perf_counter() - t
        t_build = min(t_build, median_time(lambda: jax.block_until_ready(bvh.build(m.vertices, m.faces)), 2))
        st = tree.stats
        print(f"# {name}: {m.num_faces} triangles, load {t_load:.2f} s, build {t_build:.3f} s, {st}")
        if use_embree:
            esc, t_ebuild = embree_scene(m.vertices, m.faces)
        for res in args.res:
            o, d, light = camera_rays(m.vertices, res)
            n = len(o)
            od, dd = jnp.asarray(o), jnp.asarray(d)
            z = jnp.zeros(n, jnp.float32)
            t = time.perf_counter()
            hit = f_hit(tree, od, dd, z)
            jax.block_until_ready(hit)
            t_compile = time.perf_counter() - t
            t_prim = median_time(lambda: jax.block_until_ready(f_hit(tree, od, dd, z)), args.repeats)
            vis_p = np.asarray(f_vis(tree, od, dd, z, jnp.full(n, jnp.inf), False))
            hit_np = jax.tree.map(np.asarray, hit)
            ok = hit_np.prim >= 0
            p = o[ok] + hit_np.t[ok, None] * d[ok]
            # shadow rays: from the hit points to the light
            so = p.astype(np.float32)
            sd = (light[None] - p).astype(np.float32)
            eps = np.float32(1e-4)
            sod, sdd = jnp.asarray(so), jnp.asarray(sd)
            smin, smax = jnp.full(len(so), eps), jnp.full(len(so), 1 - eps)
            occ = f_occ(tree, sod, sdd, smin, smax)
            jax.block_until_ready(occ)
            t_shadow = median_time(lambda: jax.block_until_ready(f_occ(tree, sod, sdd, smin, smax)), args.repeats)
            vis_s = np.asarray(f_vis(tree, sod, sdd, smin, smax, True))
            # incoherent rays: uniform random directions from the hit points
            rng = np.random.default_rng(0)
            rd = rng.normal(size=so.shape).astype(np.float32)
            rd /= np.linalg.norm(rd, axis=1, keepdims=True)
            rdd = jnp.asarray(rd)
            rmin = jnp.full(len(so), np.float32(1e-5 * np.linalg.norm(m.vertices.max(0) - m.vertices.min(0))))
            rh = f_hit(tree, sod, rdd, rmin)
            jax.block_until_ready(rh)
            t_inc = median_time(lambda: jax.block_until_ready(f_hit(tree, sod, rdd, rmin)), args.repeats)
            vis_i = np.asarray(f_vis(tree, sod, rdd, rmin, jnp.full(len(so), jnp.inf), False))
            row = dict(model=name, res=res, tris=m.num_faces, build_s=t_build, compile_s=t_compile,
                       primary=n / t_prim / 1e6, shadow=len(so) / t_shadow / 1e6, incoherent=len(so) / t_inc / 1e6,
                       vis_p=vis_p.mean(), vis_p_max=vis_p.max(), vis_s=vis_s.mean(), vis_i=vis_i.mean(),
                       hit_frac=ok.mean())
            if use_embree:
                e_prim = median_time(lambda: esc.run(o, d, output=1), args.repeats)
                ed = esc.run(o, d, output=1)
                e_occ = median_time(lambda: esc.run(so + sd * eps, sd * (1 - 2 * eps), query="OCCLUDED"), args.repeats)
                e_inc = median_time(lambda: esc.run(so + rd * float(rmin[0]), rd, output=1), args.repeats)
                row.update(e_build=t_ebuild, e_primary=n / e_prim / 1e6, e_shadow=len(so) / e_occ / 1e6,
                           e_incoherent=len(so) / e_inc / 1e6,
                           e_agree=float(np.mean(ed["primID"].astype(np.int64) == hit_np.prim)))
            if args.check:
                k = min(args.check, n)
                idx = np.random.default_rng(1).choice(n, k, replace=False)
                bt, bp = brute_force(m.vertices.astype(np.float64)[m.faces], o[idx].astype(np.float64),
                                     d[idx].astype(np.float64), np.zeros(k))
                with np.errstate(invalid="ignore"):
                    same = (bp == hit_np.prim[idx]) | (np.abs(bt - hit_np.t[idx]) <= 1e-5 * np.abs(bt))
                row["check"] = f"{int(same.sum())}/{k}"
            rows.append(row)
            print("  ", {k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)

    print()
    hdr = ("| model | res | tris | build s | compile s | primary Mrays/s | shadow Mrays/s | incoherent Mrays/s "
           "| steps/ray prim (max) | shadow | incoh |")
    if use_embree:
        hdr += " Embree build s | Embree prim / shadow / incoh Mrays/s | ratio prim / shadow / incoh |"
    if args.check:
        hdr += " brute-force check |"
    print(hdr)
    print("|" + "---|" * (hdr.count("|") - 1))
    for r in rows:
        s = (f"| {r['model']} | {r['res']}² | {r['tris']} | {r['build_s']:.2f} | {r['compile_s']:.1f} | {r['primary']:.2f} "
             f"| {r['shadow']:.2f} | {r['incoherent']:.2f} | {r['vis_p']:.1f} ({r['vis_p_max']}) | {r['vis_s']:.1f} "
             f"| {r['vis_i']:.1f} |")
        if use_embree:
            s += (f" {r['e_build']:.2f} | {r['e_primary']:.2f} / {r['e_shadow']:.2f} / {r['e_incoherent']:.2f} | "
                  f"{r['primary'] / r['e_primary']:.2f} / {r['shadow'] / r['e_shadow']:.2f} / "
                  f"{r['incoherent'] / r['e_incoherent']:.2f} |")
        if args.check:
            s += f" {r['check']} |"
        print(s)


if __name__ == "__main__":
    main()
