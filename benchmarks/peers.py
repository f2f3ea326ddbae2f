"""jaxrt beside Mitsuba 3 on the same scene descriptions, in one run: the table of frame, ray and
path-tracing times with the ratio time jaxrt / time Mitsuba.

    JAXRT_DATA=… python benchmarks/peers.py                       # CPU, full sizes (slow on 2 cores)
    JAXRT_DATA=… python benchmarks/peers.py --size 256 --path-size 128 --spp 4   # a loaded small CPU
    JAXRT_DATA=… python benchmarks/peers.py --size 1024 --no-mitsuba             # a GPU without Mitsuba

Rows (each a median of --repeats runs after a warm-up run that compiles):
  direct   bunny and dragon at --size², 1 spp: the shipped scene's mesh, plane and camera, every
           surface Lambert ρ = 0.5, its first point light, a black background, max_depth 1 (jaxrt's Whitted frame: one
           camera ray and one shadow ray per pixel); Mitsuba's `direct` integrator with
           emitter_samples 1, bsdf_samples 0 on the same world-space triangles (`_mitsuba.direct_scene`).
  rays     the same scenes' camera rays (--size², pixel centres): closest hit (jaxrt
           `geometry.intersect`, Mitsuba `ray_intersect_preliminary`: t, triangle, barycentrics), the
           hit's surface as well (jaxrt `geometry.intersect` then `geometry.surface`: point, normals,
           tangent, material; Mitsuba `ray_intersect`, its SurfaceInteraction) and shadow rays from
           those hits to the light (jaxrt `bvh.occluded`, Mitsuba `ray_test`), the same rays for both.
  path     `benchmarks/path.py`'s scenes and code: the Cornell box (area light) and the dragon in an
           environment map, --path-size², --spp, --depth; Mitsuba in a child process (path.py's).
           Each jaxrt pass is split over the devices `jaxrt render` uses: on a CPU one per core (at
           most 8; XLA:CPU runs one program's loops on one thread, the device programs run side by
           side; Mitsuba uses every core either way), on a GPU one; --path-devices N sets the count
           (JAX_NUM_CPU_DEVICES sets how many CPU devices there are).

Mitsuba's variant: cuda_ad_rgb where JAX runs on a GPU, else llvm_ad_rgb (its libLLVM found by
`_mitsuba.use_libllvm`); if Mitsuba cannot be imported or the variant not set, jaxrt's rows are
printed alone (as with --no-mitsuba). Stanford meshes need $JAXRT_DATA.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import os
import statistics
import sys
import time
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from jaxrt import _config  # noqa: E402

# the devices a `jaxrt` command's JAX has (on a CPU one per core: `_config.command_defaults`), set
# before JAX is imported, so that the path rows split their passes as `jaxrt render` does
_config.command_defaults()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxrt as R  # noqa: E402
from _mitsuba import direct_scene, use_libllvm  # noqa: E402
from jaxrt import camera as C  # noqa: E402
from jaxrt import scene as S  # noqa: E402
from jaxrt.accel import bvh  # noqa: E402
from jaxrt.integrators.common import sample_order  # noqa: E402


def _load_path_bench():
    # benchmarks/path.py as a module (a plain `import path` would be ambiguous)
    spec = importlib.util.spec_from_file_location("bench_path", HERE / "path.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def median_time(fn, repeats: int) -> float:
    fn()  # warm-up: compilation
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def direct_doc(name: str) -> dict:
    """The shipped scene `name` as a direct-lighting workload: Lambert ρ = 0.5 everywhere (Mitsuba's
    default diffuse), the first light only, max_depth 1."""
    doc = tomllib.loads(S.find_scene(name).read_text())
    doc["materials"] = {"grey": {"model": "lambert", "rho_d": [0.5, 0.5, 0.5]}}
    for ob in doc["objects"]:
        ob["material"] = "grey"
    doc["lights"] = doc["lights"][:1]
    doc.setdefault("render", {})["max_depth"] = 1
    doc["render"]["integrator"] = "whitted"
    doc["render"]["background"] = [0.0, 0.0, 0.0]  # Mitsuba: no emitter, black
    return doc


@functools.lru_cache(maxsize=None)  # the direct and ray rows share a scene (one BVH build)
def load_direct(name: str, size: int):
    base = S.find_scene(name).parent
    return S.load(direct_doc(name), base_dir=base, overrides={"camera.width": size, "camera.height": size})


def camera_rays(scn):
    """The frame's camera rays (pixel centres, the integrator's slot order), unit directions."""
    cam = scn.camera
    o, d = C.generate_rays(cam, 1, 0)
    order, _ = sample_order(cam.height, cam.width, 1)
    d = d[order]
    return o[order], d / jnp.linalg.norm(d, axis=-1, keepdims=True)


class Peer:
    """Mitsuba 3 in this process (direct frames and rays); None-like when unavailable."""

    def __init__(self, gpu: bool):
        self.mi = None
        self.variant = "cuda_ad_rgb" if gpu else "llvm_ad_rgb"
        self.libllvm = None if gpu else use_libllvm()
        try:
            import mitsuba as mi

            mi.set_variant(self.variant)
        except Exception as e:  # noqa: BLE001 -- not installed / no such variant here: jaxrt alone
            print(f"# Mitsuba not used ({type(e).__name__}: {str(e)[:120]})")
            return
        self.mi = mi
        print(f"# Mitsuba {mi.__version__} {self.variant}" + (f", libLLVM {self.libllvm}" if self.libllvm else ""))

    def direct(self, scn, size: int, repeats: int) -> float:
        mi = self.mi
        lt = scn.lights
        scene = direct_scene(mi, scn.geometry.vertices, scn.geometry.faces, scn.camera, lt.position[0],
                             lt.intensity[0], size)
        seed = iter(range(1, 10**6))
        t = median_time(lambda: np.asarray(mi.render(scene, spp=1, seed=next(seed))), repeats)
        return t, float(np.asarray(mi.render(scene, spp=1))[..., :3].mean())

    def rays(self, scn, o, d, so, sd, smin, smax, repeats: int) -> tuple[float, float]:
        import drjit as dr

        mi = self.mi
        size = scn.camera.width
        lt = scn.lights
        scene = direct_scene(mi, scn.geometry.vertices, scn.geometry.faces, scn.camera, lt.position[0],
                             lt.intensity[0], size)
        vec = lambda a, T: T(*(np.ascontiguousarray(a[:, i]) for i in range(3)))  # noqa: E731
        prim = mi.Ray3f(vec(o, mi.Point3f), vec(d, mi.Vector3f))
        # Mitsuba's shadow rays span [0, maxt]: start them at tmin along d
        shadow = mi.Ray3f(vec(so + smin[:, None] * sd, mi.Point3f), vec(sd, mi.Vector3f))
        shadow.maxt = mi.Float(np.ascontiguousarray(smax - smin))
        dr.eval(prim, shadow)

        def hit():
            pi = scene.ray_intersect_preliminary(prim)
            dr.eval(pi.t, pi.prim_index, pi.shape_index, pi.prim_uv)
            dr.sync_thread()

        def occ():
            m = scene.ray_test(shadow)
            dr.eval(m)
            dr.sync_thread()

        def surf():
            si = scene.ray_intersect(prim)
            dr.eval(si)
            dr.sync_thread()

        return median_time(hit, repeats), median_time(occ, repeats), median_time(surf, repeats)


def bench_direct(name: str, size: int, repeats: int, peer: Peer | None) -> dict:
    scn = load_direct(name, size)
    compiled = R.frame.lower(scn).compile()
    img = np.asarray(compiled(scn))
    assert np.all(np.isfinite(img)), f"{name}: non-finite pixels"
    r = dict(jaxrt=median_time(lambda: compiled(scn).block_until_ready(), repeats), mean=float(img.mean()))
    if peer is not None and peer.mi is not None:
        r["mitsuba"], r["mitsuba_mean"] = peer.direct(scn, size, repeats)
    return r


def bench_rays(name: str, size: int, repeats: int, peer: Peer | None) -> dict:
    scn = load_direct(name, size)
    geo = scn.geometry
    o, d = camera_rays(scn)
    f_hit = jax.jit(lambda g, o, d: g.intersect(o, d))

    @jax.jit
    def f_surf(g, o, d):
        h = g.intersect(o, d)
        return h, g.surface(h.prim, h.u, h.v)

    hit = f_hit(geo, o, d)
    ok = np.asarray(hit.prim) >= 0
    on, dn, tn = np.asarray(o), np.asarray(d), np.asarray(hit.t)
    p = on[ok] + tn[ok, None] * dn[ok]
    to_light = np.asarray(scn.lights.position[0])[None] - p
    dist = np.linalg.norm(to_light, axis=1)
    sd = (to_light / dist[:, None]).astype(np.float32)
    so = p.astype(np.float32)
    smin, smax = (1e-4 * dist).astype(np.float32), ((1 - 1e-4) * dist).astype(np.float32)
    f_occ = jax.jit(lambda tree, o, d, tmin, tmax: bvh.occluded(tree, o, d, tmax, tmin))
    args = tuple(jnp.asarray(x) for x in (so, sd, smin, smax))
    r = dict(n=len(on), n_shadow=len(so),
             jaxrt=(median_time(lambda: jax.block_until_ready(f_hit(geo, o, d)), repeats),
                    median_time(lambda: jax.block_until_ready(f_occ(geo.tree, *args)), repeats),
                    median_time(lambda: jax.block_until_ready(f_surf(geo, o, d)), repeats)))
    if peer is not None and peer.mi is not None:
        r["mitsuba"] = peer.rays(scn, on, dn, so, sd, smin, smax, repeats)
    return r


def bench_path(pb, names, args, use_mitsuba: bool, variant: str) -> dict:
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        exr = pb.sky_exr(Path(tmp) / "sky.exr")
        for name in names:
            sc = pb.load(name, args.path_size, args.spp, args.depth, exr, args.mesh)
            r = dict(jaxrt=pb.bench_jaxrt(sc, args.passes, args.path_devices))
            if use_mitsuba:
                ns = argparse.Namespace(size=args.path_size, spp=args.spp, depth=args.depth, passes=args.passes,
                                        mesh=args.mesh)
                m = pb.mitsuba_subprocess(variant, ns, name, exr)
                if m is not None:
                    r["mitsuba"] = m
            out[name] = r
            print(f"# path {name}: {r}", flush=True)
    return out


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:.1f} ms" if s >= 0.01 else f"{s * 1e3:.2f} ms"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", nargs="+", default=["direct", "rays", "path"], choices=["direct", "rays", "path"])
    ap.add_argument("--models", nargs="+", default=["bunny", "dragon"], help="scenes of the direct rows")
    ap.add_argument("--ray-models", nargs="+", default=None, help="scenes of the ray rows (default: bunny on "
                    "the CPU, dragon on a GPU)")
    ap.add_argument("--size", type=int, default=512, help="direct frames and camera rays: size² pixels")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--paths", nargs="+", default=["cornell", "dragon"], choices=["cornell", "dragon"])
    ap.add_argument("--path-size", type=int, default=512)
    ap.add_argument("--path-devices", type=int, default=None,
                    help="path tracing: split each jaxrt pass over this many devices (`path.py --devices`); "
                         "default: on a CPU every device, one per core as in `jaxrt render` "
                         "(JAX_NUM_CPU_DEVICES=1 for one), on a GPU 1 (Mitsuba's variant uses one GPU)")
    ap.add_argument("--spp", type=int, default=16, help="path tracing: samples per pixel per pass")
    ap.add_argument("--depth", type=int, default=4, help="path tracing: max_depth (Mitsuba's is +1)")
    ap.add_argument("--passes", type=int, default=3, help="path tracing: timed passes (median)")
    ap.add_argument("--mesh", default="dragon", help="the path-traced dragon's mesh (dragon, dragon_res2, ...)")
    ap.add_argument("--no-mitsuba", action="store_true")
    args = ap.parse_args(argv)
    if args.path_devices is None:
        args.path_devices = len(jax.devices()) if jax.default_backend() == "cpu" else 1

    gpu = jax.default_backend() == "gpu"
    dev = jax.devices()[0]
    load = os.getloadavg()
    print(f"# backend {jax.default_backend()}, device {dev.device_kind}, jax {jax.__version__}, cpus {os.cpu_count()}, "
          f"load {load[0]:.1f}/{load[1]:.1f}/{load[2]:.1f}")
    peer = None if args.no_mitsuba else Peer(gpu)
    use_mi = peer is not None and peer.mi is not None
    where = dev.device_kind if gpu else f"{os.cpu_count()}-core CPU"
    rows = []  # (workload, jaxrt, mitsuba or None, ratio or None)

    def add(workload, t_j, t_m, unit=fmt_ms):
        rows.append((workload, unit(t_j), unit(t_m) if t_m is not None else "", f"{t_j / t_m:.2f}" if t_m else ""))
        print("  ", " | ".join(rows[-1]), flush=True)

    if "direct" in args.rows:
        for name in args.models:
            r = bench_direct(name, args.size, args.repeats, peer)
            add(f"{where}, {name} {args.size}², direct light + shadow ray, diffuse, 1 spp", r["jaxrt"],
                r.get("mitsuba"))
            peer_mean = f", Mitsuba {r['mitsuba_mean']:.5f}" if "mitsuba_mean" in r else ""
            print(f"#   image means: jaxrt {r['mean']:.5f}{peer_mean}")
    if "rays" in args.rows:
        for name in args.ray_models or (["dragon"] if gpu else ["bunny"]):
            r = bench_rays(name, args.size, args.repeats, peer)
            (hj, oj, sj), m = r["jaxrt"], r.get("mitsuba")
            add(f"{where}, {name} {args.size}² camera rays ({r['n']:,}), closest hit", hj, m and m[0])
            add(f"{where}, {name}: the same with the hit's surface (jaxrt intersect + surface, Mitsuba "
                "ray_intersect)", sj, m and m[2])
            add(f"{where}, {name}: shadow rays from those hits ({r['n_shadow']:,}), any hit", oj, m and m[1])
            rate = lambda n: lambda t: f"{n / t / 1e6:.1f} Mrays/s"  # noqa: E731
            rows.append((f"{where}, {name}: camera rays, rate", rate(r["n"])(hj), rate(r["n"])(m[0]) if m else "", ""))
            rows.append((f"{where}, {name}: camera rays with the surface, rate", rate(r["n"])(sj),
                         rate(r["n"])(m[2]) if m else "", ""))
    if "path" in args.rows:
        pb = _load_path_bench()
        variant = peer.variant if use_mi else None
        res = bench_path(pb, args.paths, args, use_mi, variant)
        n = args.path_size ** 2 * args.spp
        label = {"cornell": "Cornell box (area light)", "dragon": "dragon in an environment map"}
        for name, r in res.items():
            tj = r["jaxrt"]["pass_s"]
            m = r.get("mitsuba")
            tm = m["pass_s"] if m else None
            add(f"{where}, path tracing {args.path_size}², {args.spp} spp, depth {args.depth}: {label[name]}", tj, tm)
            rows.append((f"{where}, {label[name]}: rate, image mean",
                         f"{n / tj / 1e6:.3f} Msamples/s, {r['jaxrt']['mean']:.4f}",
                         f"{n / tm / 1e6:.3f} Msamples/s, {m['mean']:.4f}" if m else "", ""))
    mname = f"Mitsuba 3 ({peer.variant})" if use_mi else "Mitsuba 3 (not run)"
    print(f"\nmedians of {args.repeats} (frames, rays) / {args.passes} (path passes) after a warm-up; "
          f"jaxrt's path passes on {args.path_devices} {jax.default_backend()} device(s); "
          f"load at the end {os.getloadavg()[0]:.1f}\n")
    print(f"| workload | jaxrt | {mname} | ratio (time jaxrt / time Mitsuba) |")
    print("|---|---|---|---|")
    for w, j, m, q in rows:
        print(f"| {w} | {j} | {m} | {q} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
