"""Load balance of renders split over devices: how close the tile assignment comes to an even split.

    python benchmarks/devices_balance.py                              # showcase (glass) 128x96, 2/4/8 devices
    python benchmarks/devices_balance.py --scene cornell_area --integrator path --spp 4 --size 96 72
    python benchmarks/devices_balance.py --passes --integrator path --spp 2 --size 64 48 --devices 4

A render on N devices runs its tiles N at a time (`jaxrt._devices.program`: one tile per device per
call, and a call lasts as long as its slowest tile). This script plans the render on N virtual CPU
devices (`render_tiles.plan(devices=N)`: at least max(32, 4·N) tiles, the same tiles for N ≤ 8),
times every tile alone on one device (`integrators.tile`, median of `--repeats`), and from those
costs computes the wall time of the calls under two assignments:

- interleaved (what `render_tiles` does): call c renders steps c·N … c·N + N − 1, so each device's
  tiles are spread over the image and the tiles of one call are neighbours of similar cost;
- blocks: device d renders the d-th contiguous run of T/N steps (call c: steps d·T/N + c), so one
  device may get all the glass or all the sky;
- sorted (a bound, not implemented): the tiles ordered by their measured cost, then taken N at a
  time, which minimises the sum over calls of the slowest tile; what a perfect cost estimate (say
  from a previous pass) could give.

It prints, per N, the ideal Σ cost / N, each assignment's Σ over calls of the slowest tile, and the
efficiency ideal / actual. Tile costs come from one device, so the figures describe the assignment,
not the interconnect; on a shared CPU the tile timings carry its noise.

With `--passes` (a path-traced scene) it also compares the loads of progressive passes, max/mean
device load (1 is a perfect split), the loads evaluated with the tile costs measured alone:

- interleaved calls: what a pass without costs runs (one tile per device per call, a call as
  long as its slowest tile), Σ over calls of the slowest tile / (Σ cost / N);
- interleaved lists: each device's interleaved tiles run back to back (no wait after each call);
- cost-based, timed passes on N virtual devices: `render_tiles.accumulate`'s schedule for later
  passes, longest processing time first (`_devices.lpt`) over the costs its first pass measured on
  the N virtual devices (one tile program per device, `_devices.timed`), and over the least of the
  first TIMED_PASSES passes' times (what runs). Virtual CPU devices share
  the host's cores, so there a tile's wall time on its device also measures what the other devices
  ran beside it: an estimate degraded by contention that separate devices (GPUs) do not have;
- cost-based, separate timing: LPT over a second, independent run of the alone timings (what a
  first pass gives where each device's time is its own);
- LPT on the evaluated timings themselves: the bound of a perfect estimate.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=8")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxrt import _devices, integrators, render_tiles  # noqa: E402
from jaxrt import scene as S  # noqa: E402
from jaxrt.camera import Window  # noqa: E402


def tile_costs(scene, p, repeats: int) -> np.ndarray:
    th, tw, sb = p.shape
    dev0 = jax.devices()[0]
    scene = jax.device_put(scene, dev0)
    i32 = np.int32
    def window(step):
        (_, (r0, c0), (s0, n)) = step
        return Window(i32(r0), i32(c0), i32(s0), i32(n), th, tw, sb)
    integrators.tile(scene, window(p.steps[0])).block_until_ready()  # compile
    out = []
    for step in p.steps:
        w = window(step)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            integrators.tile(scene, w).block_until_ready()
            ts.append(time.perf_counter() - t)
        out.append(statistics.median(ts))
    return np.array(out)


def makespan(cost: np.ndarray, n: int, order: str) -> float:
    t = len(cost)
    calls = -(-t // n)
    pad = np.concatenate([cost, np.zeros(calls * n - t)])
    if order == "sorted":
        pad = np.sort(pad)[::-1]
    if order in ("interleaved", "sorted"):
        per_call = pad.reshape(calls, n)  # row c: steps c·n … c·n + n − 1
    else:
        per_call = pad.reshape(n, calls).T  # column d: device d's contiguous run
    return float(per_call.max(axis=1).sum())


def pass_costs(scene, p, repeats: int) -> np.ndarray:
    """Each step's least time of `repeats` alone on the first device as a tile of a progressive pass
    (the least: on a shared CPU other work only ever adds time)."""
    th, tw, sb = p.shape
    dev0 = jax.devices()[0]
    run = _devices.tile_pass_program(p.shape)
    sc = jax.device_put(scene, dev0)
    i32 = np.int32
    def call(step):
        return run(sc, np.array(step[1], i32), np.array(step[2], i32), i32(1))
    call(p.steps[0]).block_until_ready()  # compile
    out = []
    for step in p.steps:
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            call(step).block_until_ready()
            ts.append(time.perf_counter() - t)
        out.append(min(ts))
    return np.array(out)


def loads(cost: np.ndarray, lists) -> float:
    per = [cost[list(x)].sum() for x in lists]
    return float(max(per) / (cost.sum() / len(lists)))


def passes(sc, ns, repeats: int) -> None:
    for n in ns:
        p = render_tiles.plan(sc, memory="8G", devices=n)
        sep = pass_costs(sc, p, repeats)  # the estimate of a device that runs alone
        c = pass_costs(sc, p, repeats)  # the evaluation
        acc, m1 = render_tiles.accumulate(sc, None, use_plan=p, return_plan=True)
        _, m2 = render_tiles.accumulate(sc, acc, use_plan=m1, return_plan=True)
        est1, est = np.array(m1.costs), np.array(m2.costs)
        inter = [list(range(d, p.tiles, n)) for d in range(n)]
        lockstep = makespan(c, n, "interleaved") / (c.sum() / n)

        def rank(a):
            return np.corrcoef(np.argsort(np.argsort(a)), np.argsort(np.argsort(c)))[0, 1]

        print(f"passes N={n}: {p.tiles} tiles {p.shape}, tile cost ms min/median/max {1e3 * c.min():.1f}/"
              f"{1e3 * np.median(c):.1f}/{1e3 * c.max():.1f}; max/mean device load: interleaved calls "
              f"{lockstep:.2f}, interleaved lists {loads(c, inter):.2f}, cost-based (first pass on {n} virtual "
              f"devices) {loads(c, _devices.lpt(est1, n)):.2f}, (least of the {render_tiles.TIMED_PASSES} timed "
              f"passes: what runs) {loads(c, _devices.lpt(est, n)):.2f}, cost-based (separate timing) "
              f"{loads(c, _devices.lpt(sep, n)):.2f}, LPT on the evaluated timings {loads(c, _devices.lpt(c, n)):.2f}; "
              f"rank correlation with the evaluated timings: first pass {rank(est1):.2f}, least of the timed passes "
              f"{rank(est):.2f}, separate {rank(sep):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="showcase")
    ap.add_argument("--size", type=int, nargs=2, default=(128, 96), metavar=("W", "H"))
    ap.add_argument("--integrator")
    ap.add_argument("--spp", type=int)
    ap.add_argument("--devices", type=int, nargs="+", default=(2, 4, 8))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--passes", action="store_true",
                    help="progressive path passes: interleaved against cost-based (path-traced scenes)")
    a = ap.parse_args()
    ov = {"camera.width": a.size[0], "camera.height": a.size[1]}
    if a.integrator:
        ov["render.integrator"] = a.integrator
    if a.spp:
        ov["render.spp"] = a.spp
    sc = S.load(a.scene, overrides=ov)
    if a.passes:
        print(f"{a.scene} {a.size[0]}x{a.size[1]} {sc.settings.integrator} spp {sc.settings.spp}: "
              f"{jax.devices()[0].device_kind}")
        passes(sc, a.devices, a.repeats)
        return
    plans = {n: render_tiles.plan(sc, memory="8G", devices=n) for n in a.devices}
    shapes = {p.shape for p in plans.values()}
    print(f"{a.scene} {a.size[0]}x{a.size[1]} {sc.settings.integrator} spp {sc.settings.spp}: "
          f"{jax.devices()[0].device_kind}, tile shapes {sorted(shapes)}")
    costs = {}
    for n, p in plans.items():
        if p.shape not in costs:
            costs[p.shape] = tile_costs(sc, p, a.repeats)
        c = costs[p.shape]
        ideal = c.sum() / n
        inter, block, best = (makespan(c, n, o) for o in ("interleaved", "blocks", "sorted"))
        print(f"N={n}: {p.tiles} tiles, tile cost ms min/median/max {1e3 * c.min():.1f}/{1e3 * np.median(c):.1f}/"
              f"{1e3 * c.max():.1f}; ideal {1e3 * ideal:.0f} ms, interleaved {1e3 * inter:.0f} ms "
              f"({ideal / inter:.0%}), blocks {1e3 * block:.0f} ms ({ideal / block:.0%}), sorted {1e3 * best:.0f} ms "
              f"({ideal / best:.0%})")


if __name__ == "__main__":
    main()
