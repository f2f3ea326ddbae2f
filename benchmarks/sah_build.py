"""Build time and tree quality of the binned-SAH builder against the LBVH (BENCHMARKS.md, "Tree quality").

Prints, for one model (default the full dragon):
- host build times (`bvh_build.build_arrays`, leaf_size 1) of the LBVH, the SAH tree and the SAH
  tree with depth-first numbering, alternating in one process (the machine is shared, so the
  ratio to the LBVH within a round is the figure to compare), wall and CPU seconds, with the
  load average before and after;
- per tree: `bvh.stats` SAH cost and depth, and node visits per ray (`bvh.node_visits`, the XLA
  loop) for `rays.py`'s camera at --res², shadow rays from its primary hits to its light, and the
  same shadow segments traced from the light end: mean / mean over groups of 32 consecutive rays
  of the group's maximum (a GPU warp's cost).
Trees: "lbvh", "sah" (this builder's defaults) and "sah-exact" (`SahSettings(exact_bounds=True)`, which
also turns the clusters off: the tree of the first, slower SAH builder).
--baseline DIR also times the builders of another checkout (DIR/jaxrt/bvh_build.py and bvh_sah.py,
e.g. an older main) in the same rounds, as "base lbvh" / "base sah".

    python benchmarks/sah_build.py [--model dragon] [--rounds 5] [--res 128] [--no-visits] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import types

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import jax
import jax.numpy as jnp
from rays import camera_rays

from jaxrt.accel import bvh
from jaxrt.accel import builder as bvh_build
from jaxrt.accel import sah as bvh_sah
from jaxrt.geometry import data
from jaxrt.geometry import mesh


def baseline_build(root):
    """build_arrays of the checkout at `root`, with its own bvh_sah (a package 'baseline_jaxrt')."""
    pkg = types.ModuleType("baseline_jaxrt")
    pkg.__path__ = []
    sys.modules["baseline_jaxrt"] = pkg
    mods = {}
    for name in ("bvh_build", "bvh_sah"):
        with open(os.path.join(root, "jaxrt", f"{name}.py")) as fh:
            src = fh.read()
        src = src.replace("from jaxrt.accel.builder import", "from baseline_jaxrt.bvh_build import")
        src = src.replace("from jaxrt import bvh_sah", "from baseline_jaxrt import bvh_sah")
        m = types.ModuleType(f"baseline_jaxrt.{name}")
        sys.modules[m.__name__] = m
        setattr(pkg, name, m)
        mods[name] = m
        # its imports of jaxrt.accel.builder / bvh_sah rewritten to the baseline's own
        exec(compile(src, f"{root}/jaxrt/{name}.py", "exec"), m.__dict__)  # noqa: S102
    return mods["bvh_build"].build_arrays


def build_times(v, f, rounds, baseline=None):
    builds = {b: bvh_build.build_arrays for b in ["lbvh", "sah", "sah/dfs"]}
    if baseline:
        base = baseline_build(baseline)
        builds = {"base lbvh": base, **builds, "base sah": base}
    names = list(builds)
    wall = {b: [] for b in names}
    cpu = {b: [] for b in names}
    load0 = os.getloadavg()
    for _ in range(rounds):
        for b in names:
            builder, _, layout = b.removeprefix("base ").partition("/")
            t, c = time.perf_counter(), time.process_time()
            builds[b](v, f, leaf_size=1, builder=builder, layout=layout or "bfs")
            wall[b].append(time.perf_counter() - t)
            cpu[b].append(time.process_time() - c)
    load1 = os.getloadavg()
    print(f"# load average before {load0[0]:.2f} / {load0[1]:.2f}, after {load1[0]:.2f} / {load1[1]:.2f}")
    ref = names[0]
    print(f"| build | wall s per round | median | min | CPU s median | median of per-round ratio to {ref} |")
    print("|---|---|---|---|---|---|")
    for b in names:
        r = np.median(np.array(wall[b]) / np.array(wall[ref]))
        print(f"| {b} | {' '.join(f'{t:.2f}' for t in wall[b])} | {np.median(wall[b]):.2f} | {min(wall[b]):.2f} "
              f"| {np.median(cpu[b]):.2f} | {r:.2f} |")


def visits(tree, f_vis, o, d, light):
    n = len(o)
    z = jnp.zeros(n, jnp.float32)
    prim = np.asarray(f_vis(tree, jnp.asarray(o), jnp.asarray(d), z, jnp.full(n, jnp.inf), False))
    hit = jax.jit(bvh.intersect)(tree, jnp.asarray(o), jnp.asarray(d), z, jnp.inf)
    ok = np.asarray(hit.prim) >= 0
    p = o[ok] + np.asarray(hit.t)[ok, None] * d[ok]
    so, sd = p.astype(np.float32), (light[None] - p).astype(np.float32)
    eps = np.float32(1e-4)
    m = len(so)
    shadow = np.asarray(f_vis(tree, jnp.asarray(so), jnp.asarray(sd), jnp.full(m, eps), jnp.full(m, 1 - eps), True))
    # from the light end over the same segment (as bvh.occluded(from_end=True))
    lo_ = (so + (1 - eps) * sd).astype(np.float32)
    light_v = np.asarray(f_vis(tree, jnp.asarray(lo_), jnp.asarray(-sd), jnp.zeros(m, jnp.float32),
                               jnp.full(m, 1 - 2 * eps), True))

    def fmt(x):
        g = x[:len(x) // 32 * 32].reshape(-1, 32).max(1)
        return f"{x.mean():.1f} / {g.mean():.1f}"

    return fmt(prim), fmt(shadow), fmt(light_v)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="dragon")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--no-visits", action="store_true")
    ap.add_argument("--baseline", default=None, help="another checkout whose builders to time alongside")
    args = ap.parse_args(argv)
    m = mesh.load(data.find(args.model))
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    print(f"# {args.model}: {len(f)} triangles, cpus {os.cpu_count()}")
    build_times(v, f, args.rounds, args.baseline)
    f_vis = jax.jit(lambda tr, o, d, tmin, tmax, a: bvh.node_visits(tr, o, d, tmin, tmax, any_hit=a), static_argnums=5)
    o, d, light = camera_rays(v, args.res)
    print("\n| tree | SAH cost | depth | build s (this call) | primary visits | shadow | shadow from light |")
    print("|---|---|---|---|---|---|---|")
    for name in ["lbvh", "sah", "sah-exact"]:
        t = time.perf_counter()
        tree = bvh.build(v, f, builder=name[:4].rstrip("-"),
                         sah_settings=bvh_sah.SahSettings(exact_bounds=name == "sah-exact"))
        tb = time.perf_counter() - t
        st = tree.stats
        vis = ("", "", "") if args.no_visits else visits(tree, f_vis, o, d, light)
        print(f"| {name} | {st.sah_cost:.2f} | {st.depth} | {tb:.2f} | {vis[0]} | {vis[1]} | {vis[2]} |", flush=True)


if __name__ == "__main__":
    main()
