"""Path-tracing throughput: samples per second of jaxrt's path tracer beside Mitsuba 3's.

    python benchmarks/path.py                                  # 64^2, 4 spp per pass, depth 4
    python benchmarks/path.py --size 256 --spp 16 --passes 5   # e.g. on a GPU
    python benchmarks/path.py --scenes cornell --mitsuba-variant scalar_rgb
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/path.py --devices 2   # 2 CPU devices

Scenes (Stanford meshes need $JAXRT_DATA):
  cornell  scenes/cornell_area.toml: the Cornell box lit by its emissive ceiling quad (all Lambert).
  dragon   the Stanford dragon (copper Cook-Torrance) on a plane (blue Phong) lit only by a
           lat-long environment map synthesised here (a sky gradient with a sun blob, 64x128, written
           to a temporary EXR; nothing binary is committed).

jaxrt: compile time of one pass (`jaxrt.integrators.path.render_host`), then the median wall time of `passes`
passes (different random streams), each to its image on the host as Mitsuba's; samples/s = width·height·spp / time.
Mitsuba 3 renders the same triangles, camera, resolution, spp and depth (its max_depth = ours + 1)
with its `path` integrator, after a warm-up render (LLVM kernel compilation), timed the same way.
Materials: the Cornell box is identical (two-sided diffuse). For the dragon Mitsuba has no Cook-
Torrance/Phong with these exact parameterisations, so it gets the nearest plugins (roughconductor
Beckmann with alpha = m, roughplastic for the floor): the timing compares the same light transport
workload, not identical images. Mitsuba's variant: llvm_ad_rgb (CPU, JIT-compiled, vectorised), or
scalar_rgb when llvm fails (each Mitsuba run is a child process, so an LLVM abort only costs the
fallback); the variant that ran is printed. Mitsuba's path integrator needs a libLLVM newer than
Debian 12's default 15 (`apt-get install libllvm19`); `_mitsuba.use_libllvm` finds it, or set
DRJIT_LIBLLVM_PATH. Runs unchanged on a GPU (JAX
picks the backend; Mitsuba stays on the CPU).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from jaxrt import image  # noqa: E402
from jaxrt.integrators import path as P# noqa: E402
from jaxrt import scene as S  # noqa: E402
from _mitsuba import use_libllvm  # noqa: E402


def sky_exr(path: Path, h: int = 64, w: int = 128) -> Path:
    """A synthetic lat-long sky: blue gradient above, dim ground below, a small bright sun."""
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    theta, phi = v * np.pi, u * 2 * np.pi
    sky = np.where(theta[:, None, None] < np.pi / 2,
                   (0.4 + 0.6 * np.cos(theta))[:, None, None] * np.array([0.45, 0.6, 1.0]),
                   np.array([0.12, 0.1, 0.08]))
    tex = np.broadcast_to(sky, (h, w, 3)).copy()
    # sun at θ = 35°, φ = 60°: an angular radius of ~3°
    st, sp = np.radians(35.0), np.radians(60.0)
    d = np.stack([np.sin(phi)[None] * np.sin(theta)[:, None], np.cos(theta)[:, None] * np.ones((1, w)),
                  -np.cos(phi)[None] * np.sin(theta)[:, None]], -1)
    s = np.array([np.sin(sp) * np.sin(st), np.cos(st), -np.cos(sp) * np.sin(st)])
    tex[(d @ s) > np.cos(np.radians(3.0))] = [400.0, 380.0, 340.0]
    image.write_exr(path, tex.astype(np.float32))
    return path


def dragon_dict(exr: Path, mesh: str) -> dict:
    return {
        "camera": {"position": [0.0, 1.3, 3.4], "look_at": [0.0, 0.75, 0.0], "vfov": 35.0},
        "render": {"integrator": "path"},
        "environment": {"file": str(exr)},
        "materials": {
            "copper": {"model": "cook_torrance", "rho_d": [0.04, 0.02, 0.01], "rho_s": [0.95, 0.64, 0.54],
                       "m": 0.2, "eta": 8.0},
            "blue_plastic": {"model": "phong", "rho_d": [0.05, 0.12, 0.45], "rho_s": 0.25, "s": 80.0},
        },
        "objects": [
            {"mesh": mesh, "scale": 8.0, "translate": [0.05, -0.42, 0.0], "rotate": [0.0, 20.0, 0.0],
             "material": "copper"},
            {"primitive": "plane", "size": [30.0, 30.0], "material": "blue_plastic"},
        ],
    }


def load(name: str, size: int, spp: int, depth: int, exr: Path, mesh: str):
    ov = {"camera.width": size, "camera.height": size, "render.spp": spp, "render.max_depth": depth}
    if name == "cornell":
        return S.load("cornell_area", overrides=ov)
    return S.load(dragon_dict(exr, mesh), overrides=ov)


def bench_jaxrt(sc, passes: int, devices: int = 1) -> dict:
    if devices > 1:
        return bench_jaxrt_devices(sc, passes, devices)
    # A pass is timed as Mitsuba's is (`bench_mitsuba`): from the call to the pass's image on the host
    # (`path.render_host`: the spp samples of each pixel averaged on the device). The per-sample
    # radiance (H·W·spp·3 floats) is not copied: reading 50 MB on the host between passes left the
    # GPU idle long enough to slow the next pass (one NVIDIA H200, Cornell box 512², 16 spp: 14.9 ms
    # a pass after such a read against 12.4 ms back to back).
    # (`path.render_host`: on a GPU the program writes the image to page-locked host memory itself)
    t0 = time.perf_counter()
    P.render_host(sc, 0, jitter=True)
    compile_s = time.perf_counter() - t0
    times, means = [], []
    for i in range(1, passes + 1):
        s = time.perf_counter()
        a = P.render_host(sc, i, jitter=True)
        times.append(time.perf_counter() - s)
        assert np.all(np.isfinite(a))
        means.append(a.mean())
    return dict(compile_s=compile_s, pass_s=statistics.median(times), mean=float(np.mean(means)))


def bench_jaxrt_devices(sc, passes: int, devices: int) -> dict:
    """A pass split into tiles over `devices` devices (`jaxrt.render_tiles.accumulate`, the plan kept
    across passes). On a CPU these are virtual devices
    (XLA_FLAGS=--xla_force_host_platform_device_count=N, set before the process starts): XLA:CPU runs
    one program's loops on one thread (only the Embree calls use the pool's threads), and each
    device runs its own program, so N devices can keep N cores busy. compile_s covers the compiles,
    the plan's timed passes (`render_tiles.TIMED_PASSES`) and a first pass of its schedule; pass_s is
    the median of `passes` passes after them."""
    from jaxrt import render_tiles

    if len(jax.devices()) < devices:
        raise SystemExit(f"--devices {devices}: this process has {len(jax.devices())} devices (on a CPU set "
                         f"XLA_FLAGS=--xla_force_host_platform_device_count={devices})")
    devs = jax.devices()[:devices]
    t0 = time.perf_counter()
    st, plan = render_tiles.accumulate(sc, devices=devs, return_plan=True)
    # the timed passes, then one pass of the scheduled queue (`render_tiles.accumulate`: a second program)
    for _ in range(render_tiles.TIMED_PASSES):
        st, plan = render_tiles.accumulate(sc, st, use_plan=plan, return_plan=True)
    jax.block_until_ready(st.total)
    compile_s = time.perf_counter() - t0
    times, means = [], []
    for _ in range(passes):
        before = np.asarray(st.total)
        s = time.perf_counter()
        st, plan = render_tiles.accumulate(sc, st, use_plan=plan, return_plan=True)
        jax.block_until_ready(st.total)
        times.append(time.perf_counter() - s)
        img = (np.asarray(st.total) - before) / sc.settings.spp
        assert np.all(np.isfinite(img))
        means.append(img.mean())
    return dict(compile_s=compile_s, pass_s=statistics.median(times), mean=float(np.mean(means)))


def mitsuba_scene(mi, sc, name: str, exr: Path, tmp: Path, spp: int, depth: int):
    v = np.asarray(sc.geometry.vertices, np.float64)
    faces = np.asarray(sc.geometry.faces)
    mat = np.asarray(sc.geometry.material)
    cam = sc.camera
    T = mi.ScalarTransform4f
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": depth + 1},
         "sensor": {"type": "perspective", "fov": float(cam.vfov), "fov_axis": "y",
                    "to_world": T().look_at(origin=np.asarray(cam.position).tolist(),
                                            target=np.asarray(cam.look_at).tolist(), up=np.asarray(cam.up).tolist()),
                    "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                    "sampler": {"type": "independent", "sample_count": spp}}}
    if name == "dragon":
        d["env"] = {"type": "envmap", "filename": str(exr)}
    import trimesh

    for m, mname in enumerate(sc.materials.names):
        sel = faces[mat == m]
        if not len(sel):
            continue
        ply = tmp / f"{name}_{mname}.ply"
        used = np.unique(sel)
        remap = np.zeros(len(v), np.int64)
        remap[used] = np.arange(len(used))
        trimesh.Trimesh(v[used], remap[sel], process=False).export(ply)
        k, row = int(sc.materials.model_id[m]), int(sc.materials.row[m])
        p = {key: np.asarray(val[row], np.float64) for key, val in sc.materials.params[k].items()}
        model = sc.materials.models[k]
        if model == "lambert":
            bsdf = {"type": "twosided", "bsdf": {"type": "diffuse",
                                                 "reflectance": {"type": "rgb", "value": p["rho_d"].tolist()}}}
        elif model == "cook_torrance":
            bsdf = {"type": "roughconductor", "distribution": "beckmann", "alpha": float(p["m"]),
                    "specular_reflectance": {"type": "rgb", "value": p["rho_s"].tolist()}}
        else:
            bsdf = {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.15,
                    "diffuse_reflectance": {"type": "rgb", "value": p["rho_d"].tolist()}}
        ent = {"type": "ply", "filename": str(ply), "face_normals": True, "bsdf": bsdf}
        em = np.asarray(sc.area_lights.emission[m], np.float64)
        if em.max() > 0:
            ent["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": em.tolist()}}
        d[f"mesh_{mname}"] = ent
    return mi.load_dict(d)


def bench_mitsuba(mi, scene, spp: int, passes: int) -> dict:
    img = np.asarray(mi.render(scene, spp=spp, seed=0))  # warm-up (LLVM kernel compilation)
    times, means = [], []
    for i in range(1, passes + 1):
        s = time.perf_counter()
        img = np.asarray(mi.render(scene, spp=spp, seed=i))
        times.append(time.perf_counter() - s)
        means.append(img[..., :3].mean())
    return dict(pass_s=statistics.median(times), mean=float(np.mean(means)))


def mitsuba_subprocess(variant: str, args, name: str, exr: Path) -> dict | None:
    """Time Mitsuba in a child process: an LLVM back-end fault (e.g. drjit's libLLVM failing to
    select an instruction) aborts the whole process, which must not take jaxrt's numbers with it."""
    import json
    import subprocess

    cmd = [sys.executable, __file__, "--mitsuba-child", name, "--mitsuba-variant", variant, "--exr", str(exr),
           "--size", str(args.size), "--spp", str(args.spp), "--depth", str(args.depth),
           "--passes", str(args.passes), "--mesh", args.mesh]
    res = subprocess.run(cmd, capture_output=True, text=True)
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode != 0 or not lines:
        err = [ln for ln in res.stderr.splitlines() if "ERROR" in ln or "Error" in ln][:1]
        print(f"  Mitsuba {variant} failed on {name} (exit {res.returncode}: {err[0] if err else '?'})")
        return None
    return json.loads(lines[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["cornell", "dragon"], choices=["cornell", "dragon"])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4, help="samples per pixel per pass")
    ap.add_argument("--depth", type=int, default=4, help="max_depth (scattering events; Mitsuba's is +1)")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--mesh", default="dragon", help="dragon mesh data name (dragon, dragon_res2, dragon_res4)")
    ap.add_argument("--mitsuba-variant", default="llvm_ad_rgb")
    ap.add_argument("--devices", type=int, default=1,
                    help="split each jaxrt pass over this many devices (render_tiles.accumulate; on a CPU "
                         "virtual devices: XLA_FLAGS=--xla_force_host_platform_device_count=N)")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--mitsuba-child", help=argparse.SUPPRESS)
    ap.add_argument("--exr", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.mitsuba_child:
        import json

        use_libllvm()
        import mitsuba as mi

        mi.set_variant(args.mitsuba_variant)
        name = args.mitsuba_child
        sc = load(name, args.size, args.spp, args.depth, Path(args.exr), args.mesh)
        with tempfile.TemporaryDirectory() as tmp:
            m = bench_mitsuba(mi, mitsuba_scene(mi, sc, name, Path(args.exr), Path(tmp), args.spp, args.depth),
                              args.spp, args.passes)
        print(json.dumps(dict(m, variant=mi.variant(), version=mi.__version__)))
        return 0

    dev = jax.devices()[0]
    print(f"backend: {jax.default_backend()}  device: {dev.device_kind}  jax {jax.__version__}")
    n = args.size * args.size * args.spp
    print(f"{args.size}x{args.size}, {args.spp} spp per pass, max_depth {args.depth}, median of {args.passes} passes"
          + (f", jaxrt on {args.devices} devices" if args.devices > 1 else ""))
    print(f"{'scene':8s} {'tris':>8s} {'build s':>8s} {'compile s':>9s} {'pass s':>8s} {'Msamples/s':>10s} "
          f"{'mean':>8s}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        exr = sky_exr(tmp / "sky.exr")
        for name in args.scenes:
            t0 = time.perf_counter()
            sc = load(name, args.size, args.spp, args.depth, exr, args.mesh)
            build = time.perf_counter() - t0
            r = bench_jaxrt(sc, args.passes, args.devices)
            line = (f"{name:8s} {sc.geometry.faces.shape[0]:8d} {build:8.2f} {r['compile_s']:9.2f} "
                    f"{r['pass_s']:8.3f} {n / r['pass_s'] / 1e6:10.4f} {r['mean']:8.4f}")
            print(line, flush=True)
            if not args.no_mitsuba:
                for variant in dict.fromkeys([args.mitsuba_variant, "scalar_rgb"]):
                    m = mitsuba_subprocess(variant, args, name, exr)
                    if m is not None:
                        print(f"{'':8s} Mitsuba {m['version']} {m['variant']}: pass {m['pass_s']:.3f} s, "
                              f"{n / m['pass_s'] / 1e6:.4f} Msamples/s, mean {m['mean']:.4f}; "
                              f"jaxrt/Mitsuba time {r['pass_s'] / m['pass_s']:.1f}x", flush=True)
                        break
    return 0


if __name__ == "__main__":
    sys.exit(main())
