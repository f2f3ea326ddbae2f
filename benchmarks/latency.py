"""Time to first result: each case as a fresh process, twice (cold = empty cache folder, then warm).

    python benchmarks/latency.py                         # every case (GPU sizes: 1024² dragon, 256² fit)
    python benchmarks/latency.py --quick                 # a CPU: imports and the spheres render, smaller sizes
    python benchmarks/latency.py --cases imports render-spheres fit-bunny --quick
    python benchmarks/latency.py --preview-wiring        # as if the CLI and scenes used jaxrt.cache already
    python benchmarks/latency.py --no-mitsuba            # skip the Mitsuba 3 column
    python benchmarks/latency.py --quick --worker        # also: the warm rows as clients of `jaxrt serve`
    python benchmarks/latency.py --quick --cases fit-cli  # `jaxrt fit TARGET.exr ...` of a 64² target

A case is one process start to exit (files written), timed from outside (wall seconds and the CPU
seconds of the process and its threads, which a loaded shared machine disturbs far less; `--warm-runs N`
reports the medians of N warm processes); the CLI cases are the
commands exactly as typed (`python -m jaxrt.cli` for `jaxrt`, run in an empty folder, so
`jaxrt render` writes its default EXR and PNG); scripted cases also print
their phases (load / compile / first frame, prepare / first fit / solve). `fit-cli` first writes,
untimed and with a cache folder of its own, the scene file at the fit size and a target EXR into the
work folder; then `jaxrt fit target.exr --scene scene.toml ...` is the timed command. Each case runs with
JAXRT_CACHE_DIR set to a new empty folder (cold), then again with the same folder (warm), so the
figures show what a second process reuses, whether or not the commands use `jaxrt.cache` yet.
The native CPU kernels' libraries live in the cache folder too (<JAXRT_CACHE_DIR>/native), so a cold CPU
process also compiles them (two C++ compilations, `jaxrt.cli.render.start_kernels`), as a first-time user's does.
`--preview-wiring` runs a prelude in each process that calls `jaxrt.cache.enable_compilation_cache()`
and routes `jaxrt.geometry.mesh.load` / `jaxrt.accel.bvh.build` through `jaxrt.cache.load_mesh` / `build_bvh`: the
figures the caches give once the CLI and the scene builder call them. The table's last column is
Mitsuba 3 on the same machine where `import mitsuba` works (cuda_ad_rgb on a GPU, else llvm_ad_rgb):
scene load + first render of the same dragon view and resolution, and a 4-parameter `mi.ad.Adam`
fit on the bunny view (rough plastic: diffuse and specular reflectance, roughness, IOR; the nearest
Mitsuba material to the grey Cook-Torrance fit), each as a fresh process, run twice.
Stanford-mesh cases need $JAXRT_DATA; cases that cannot run say why in the table.
`--worker` adds a column: after the warm runs, `jaxrt serve` starts a resident worker on the same
cache folder and the case runs again as fresh client processes (JAXRT_WORKER=use): its first job
(the worker loads what the command needs) and the median of the `--warm-runs` jobs after it. The
CPU seconds of those rows are the client's plus the worker's during the job (read from /proc).
Imports never go through a worker: their rows are the same with and without it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# A prelude for --preview-wiring: the compilation cache on, meshes and BVHs through the array cache.
PREVIEW = """
import jaxrt.accel.bvh as _B, jaxrt.cache as _C, jaxrt.geometry.mesh as _M
_C.enable_compilation_cache()
_load, _build, _inside = _M.load, _B.build, []
def _cached(orig, via):
    def f(*a, **k):
        if _inside:  # the cache's own call of the original
            return orig(*a, **k)
        _inside.append(1)
        try:
            return via(*a, **k)
        finally:
            _inside.pop()
    return f
_M.load = _cached(_load, lambda path, flat=False, name=None: _C.load_mesh(path, flat, name=name))
_B.build = _cached(_build, _C.build_bvh)
"""

PHASES = "LATENCY-PHASES "

DRAGON_FRAME = """
import json, time
t0 = time.perf_counter()
import jax
from jaxrt import scene as S
import jaxrt as R
t1 = time.perf_counter()
scn = S.load("dragon", overrides={{"camera.width": {size}, "camera.height": {size}}})
t2 = time.perf_counter()
f = R.frame.lower(scn).compile()
t3 = time.perf_counter()
f(scn).block_until_ready()
t4 = time.perf_counter()
print("%s" + json.dumps({{"imports": t1 - t0, "load": t2 - t1, "compile": t3 - t2, "frame": t4 - t3}}))
""" % PHASES

FIT_BUNNY = """
import json, time
t0 = time.perf_counter()
import numpy as np
import brdfs
from fitting import setup as scene_fit
from jaxrt.cli.fit import hidden_params
t1 = time.perf_counter()
model = brdfs.get("cook_torrance")
view = scene_fit.variant("bunny", camera={{"width": {size}, "height": {size}}})
setup = scene_fit.prepare([view], model)
t2 = time.perf_counter()
def truth(seed):
    return model.params(**{{k: (np.mean(v) if isinstance(v, list) else v) for k, v in hidden_params(model, seed).items()}})
target = np.asarray(scene_fit.render_with(setup, truth(0)))
t3 = time.perf_counter()
r, _ = scene_fit.fit(None, target, model, setup=setup, rgb=False, starts=1, progress=False)
t4 = time.perf_counter()
target = np.asarray(scene_fit.render_with(setup, truth(1)))
t5 = time.perf_counter()
r2, _ = scene_fit.fit(None, target, model, setup=setup, rgb=False, starts=1, progress=False)
t6 = time.perf_counter()
print("%s" + json.dumps({{"imports": t1 - t0, "prepare": t2 - t1, "target": t3 - t2, "first fit": t4 - t3,
                          "solve": t6 - t5, "iterations": int(r2.iterations)}}))
""" % PHASES

# The fit-cli case's untimed preparation, in its work folder: the scene file at the fit size and a target
# rendered with grey "hidden" parameters, as `fit-bunny` renders its target.
FIT_TARGET = """
import re, sys
from pathlib import Path
import numpy as np
import brdfs
from fitting import setup as scene_fit
from jaxrt import image, scene
from jaxrt.cli.fit import hidden_params
name, size, obj = sys.argv[1], int(sys.argv[2]), sys.argv[3] or None
# the shipped file with its resolution replaced (its meshes are data-registry names, found from anywhere)
text = scene.find_scene(name).read_text()
for key in ("width", "height"):
    text, n = re.subn(rf"(?m)^{key} = \\d+", f"{key} = {size}", text)
    assert n == 1, key
Path("scene.toml").write_text(text)
model = brdfs.get("cook_torrance")
setup = scene_fit.prepare(["scene.toml"], model, object=obj)
truth = model.params(**{k: (np.mean(v) if isinstance(v, list) else v) for k, v in hidden_params(model, 0).items()})
image.write("target.exr", np.asarray(scene_fit.render_with(setup, truth))[0])
"""

MITSUBA_RENDER = """
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import mitsuba as mi
a = json.loads(sys.argv[1])
mi.set_variant(a["variant"])
t1 = time.perf_counter()
T = mi.ScalarTransform4f
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
    "sensor": {"type": "perspective", "fov": a["vfov"], "fov_axis": "y",
               "to_world": T().look_at(origin=a["position"], target=a["look_at"], up=a["up"]),
               "film": {"type": "hdrfilm", "width": a["size"], "height": a["size"], "rfilter": {"type": "box"}},
               "sampler": {"type": "independent", "sample_count": 1}},
    "light": {"type": "point", "position": a["lights"][0]["position"],
              "intensity": {"type": "rgb", "value": a["lights"][0]["intensity"]}},
    "mesh": {"type": "ply", "filename": a["ply"], "face_normals": True, "bsdf": {"type": "diffuse"}},
})
t2 = time.perf_counter()
img = np.asarray(mi.render(scene, spp=1))
t3 = time.perf_counter()
print("%s" + json.dumps({"imports": t1 - t0, "load": t2 - t1, "first render": t3 - t2}))
""" % PHASES

MITSUBA_FIT = """
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import drjit as dr
import mitsuba as mi
a = json.loads(sys.argv[1])
mi.set_variant(a["variant"])
t1 = time.perf_counter()
T = mi.ScalarTransform4f
lights = {f"light{i}": {"type": "point", "position": l["position"], "intensity": {"type": "rgb", "value": l["intensity"]}}
          for i, l in enumerate(a["lights"])}
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "prb", "max_depth": 2},
    "sensor": {"type": "perspective", "fov": a["vfov"], "fov_axis": "y",
               "to_world": T().look_at(origin=a["position"], target=a["look_at"], up=a["up"]),
               "film": {"type": "hdrfilm", "width": a["size"], "height": a["size"], "rfilter": {"type": "box"}},
               "sampler": {"type": "independent", "sample_count": 1}},
    "bunny": {"type": "ply", "filename": a["ply"],
              "bsdf": {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.3, "int_ior": 1.5,
                       "diffuse_reflectance": {"type": "rgb", "value": 0.5},
                       "specular_reflectance": {"type": "rgb", "value": 0.5}}},
    "table": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90) @ T().scale(15.0),
              "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.45, 0.4]}}},
    **lights,
})
t2 = time.perf_counter()
params = mi.traverse(scene)
names = {"d": "bunny.bsdf.diffuse_reflectance.value", "s": "bunny.bsdf.specular_reflectance.value",
         "alpha": "bunny.bsdf.alpha", "eta": "bunny.bsdf.eta"}
truth = {"d": 0.3, "s": 0.6, "alpha": 0.2, "eta": 1.8}
def put(values):
    for k, n in names.items():
        params[n] = mi.Color3f(values[k]) if k in ("d", "s") else values[k]
    params.update()
put({k: mi.Float(v) for k, v in truth.items()})
target = mi.TensorXf(mi.render(scene, params, spp=1, seed=0))
t3 = time.perf_counter()
opt = mi.ad.Adam(lr=0.05)
for k, v in {"d": 0.5, "s": 0.5, "alpha": 0.3, "eta": 1.5}.items():
    opt[k] = mi.Float(v)
for it in range(a["steps"]):
    put(opt)
    img = mi.render(scene, params, spp=1, seed=0)
    loss = dr.mean(dr.square(img - target))
    dr.backward(loss)
    opt.step()
    opt["d"] = dr.clip(opt["d"], 0.0, 1.0)
    opt["s"] = dr.clip(opt["s"], 0.0, 1.0)
    opt["alpha"] = dr.clip(opt["alpha"], 0.01, 1.0)
    opt["eta"] = dr.clip(opt["eta"], 1.0, 3.0)
got = {k: float(opt[k][0]) for k in names}
t4 = time.perf_counter()
err = max(abs(got[k] - truth[k]) for k in names)
print("%s" + json.dumps({"imports": t1 - t0, "load": t2 - t1, "target": t3 - t2, "fit": t4 - t3,
                         "steps": a["steps"], "max parameter error": err}))
""" % PHASES


@dataclasses.dataclass(frozen=True)
class Case:
    row: str  # the table's row label
    argv: tuple[str, ...]  # after `python`
    needs_data: bool = False
    peer: str | None = None  # the Mitsuba case beside it
    setup: tuple[str, ...] = ()  # after `python`: run once in the work folder before the timed runs (untimed)


def cases(args) -> dict[str, Case]:
    dragon = 256 if args.quick else args.dragon_size
    frame = 128 if args.quick else 512
    fit = 64 if args.quick else args.fit_size
    cli = ("-m", "jaxrt.cli")
    # the CLI fit: the bunny as `fit-bunny` (spheres' Cook-Torrance sphere without $JAXRT_DATA)
    fit_scene, fit_object = ("bunny", "") if os.environ.get("JAXRT_DATA") else ("spheres", "cook_torrance")
    fit_cli = (*cli, "fit", "target.exr", "--scene", "scene.toml", "--model", "cook_torrance", "--grey",
               *(("--object", fit_object) if fit_object else ()))
    return {
        "render-dragon": Case(f"`jaxrt render dragon --width {dragon} --height {dragon}`",
                              (*cli, "render", "dragon", "--width", str(dragon), "--height", str(dragon)),
                              needs_data=True, peer="mitsuba-render"),
        "render-spheres": Case("`jaxrt render spheres`", (*cli, "render", "spheres")),
        "fit-demo": Case("`jaxrt fit --demo`", (*cli, "fit", "--demo")),
        "fit-bunny": Case(f"bunny {fit}² 4-parameter fit (`fitting.setup`)",
                          ("-c", FIT_BUNNY.format(size=fit)), needs_data=True, peer="mitsuba-fit"),
        "fit-cli": Case(f"`jaxrt fit target.exr --scene {fit_scene}.toml --model cook_torrance --grey"
                        f"{' --object ' + fit_object if fit_object else ''}`, {fit}² target (4 parameters)",
                        fit_cli, setup=("-c", FIT_TARGET, fit_scene, str(fit), fit_object)),
        "dragon-frame": Case(f"dragon scene load + first frame ({frame}²; compile = first frame compile)",
                             ("-c", DRAGON_FRAME.format(size=frame)), needs_data=True, peer="mitsuba-frame"),
        "imports": Case("Python imports before any work (jax, jaxrt.scene/render, fitting.setup)",
                        ("-c", "import jax, jaxrt.scene, jaxrt.api, brdfs, fitting.setup")),
        "sweep-frame": Case("a notebook's first sweep frame (`jaxrt.sweep.sweep`, phong rho_d, one 128² frame of "
                            "spheres, as the parameter_sweeps notebook)",
                            ("-c", "from jaxrt import sweep; sweep.sweep('phong', 'rho_d', [0.5], width=128, height=128)")),
        "import-jaxrt": Case("`import jaxrt`", ("-c", "import jaxrt")),
        "import-brdfs": Case("`import brdfs`", ("-c", "import brdfs")),
        "import-fitting": Case("`import fitting`", ("-c", "import fitting")),
    }


QUICK = ("imports", "import-jaxrt", "import-brdfs", "import-fitting", "render-spheres")


def _env(cache_dir: Path) -> dict:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAXRT_CACHE", "JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env["JAXRT_CACHE_DIR"] = str(cache_dir)
    env["PYTHONUNBUFFERED"] = "1"
    env["JAXRT_WORKER"] = "off"
    return env


def _proc_cpu(pid: int | None) -> float:
    """CPU seconds (user + system, all threads) of process `pid` so far; 0 where unknown."""
    if pid is None:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def _serve(action: str, cache_dir: Path, cwd: Path) -> dict | None:
    """Start (`start`), query (`status`) or stop (`stop`) the worker of `cache_dir`'s environment."""
    env = _env(cache_dir)
    argv = {"start": ["serve", "--idle-timeout", "600"], "status": ["serve", "--status"], "stop": ["serve", "--stop"]}
    p = subprocess.run([sys.executable, "-m", "jaxrt.cli", *argv[action]], env=env, cwd=cwd, capture_output=True,
                       text=True, check=False)
    if action == "status":
        return json.loads(p.stdout) if p.returncode == 0 else None
    return {"rc": p.returncode, "out": p.stdout + p.stderr}


def _run_worker(argv: tuple[str, ...], cache_dir: Path, cwd: Path, timeout: float, pid: int | None) -> dict:
    """One client process of the running worker; its CPU seconds plus the worker's during the job."""
    c0 = _proc_cpu(pid)
    out = _run(argv, cache_dir, cwd, False, timeout, worker=True)
    out["cpu"] += _proc_cpu(pid) - c0
    return out


def _run(argv: tuple[str, ...], cache_dir: Path, cwd: Path, preview: bool, timeout: float, worker: bool = False) -> dict:
    if preview and argv[:2] == ("-m", "jaxrt.cli"):
        argv = ("-c", PREVIEW + "import sys; from jaxrt.cli import main; sys.exit(main(sys.argv[1:]))", *argv[2:])
    elif preview and argv[0] == "-c":
        argv = ("-c", PREVIEW + argv[1], *argv[2:])
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    env = _env(cache_dir)
    if worker:
        env["JAXRT_WORKER"] = "use"
    p = subprocess.run([sys.executable, *argv], env=env, cwd=cwd, capture_output=True, text=True,
                       timeout=timeout, check=False)
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # CPU seconds of the process and its threads: on a shared, loaded machine far steadier than the wall time
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    out = {"wall": wall, "cpu": cpu, "rc": p.returncode}
    for line in p.stdout.splitlines():
        if line.startswith(PHASES):
            out["phases"] = json.loads(line[len(PHASES):])
    if p.returncode != 0:
        out["error"] = (p.stderr.strip().splitlines() or ["(no output)"])[-1][:160]
    entries = [f for sub in ("xla", "arrays") for f in (cache_dir / sub).glob("*") if not f.name.startswith(".")]
    out["entries"] = len(entries)
    return out


def _mitsuba_variant() -> str | None:
    try:
        import mitsuba as mi
    except Exception:  # noqa: BLE001 -- not installed or not loadable: no peer column
        return None
    for v in ("cuda_ad_rgb", "llvm_ad_rgb"):
        if v in mi.variants():
            try:
                mi.set_variant(v)
                return v
            except Exception:  # noqa: BLE001 -- no CUDA here: try the next one
                continue
    return None


def _mitsuba_args(kind: str, size: int, variant: str, tmp: Path) -> tuple[str, dict]:
    """(script, JSON arguments) for a Mitsuba case: the jaxrt scene's camera, lights and mesh (placed
    in the world and written as PLY once, untimed)."""
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import trimesh

    from jaxrt import scene
    from jaxrt.geometry import mesh

    name = "bunny" if kind == "mitsuba-fit" else "dragon"
    spec = scene.parse(scene.find_scene(name))
    ply = tmp / f"{name}.ply"
    if not ply.exists():
        o = next(o for o in spec.objects if o.mesh is not None)
        m = mesh.load(o.mesh).transformed(scale=1.0 if o.scale is None else np.asarray(o.scale),
                                          rotation=o.rotate or (0.0, 0.0, 0.0),
                                          translation=o.translate or (0.0, 0.0, 0.0))
        trimesh.Trimesh(m.vertices, m.faces, process=False).export(ply)
    cam = spec.camera
    lights = [{"position": [float(x) for x in p], "intensity": [float(x) for x in i]} for p, i in spec.lights]
    a = {"ply": str(ply), "lights": lights if kind == "mitsuba-fit" else lights[:1], "variant": variant, "size": size,
         "vfov": float(cam.vfov), "position": [float(x) for x in cam.position],
         "look_at": [float(x) for x in cam.look_at], "up": [float(x) for x in cam.up], "steps": 120}
    return (MITSUBA_FIT if kind == "mitsuba-fit" else MITSUBA_RENDER), a


def _median(runs: list[dict]) -> dict:
    """One run's record with the median wall and CPU time of `runs` (the first failure, if any)."""
    bad = [r for r in runs if r["rc"] != 0]
    if bad or len(runs) == 1:
        return (bad or runs)[0]
    out = dict(runs[0])
    for k in ("wall", "cpu"):
        out[k] = statistics.median(r[k] for r in runs)
    if all("phases" in r for r in runs):
        out["phases"] = {k: statistics.median(r["phases"][k] for r in runs) if isinstance(v, float) else v
                         for k, v in runs[0]["phases"].items()}
    out["runs"] = len(runs)
    return out


def _fmt(r: dict | None) -> str:
    if r is None:
        return ""
    if r.get("skip"):
        return r["skip"]
    if r["rc"] < 0:
        return f"aborted by signal {-r['rc']} ({r.get('error', '')[:60]})"
    if r["rc"] != 0:
        return f"failed ({r.get('error', '')})"
    s = f"{r['wall']:.2f} s" + (f" [cpu {r['cpu']:.2f} s]" if "cpu" in r else "")
    ph = r.get("phases")
    if ph:
        s += " (" + ", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in ph.items()
                              if k != "imports") + ")"
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", metavar="CASE", help="cases to run (default: all; with --quick: "
                    + " ".join(QUICK) + ")")
    ap.add_argument("--quick", action="store_true", help="small sizes for a CPU (dragon 256², frame 128², fit 64²)")
    ap.add_argument("--dragon-size", type=int, default=1024, help="dragon render size (default 1024)")
    ap.add_argument("--fit-size", type=int, default=256, help="bunny fit size (default 256)")
    ap.add_argument("--preview-wiring", action="store_true",
                    help="enable jaxrt.cache in each process (compilation cache, mesh and BVH cache) before the work")
    ap.add_argument("--no-mitsuba", action="store_true", help="skip the Mitsuba 3 column")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per process (default 1800)")
    ap.add_argument("--warm-runs", type=int, default=1, metavar="N",
                    help="run the warm process N times and report the median wall and CPU time (default 1)")
    ap.add_argument("--json", metavar="OUT.json", help="also write every measurement as JSON")
    ap.add_argument("--worker", action="store_true",
                    help="also run the warm rows as clients of a resident worker (`jaxrt serve`) on the same cache")
    args = ap.parse_args(argv)
    table = cases(args)
    chosen = args.cases or (list(QUICK) if args.quick else list(table))
    unknown = [c for c in chosen if c not in table]
    if unknown:
        ap.error(f"unknown case(s) {', '.join(unknown)}; cases: {', '.join(table)}")
    import jax  # only to name the machine

    dev = jax.devices()[0]
    print(f"machine: {platform.node()} ({os.cpu_count()} CPUs), {dev.platform} {dev.device_kind}, jax {jax.__version__},"
          f" python {platform.python_version()}; preview-wiring {'on' if args.preview_wiring else 'off'}", flush=True)
    variant = None if args.no_mitsuba else _mitsuba_variant()
    has_data = bool(os.environ.get("JAXRT_DATA"))
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="jaxrt-latency-") as tmpname:
        tmp = Path(tmpname)
        for name in chosen:
            case = table[name]
            res: dict = {"row": case.row}
            if case.needs_data and not has_data:
                res["cold"] = res["warm"] = {"skip": "skipped: needs $JAXRT_DATA"}
            else:
                cdir = tmp / f"cache-{name}"
                work = tmp / f"work-{name}"
                work.mkdir()
                if case.setup:  # its own cache folder: the cold run starts empty
                    p = subprocess.run([sys.executable, *case.setup], env=_env(tmp / f"setup-cache-{name}"), cwd=work,
                                       capture_output=True, text=True, timeout=args.timeout, check=False)
                    if p.returncode != 0:
                        sys.exit(f"{name}: preparation failed: {(p.stderr.strip().splitlines() or ['?'])[-1]}")
                for phase in ("cold", "warm"):
                    runs = [_run(case.argv, cdir, work, args.preview_wiring, args.timeout)
                            for _ in range(args.warm_runs if phase == "warm" else 1)]
                    for r in runs:
                        print(f"  {name} {phase}: {_fmt(r)}; cache entries {r['entries']}", flush=True)
                    res[phase] = _median(runs)
                if args.worker and case.argv[:2] == ("-m", "jaxrt.cli"):
                    started = _serve("start", cdir, work)
                    state = _serve("status", cdir, work)
                    if state is None:
                        res["worker"] = [{"rc": 1, "error": started["out"].strip()[-160:]}]
                    else:
                        runs = [_run_worker(case.argv, cdir, work, args.timeout, state["pid"])
                                for _ in range(args.warm_runs + 1)]
                        after = _serve("status", cdir, work) or {}
                        for r in runs:
                            print(f"  {name} worker: {_fmt(r)}", flush=True)
                        print(f"  {name} worker status: jobs {after.get('jobs')}, compile requests "
                              f"{after.get('compile_requests')}, traces {after.get('traces')}", flush=True)
                        res["worker"] = [runs[0], _median(runs[1:])]
                    _serve("stop", cdir, work)
                shutil.rmtree(cdir, ignore_errors=True)
            if case.peer and variant and has_data:
                size = {"mitsuba-render": 256 if args.quick else args.dragon_size, "mitsuba-frame": 128 if args.quick
                        else 512, "mitsuba-fit": 64 if args.quick else args.fit_size}[case.peer]
                script, a = _mitsuba_args(case.peer, size, variant, tmp)
                runs = [_run(("-c", script, json.dumps(a)), tmp / "mitsuba-unused", tmp, False, args.timeout)
                        for _ in range(2)]
                res["peer"] = runs
                print(f"  {name} Mitsuba {variant}: {' / '.join(_fmt(r) for r in runs)}", flush=True)
            results[name] = res

    print()
    wcol = " jaxrt warm, through a resident worker: first job / later jobs |" if args.worker else ""
    print(f"| what (whole process, start to exit) | jaxrt cold (empty cache folder) | jaxrt warm (second process) |"
          f"{wcol} Mitsuba 3 {variant or '(not run)'}: first run / second run |")
    print("|---|---|---|" + ("---|" if args.worker else "") + "---|")
    for name, r in results.items():
        peer = " / ".join(_fmt(x) for x in r.get("peer", []))
        w = (" " + " / ".join(_fmt(x) for x in r.get("worker", [])) + " |") if args.worker else ""
        print(f"| {r['row']} | {_fmt(r['cold'])} | {_fmt(r['warm'])} |{w} {peer} |")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
