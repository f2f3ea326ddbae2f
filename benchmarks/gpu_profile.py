"""Where a GPU program's time goes, kernel by kernel: one workload traced with JAX's profiler, the
device's kernels summed by name (launches, total and median microseconds, share of device time),
and the launches and device time per repetition. For deciding what to fuse or drop, not for ratios
against a peer (`benchmarks/peers.py`, `benchmarks/sppm.py` do those).

    python benchmarks/gpu_profile.py sppm --size 96 --repeats 20       # calls of 8 SPPM passes, equal-time scene
    python benchmarks/gpu_profile.py path-dragon --size 512 --repeats 5  # a path-tracing pass, dragon in an envmap
    python benchmarks/gpu_profile.py path-cornell --size 512 --repeats 5
    python benchmarks/gpu_profile.py direct-dragon --size 1024 --repeats 10  # a direct-light frame
    python benchmarks/gpu_profile.py rays-dragon --size 1024 --repeats 10    # peers.py's camera-ray row

On a machine without a GPU the trace holds host events only: the script says so and prints the host
side's largest XLA events instead (still useful to count programs per repetition).
"""

from __future__ import annotations

import argparse
import collections
import os
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import numpy as np  # noqa: E402


def _workload(name: str, size: int, photons: int, camera_samples: int, passes: int):
    """(one repetition as a callable returning an array to wait on, a description)."""
    import jaxrt.scene as S
    from jaxrt.integrators import path as P
    from jaxrt.integrators import sppm
    if name == "sppm":
        import sppm as bench  # benchmarks/sppm.py: the equal-time scene
        scn = bench._build(bench.caustic_doc(size), photons=photons, camera_samples=camera_samples)
        state = [sppm.accumulate(scn)]

        def run():
            state[0] = sppm.step(scn, state[0], passes)
            return state[0].passes
        return run, (f"{passes} SPPM passes a call (a repetition), equal-time caustic scene {scn.camera.width}x{scn.camera.height}, "
                     f"{sppm.photons_per_pass(scn)} photons, {sppm.camera_samples(scn)} visible points/pixel, "
                     f"{sppm.grid_levels(scn)} grid levels")
    if name.startswith(("path-", "image-")):
        import pathlib
        import path as bench  # benchmarks/path.py: the scenes of its table
        exr = bench.sky_exr(pathlib.Path(tempfile.mkdtemp()) / "sky.exr")
        scn = bench.load(name.split("-", 1)[1], size, 16, 4, exr, "dragon")
        i = [0]

        # path-*: the per-sample radiance (`samples_jit`); image-*: the pass's image (`render_jit`)
        fn = P.render_jit if name.startswith("image-") else P.samples_jit

        def run():
            i[0] += 1
            return fn(scn, i[0], jitter=True)
        return run, f"path-tracing pass, {name} {size}x{size}, 16 spp, depth 4 (benchmarks/path.py's)"
    if name.startswith("direct-"):
        from jaxrt.integrators import whitted
        scn = S.load(name.split("-", 1)[1], overrides={"camera.width": size, "camera.height": size})
        frame = jax.jit(whitted.whitted)

        def run():
            return frame(scn)
        return run, f"direct-light frame, {name} {size}x{size}"
    if name.startswith("rays-"):
        import peers  # benchmarks/peers.py: its scenes and camera rays
        scn = peers.load_direct(name.split("-", 1)[1], size)
        o, d = peers.camera_rays(scn)
        hit = jax.jit(lambda g, o, d: g.intersect(o, d))

        def run():
            return hit(scn.geometry, o, d)
        return run, f"camera rays' closest hits (geometry.intersect), {name} {size}x{size}"
    raise SystemExit(f"unknown workload {name!r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workload", help="sppm, path-dragon, path-cornell, direct-dragon, direct-bunny, rays-dragon")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--photons", type=int, default=65536, help="sppm: photons per pass (the GPU's equal-time value)")
    ap.add_argument("--camera-samples", type=int, default=4, help="sppm: visible points per pixel per pass")
    ap.add_argument("--sppm-passes", type=int, default=8, help="sppm: passes a call (a repetition)")
    a = ap.parse_args()
    run, what = _workload(a.workload, a.size, a.photons, a.camera_samples, a.sppm_passes)
    for _ in range(3):  # compile and warm
        jax.block_until_ready(run())
    wall = []
    with tempfile.TemporaryDirectory() as d:
        jax.profiler.start_trace(d)
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(run())
            wall.append(time.perf_counter() - t0)
        jax.profiler.stop_trace()
        files = [os.path.join(r, f) for r, _, fs in os.walk(d) for f in fs if f.endswith(".xplane.pb")]
        data = jax.profiler.ProfileData.from_file(files[0])
    kernels = collections.defaultdict(list)
    host = collections.defaultdict(list)
    device_planes = 0
    lines_seen = []
    for plane in data.planes:
        on_gpu = plane.name.startswith("/device:GPU")
        device_planes += on_gpu
        for line in plane.lines:
            if on_gpu:
                lines_seen.append(line.name)
            # the GPU plane's kernel lines ("Stream #..."), not its module/op summary lines
            if on_gpu and "Stream" not in line.name:
                continue
            for ev in line.events:
                (kernels if on_gpu else host)[ev.name].append(ev.duration_ns / 1e3)
    if device_planes and not kernels:
        print(f"no kernel line among the GPU plane's lines {lines_seen}: every line counted")
        for plane in data.planes:
            if plane.name.startswith("/device:GPU"):
                for line in plane.lines:
                    for ev in line.events:
                        kernels[f"{line.name}: {ev.name}"].append(ev.duration_ns / 1e3)
    print(f"device {jax.devices()[0].device_kind}; {what}; {a.repeats} repetitions, wall median "
          f"{statistics.median(wall) * 1e3:.3f} ms (min {min(wall) * 1e3:.3f})")
    table, unit = (kernels, "kernel") if device_planes else (host, "host event")
    if not device_planes:
        print("no GPU plane in the trace: host events instead")
    total = sum(sum(v) for v in table.values())
    launches = sum(len(v) for v in table.values())
    print(f"{launches / a.repeats:.1f} {unit}s and {total / a.repeats:.1f} us of {unit} time per repetition")
    rows = sorted(table.items(), key=lambda kv: -sum(kv[1]))[: a.top]
    print(f"{'us/rep':>9} {'share':>6} {'n/rep':>6} {'median us':>10}  name")
    for name, v in rows:
        print(f"{sum(v) / a.repeats:9.1f} {sum(v) / total:6.1%} {len(v) / a.repeats:6.1f} "
              f"{np.median(v):10.2f}  {name[:110]}")


if __name__ == "__main__":
    main()
