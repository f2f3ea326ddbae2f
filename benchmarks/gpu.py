"""The GPU benchmark in one call: build, check and time rays and Whitted frames on this backend.

    JAXRT_DATA=../shared/data/meshes python benchmarks/gpu.py                # GPU: 1024², both traversals
    JAXRT_DATA=../shared/data/meshes python benchmarks/gpu.py --cpu          # CPU: small sizes, + Embree
    python benchmarks/gpu.py --res 512 --repeats 3 --impls pallas --json out.json

Rays (bunny, full dragon; camera framing the model, rays in 16x16 tile order): BVH build s, compile s
(lower + compile of the jitted intersect), primary (closest hit) and shadow (any hit from the primary
hits to a point light) Mrays/s for each traversal implementation (`bvh.intersect(..., impl=...)`:
"xla" = the pure-JAX loop, "pallas" = the Triton kernel of jaxrt.accel.traverse_pallas, "cpu" = the C++ kernel of
jaxrt.accel.traverse_cpu; default xla pallas on GPU, cpu xla on CPU), the fraction of rays on
which the implementations agree, and on CPU Embree's Mrays/s on the same rays in the same run; the
shadow rays are timed twice, from the surface and from the light end (`bvh.occluded(from_end=True)`),
and again from the hits of a --shadow-res² camera (default 2x res on GPU: ~1M shadow rays for the
dragon, the launch size of OptiX's quoted figures).
--builders times the rays on several trees (`bvh.build(builder=, layout=)`, e.g. `lbvh sah/dfs`).
Frames (bunny, dragon, showcase scenes, `render.frame` = Whitted: point lights, shadows, mirror/glass
bounces): compile s, frame ms, fps, GPU peak memory, and that changing the light and the camera position
does not recompile. Check: each scene at --check-size² on the default device vs the CPU backend
(max |diff| / max and the fraction of pixels differing > 1e-3 of the max; on a CPU-only run both
sides are the CPU). Times are medians over
--repeats calls after a warm-up. Nothing is written except --json. Exit status 1 if a check fails.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from jaxrt import integrators
from jaxrt.accel import bvh
from jaxrt.geometry import data
from jaxrt.geometry import mesh  # noqa: E402
from jaxrt import scene as S  # noqa: E402
from rays import camera_rays, embree_scene, median_time  # noqa: E402


def peak_gb(dev):
    st = dev.memory_stats() if hasattr(dev, "memory_stats") else None
    return (st or {}).get("peak_bytes_in_use", float("nan")) / 2**30


SHADOW_EPS = np.float32(1e-4)  # shadow segments are traced over [eps, 1 - eps] of their length


def shadow_segments(o, d, prim, t, light):
    """Shadow segments from the hits (prim, t) of rays (o, d) to the light: origins and directions (to
    the light, unnormalised), numpy float32, one per hit."""
    ok = prim >= 0
    p = o[ok] + t[ok, None] * d[ok]
    return p.astype(np.float32), (light[None] - p).astype(np.float32)


def segment_args(so, sd):
    """(origins, directions, tmin, tmax) device arrays for `bvh.occluded` over [eps, 1 - eps]."""
    return jnp.asarray(so), jnp.asarray(sd), jnp.full(len(so), SHADOW_EPS), jnp.full(len(so), 1 - SHADOW_EPS)


def bench_rays(name, res, impls, repeats, embree, builder=None, shadow_res=None):
    m = mesh.load(data.find(name))
    kw = {} if builder is None else dict(zip(("builder", "layout"), builder.split("/")))  # "sah/dfs"
    t = time.perf_counter()
    tree = jax.block_until_ready(bvh.build(m.vertices, m.faces, **kw))
    t_build = time.perf_counter() - t
    st = tree.stats
    print(f"  tree {name} builder {builder or 'default'}: build {t_build:.3f} s, {st}", flush=True)
    o, d, light = camera_rays(m.vertices, res)
    od, dd = jnp.asarray(o), jnp.asarray(d)
    z = jnp.zeros(len(o), jnp.float32)
    rows, ref, ref_big = [], None, None
    # Shadow rays from the hits of a shadow_res² camera: ~4x as many at 2x the resolution, a launch the
    # size of the 1M-ray launches OptiX's figures are quoted for (a 231k-ray launch is partly latency).
    big = None
    if shadow_res:
        ob, db, _ = camera_rays(m.vertices, shadow_res)
        hb = bvh.intersect(tree, jnp.asarray(ob), jnp.asarray(db))
        big = segment_args(*shadow_segments(ob, db, np.asarray(hb.prim), np.asarray(hb.t), light))
    for impl in impls:
        f_hit = jax.jit(lambda tr, o_, d_, lo, impl=impl: bvh.intersect(tr, o_, d_, lo, jnp.inf, impl=impl))
        f_occ = jax.jit(lambda tr, o_, d_, lo, hi, impl=impl: bvh.occluded(tr, o_, d_, hi, lo, impl=impl))
        f_rev = jax.jit(lambda tr, o_, d_, lo, hi, impl=impl: bvh.occluded(tr, o_, d_, hi, lo, impl=impl,
                                                                          from_end=True))
        t = time.perf_counter()
        c_hit = f_hit.lower(tree, od, dd, z).compile()
        t_compile = time.perf_counter() - t
        hit = jax.tree.map(np.asarray, c_hit(tree, od, dd, z))
        t_prim = median_time(lambda: jax.block_until_ready(c_hit(tree, od, dd, z)), repeats)
        if ref is None:  # shadow rays from the first implementation's hits, so all time the same rays
            so, sd = shadow_segments(o, d, hit.prim, hit.t, light)
            sod, sdd, smin, smax = segment_args(so, sd)
        t = time.perf_counter()
        c_occ = f_occ.lower(tree, sod, sdd, smin, smax).compile()
        t_compile_occ = time.perf_counter() - t
        occ = np.asarray(c_occ(tree, sod, sdd, smin, smax))
        t_shadow = median_time(lambda: jax.block_until_ready(c_occ(tree, sod, sdd, smin, smax)), repeats)
        # the same shadow segments traced from the light end (bvh.occluded(from_end=True))
        occ_rev = np.asarray(f_rev(tree, sod, sdd, smin, smax))
        t_rev = median_time(lambda: jax.block_until_ready(f_rev(tree, sod, sdd, smin, smax)), repeats)
        if ref is None:
            ref = (hit, occ)
        n_big = t_big = t_big_rev = agree_big = float("nan")
        if big is not None:
            n_big = int(big[0].shape[0])
            occ_big = np.asarray(f_rev(tree, *big))
            ref_big = occ_big if ref_big is None else ref_big
            agree_big = float(np.mean(occ_big == ref_big))
            t_big = median_time(lambda: jax.block_until_ready(f_occ(tree, *big)), repeats)
            t_big_rev = median_time(lambda: jax.block_until_ready(f_rev(tree, *big)), repeats)
        row = dict(model=name, res=res, tris=int(m.num_faces), impl=impl, builder=builder or "default",
                   sah_cost=st.sah_cost, build_s=t_build, compile_s=t_compile,
                   compile_occ_s=t_compile_occ, primary=len(o) / t_prim / 1e6, shadow=len(so) / t_shadow / 1e6,
                   shadow_rev=len(so) / t_rev / 1e6, shadow_res=shadow_res or 0, shadow_big_n=n_big,
                   shadow_big=n_big / t_big / 1e6, shadow_big_rev=n_big / t_big_rev / 1e6, agree_big=agree_big,
                   agree_prim=float(np.mean(hit.prim == ref[0].prim)), agree_occ=float(np.mean(occ == ref[1])),
                   agree_rev=float(np.mean(occ_rev == ref[1])))
        rows.append(row)
        print("  rays", {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    if embree:
        esc, t_ebuild = embree_scene(m.vertices, m.faces)
        e_prim = median_time(lambda: esc.run(o, d, output=1), repeats)
        e_occ = median_time(lambda: esc.run(so + sd * SHADOW_EPS, sd * (1 - 2 * SHADOW_EPS), query="OCCLUDED"), repeats)
        row = dict(model=name, res=res, tris=int(m.num_faces), impl="embree", builder="embree", sah_cost=float("nan"),
                   build_s=t_ebuild, compile_s=0.0, shadow_rev=float("nan"), agree_rev=float("nan"),
                   shadow_res=0, shadow_big_n=float("nan"), shadow_big=float("nan"), shadow_big_rev=float("nan"),
                   agree_big=float("nan"),
                   compile_occ_s=0.0, primary=len(o) / e_prim / 1e6, shadow=len(so) / e_occ / 1e6,
                   agree_prim=float(np.mean(esc.run(o, d, output=1)["primID"].astype(np.int64) == ref[0].prim)),
                   agree_occ=float("nan"))
        rows.append(row)
        print("  rays", {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    return rows


def bench_frame(name, res, impl, repeats, dev, overrides=None):
    os.environ["JAXRT_TRAVERSAL"] = impl  # read when the frame function is traced
    t = time.perf_counter()
    scn = S.load(name, overrides={"camera.width": res, "camera.height": res, **(overrides or {})})
    jax.block_until_ready(scn)
    t_build = time.perf_counter() - t
    # A new function object per implementation: jax.jit(integrators.whitted) would share jax's trace
    # cache with the previous implementation's and not re-read JAXRT_TRAVERSAL.
    frame = jax.jit(lambda s: integrators.whitted.whitted(s))
    t = time.perf_counter()
    img = jax.block_until_ready(frame(scn))
    t_compile = time.perf_counter() - t
    t_frame = median_time(lambda: jax.block_until_ready(frame(scn)), repeats)
    finite = bool(np.isfinite(np.asarray(img)).all())
    # New light and camera values must reuse the compiled frame (they are traced, not static).
    pos = np.asarray(scn.lights.position[0])
    cam = np.asarray(scn.camera.position)
    moved = scn.with_light(0, position=pos * 1.01 + 0.1).with_camera(position=cam * 1.02)
    n_before = frame._cache_size()
    jax.block_until_ready(frame(moved))
    recompiled = frame._cache_size() != n_before
    if overrides:
        name = name + "".join(f" {k}={v}" for k, v in overrides.items())
    row = dict(scene=name, res=res, impl=impl, build_s=t_build, compile_s=t_compile, frame_ms=t_frame * 1e3,
               fps=1 / t_frame, peak_gb=peak_gb(dev), finite=finite, recompiled=recompiled)
    print("  frame", {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    os.environ.pop("JAXRT_TRAVERSAL")
    return row


def check_images(names, size):
    """Default device (auto traversal) vs the CPU backend, same process."""
    import jaxrt as R

    dev, cpu = jax.devices()[0], jax.devices("cpu")[0]
    rows = []
    for name in names:
        sc = S.load(name, overrides={"camera.width": size, "camera.height": size})
        a = np.asarray(R.frame(jax.device_put(sc, dev)))
        with jax.default_device(cpu):
            b = np.asarray(R.frame(jax.device_put(sc, cpu)))
        scale = max(float(np.abs(b).max()), 1e-12)
        diff = np.abs(a - b).max(axis=-1) / scale
        row = dict(scene=name, size=size, max_rel=float(diff.max()), frac=float(np.mean(diff > 1e-3)),
                   finite=bool(np.isfinite(a).all()))
        rows.append(row)
        print("  check", row, flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cpu", action="store_true", help="CPU run at small sizes beside Embree (default without a GPU)")
    ap.add_argument("--models", nargs="+", default=["bunny", "dragon"])
    ap.add_argument("--scenes", nargs="+", default=["bunny", "dragon", "showcase"])
    ap.add_argument("--res", type=int, default=None, help="default 1024 on GPU, 256 on CPU")
    ap.add_argument("--impls", nargs="+", default=None, help="default: xla pallas on GPU, cpu xla on CPU")
    ap.add_argument("--frame-impls", nargs="+", default=None, help="default: auto")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--shadow-res", type=int, default=None,
                    help="also time shadow rays from the hits at this resolution (default 2x res on GPU, none on CPU)")
    ap.add_argument("--check-size", type=int, default=64)
    ap.add_argument("--skip", nargs="*", default=[], choices=["rays", "frames", "check"])
    ap.add_argument("--builders", nargs="+", default=[None], help="bvh.build builders for the ray rows, "
                    "BUILDER or BUILDER/LAYOUT, e.g. lbvh sah/dfs (default: bvh.build's; frames always use it)")
    ap.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                    help="scene override for the frame rows, e.g. render.glass_shadows=opaque (repeatable)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    overrides = dict(o.split("=", 1) for o in args.override)
    if args.cpu:  # before anything initialises a backend
        jax.config.update("jax_platforms", "cpu")
    gpu = jax.default_backend() == "gpu"
    dev = jax.devices()[0]
    res = args.res or (1024 if gpu else 256)
    impls = args.impls or (["xla", "pallas"] if gpu else ["cpu", "xla"])
    print(f"# device {dev.device_kind} ({jax.default_backend()}), jax {jax.__version__}, cpus {os.cpu_count()}, "
          f"res {res}², repeats {args.repeats}")
    out = dict(device=dev.device_kind, jax=jax.__version__, res=res, rays=[], frames=[], check=[])
    if "rays" not in args.skip:
        for name in args.models:
            for b in args.builders:
                out["rays"] += bench_rays(name, res, impls, args.repeats, embree=not gpu, builder=b,
                                          shadow_res=args.shadow_res or (2 * res if gpu else None))
    if "frames" not in args.skip:
        for name in args.scenes:
            for impl in args.frame_impls or ["auto"]:
                out["frames"].append(bench_frame(name, res, impl, args.repeats, dev, overrides))
    if "check" not in args.skip:
        out["check"] = check_images(args.scenes, args.check_size)
    if args.json:
        from jaxrt.fsutil import atomic_path

        with atomic_path(args.json) as p:
            Path(p).write_text(json.dumps(out, indent=1))

    print(f"\n{dev.device_kind}, {res}²")
    print("| model | tris | builder (SAH cost) | traversal | build s | compile s (hit / occ) | primary Mrays/s "
          "| shadow Mrays/s | shadow from light Mrays/s | shadow / from light, hits at 2x res (rays) "
          "| agree prim / occ / from light / 2x |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in out["rays"]:
        print(f"| {r['model']} | {r['tris']} | {r['builder']} ({r['sah_cost']:.1f}) | {r['impl']} | {r['build_s']:.2f} "
              f"| {r['compile_s']:.1f} / {r['compile_occ_s']:.1f} | {r['primary']:.4g} | {r['shadow']:.4g} "
              f"| {r['shadow_rev']:.4g} | {r['shadow_big']:.4g} / {r['shadow_big_rev']:.4g} ({r['shadow_big_n']}) "
              f"| {r['agree_prim']:.4f} / {r['agree_occ']:.4f} / {r['agree_rev']:.4f} / {r['agree_big']:.4f} |")
    for r in out["rays"]:
        e = next((x for x in out["rays"] if x["model"] == r["model"] and x["impl"] == "embree"), None)
        if e is not None and r["impl"] != "embree":
            print(f"{r['model']} {r['impl']} / Embree: primary {r['primary'] / e['primary']:.3f}x, "
                  f"shadow {r['shadow'] / e['shadow']:.3f}x")
    print("\n| scene | traversal | build s | compile s | frame ms | fps | peak GPU GiB | recompiles on light/camera |")
    print("|---|---|---|---|---|---|---|---|")
    for r in out["frames"]:
        print(f"| {r['scene']} | {r['impl']} | {r['build_s']:.2f} | {r['compile_s']:.1f} | {r['frame_ms']:.2f} | "
              f"{r['fps']:.1f} | {r['peak_gb']:.2f} | {'yes' if r['recompiled'] else 'no'} |")
    print(f"\n| scene | size | max \\|{'GPU' if gpu else 'default'} − CPU\\| / max | pixels > 1e-3 | finite |")
    print("|---|---|---|---|---|")
    for r in out["check"]:
        print(f"| {r['scene']} | {r['size']}² | {r['max_rel']:.2e} | {r['frac']:.3%} | {r['finite']} |")
    bad = [r for r in out["check"] if r["frac"] > 0.01 or not r["finite"]]
    bad += [r for r in out["frames"] if not r["finite"] or r["recompiled"]]
    if bad:
        print("FAILED:", bad)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
