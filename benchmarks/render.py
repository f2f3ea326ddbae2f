"""Frame time and compile time of every shipped scene on the current JAX backend.

    python benchmarks/render.py                          # all scenes at 512^2 and 1024^2
    python benchmarks/render.py --scenes spheres dragon --sizes 512 --repeats 5
    python benchmarks/render.py --mitsuba                # + dragon beside Mitsuba 3 llvm_ad_rgb (CPU)

For each scene and square size: scene build time (mesh load + BVH), compile time of the frame
function (lower + compile), and the median wall time of `repeats` frames after compilation
(block_until_ready). Runs unchanged on CPU and GPU. With --mitsuba, Mitsuba 3's `llvm_ad_rgb`
direct integrator (1 spp, point light, hard shadows) renders the dragon scene's geometry from the
same camera at the first size, timed the same way after a warm-up render, and the ratio is printed.
Stanford-mesh scenes need $JAXRT_DATA.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jaxrt as R  # noqa: E402
from _mitsuba import direct_scene, use_libllvm  # noqa: E402
from jaxrt import scene as S  # noqa: E402

SCENES = ("spheres", "bunny", "dragon", "cornell", "showcase")


def bench_scene(name: str, size: int, repeats: int) -> dict:
    t0 = time.perf_counter()
    scn = S.load(name, overrides={"camera.width": size, "camera.height": size})
    t1 = time.perf_counter()
    compiled = R.frame.lower(scn).compile()
    t2 = time.perf_counter()
    img = compiled(scn)
    img.block_until_ready()
    times = []
    for _ in range(repeats):
        s = time.perf_counter()
        compiled(scn).block_until_ready()
        times.append(time.perf_counter() - s)
    gb = R.trace(scn)  # how many rays the frame traced (per level), for rays/s
    rays = int(np.asarray(gb.active).sum())
    shadow = int(np.asarray(gb.visible.shape[-1]) * np.asarray(gb.active & (gb.prim >= 0)).sum())
    assert np.all(np.isfinite(np.asarray(img))), f"{name}: non-finite pixels"
    return dict(scene=name, size=size, triangles=int(scn.geometry.faces.shape[0]), build_s=t1 - t0,
                compile_s=t2 - t1, frame_s=statistics.median(times), frames=times, rays=rays, shadow_rays=shadow)


def mitsuba_dragon(size: int, repeats: int) -> dict:
    use_libllvm()
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    scn = S.load("dragon", overrides={"camera.width": size, "camera.height": size})
    light = scn.lights
    scene = direct_scene(mi, scn.geometry.vertices, scn.geometry.faces, scn.camera, light.position[0],
                         light.intensity[0], size)
    np.asarray(mi.render(scene, spp=1))  # warm-up: LLVM kernel compilation
    times = []
    for i in range(repeats):
        s = time.perf_counter()
        np.asarray(mi.render(scene, spp=1, seed=i + 1))
        times.append(time.perf_counter() - s)
    return dict(frame_s=statistics.median(times), frames=times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--sizes", nargs="+", type=int, default=[512, 1024])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--mitsuba", action="store_true", help="also time Mitsuba 3 llvm_ad_rgb on the dragon view")
    args = ap.parse_args(argv)

    dev = jax.devices()[0]
    print(f"backend: {jax.default_backend()}  device: {dev.device_kind}  jax {jax.__version__}")
    print(f"{'scene':10s} {'size':>6s} {'tris':>8s} {'build s':>8s} {'compile s':>9s} {'frame ms':>9s} "
          f"{'fps':>7s} {'Mrays/s':>8s}")
    results = []
    for size in args.sizes:
        for name in args.scenes:
            r = bench_scene(name, size, args.repeats)
            results.append(r)
            mrays = (r["rays"] + r["shadow_rays"]) / r["frame_s"] / 1e6
            print(f"{name:10s} {size:6d} {r['triangles']:8d} {r['build_s']:8.2f} {r['compile_s']:9.2f} "
                  f"{r['frame_s'] * 1e3:9.1f} {1 / r['frame_s']:7.2f} {mrays:8.3f}", flush=True)
    if args.mitsuba:
        size = args.sizes[0]
        ours = next((r for r in results if r["scene"] == "dragon" and r["size"] == size), None)
        if ours is None:
            ours = bench_scene("dragon", size, args.repeats)
        m = mitsuba_dragon(size, args.repeats)
        print(f"dragon {size}^2, 1 spp, direct lighting + shadows: jaxrt {ours['frame_s'] * 1e3:.1f} ms, "
              f"Mitsuba 3 llvm_ad_rgb {m['frame_s'] * 1e3:.1f} ms, ratio jaxrt/Mitsuba "
              f"{ours['frame_s'] / m['frame_s']:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
