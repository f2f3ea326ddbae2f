"""Stochastic progressive photon mapping throughput on the shipped caustic scene, and (with
--equal-time) SPPM against the path tracer at equal wall time on the area light's caustic.

    python benchmarks/sppm.py                                   # 128x96, 65536 photons, 8 passes
    python benchmarks/sppm.py --size 256 --photons 262144 --passes 8
    python benchmarks/sppm.py --equal-time 20                   # + error at 20 s each (area light only)
    python benchmarks/sppm.py --picture docs/caustics.png --seconds 40   # the README's picture

Throughput: compile time of one pass (`jaxrt.integrators.sppm.step`), then the median wall time of
`passes` passes (block_until_ready each); passes/s = 1 / median; photons/s = photons per pass /
median (the whole pass: camera pass, photon pass, hash grid, gather); the photon pass alone
(`sppm.trace_photons`, compiled separately) gives photons traced/s.

Equal time (--equal-time T): the caustic scene with its point light removed (the path tracer cannot
render a point light's caustic at all), 64x48, max_depth 6. Reference: the path tracer with
`--ref-spp` samples per pixel. Then SPPM and the path tracer each run passes until T seconds of
rendering (compilation excluded); the error is the RMS difference to the reference over the caustic
region (floor pixels under the sphere whose reference exceeds the floor's direct light by 20 %:
light focused by the glass) relative to the reference's mean there. The reference's own noise is
printed beside it.
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

from jaxrt import scene as S  # noqa: E402
from jaxrt.integrators import path as P  # noqa: E402
from jaxrt.integrators import sppm  # noqa: E402


def throughput(size: int, photons: int, passes: int) -> None:
    w, h = size, size * 3 // 4
    scn = S.load("caustics", overrides={"camera.width": w, "camera.height": h, "render.photons": photons})
    t0 = time.perf_counter()
    st = sppm.accumulate(scn)
    st.passes.block_until_ready()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(passes):
        t0 = time.perf_counter()
        st = sppm.accumulate(scn, st)
        st.passes.block_until_ready()
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    trace = jax.jit(sppm.trace_photons, static_argnums=2)
    key = jax.random.key(1)
    trace(scn, key, photons).valid.block_until_ready()
    pt = []
    for i in range(passes):
        t0 = time.perf_counter()
        trace(scn, jax.random.fold_in(key, i), photons).valid.block_until_ready()
        pt.append(time.perf_counter() - t0)
    img = np.asarray(st.image)
    print(f"device {jax.devices()[0].device_kind}; caustics {w}x{h}, {photons} photons/pass, max_depth "
          f"{scn.settings.max_depth}, {scn.geometry.triangle_count} triangles")
    print(f"  compile+first pass {compile_s:.1f} s; pass median {med * 1e3:.0f} ms over {passes}: "
          f"{1 / med:.2f} passes/s, {photons / med / 1e6:.3f} M photons/s (whole pass), "
          f"photon pass alone {statistics.median(pt) * 1e3:.0f} ms = {photons / statistics.median(pt) / 1e6:.3f} "
          f"M photons traced/s; image finite: {bool(np.isfinite(img).all())}")


def _run_for(seconds, step, state):
    state = step(state)  # compile (excluded)
    jax.block_until_ready(state)
    t0, n = time.perf_counter(), 0
    state = None
    while time.perf_counter() - t0 < seconds:
        state = step(state)
        jax.block_until_ready(state)
        n += 1
    return state, n, time.perf_counter() - t0


def equal_time(seconds: float, ref_spp: int) -> None:
    over = {"camera.width": 64, "camera.height": 48, "render.max_depth": 6}
    doc = S.parse(S.find_scene("caustics"), overrides=over)
    import dataclasses

    doc = dataclasses.replace(doc, lights=())
    base = S.build(doc)
    path_scn = S.build(dataclasses.replace(doc, render=dataclasses.replace(doc.render, integrator="path", spp=16)))
    passes = [np.asarray(P.render_jit(path_scn, 10_000 + i, jitter=True)) for i in range(ref_spp // 16)]
    ref = np.mean(passes, 0)
    ref_se = np.std(passes, 0, ddof=1) / np.sqrt(len(passes))
    # the caustic: floor pixels (depth beyond the sphere's silhouette is not needed: the floor is
    # the only diffuse surface there) brighter than 1.2x the floor's median, in the lower half
    lum = ref.mean(-1)
    h = lum.shape[0]
    region = np.zeros_like(lum, bool)
    region[h // 2:] = lum[h // 2:] > 1.2 * np.median(lum[h // 2:])
    m = ref[region].mean()

    def err(img):
        return float(np.sqrt(np.mean((img[region] - ref[region]) ** 2)) / m)

    st, n_s, t_s = _run_for(seconds, lambda s: sppm.accumulate(base, s), None)
    acc, n_p, t_p = _run_for(seconds, lambda a: P.accumulate(path_scn, a), None)
    e_s, e_p = err(np.asarray(st.image)), err(np.asarray(acc.image))
    print(f"equal time {seconds:.0f} s, area light only, 64x48, caustic region {int(region.sum())} px; reference "
          f"path tracer {ref_spp} spp (its relative standard error there {float(np.sqrt(np.mean(ref_se[region] ** 2)) / m):.3f})")
    print(f"  SPPM {n_s} passes in {t_s:.1f} s: relative RMS error {e_s:.3f}")
    print(f"  path {n_p} passes of 16 spp in {t_p:.1f} s: relative RMS error {e_p:.3f}  (ratio {e_p / e_s:.1f}x)")


def picture(out: str, seconds: float, size: int) -> None:
    """The caustics scene, path tracer (left) and SPPM (right), each for `seconds` of rendering
    after compilation, side by side with labels, sRGB PNG."""
    from PIL import Image, ImageDraw

    from jaxrt import image

    over = {"camera.width": size, "camera.height": size * 3 // 4}
    sp = S.load("caustics", overrides={**over, "render.photons": 100_000})
    pt = S.load("caustics", overrides={**over, "render.integrator": "path", "render.spp": 4})
    st, n_s, t_s = _run_for(seconds, lambda s: sppm.accumulate(sp, s), None)
    acc, n_p, t_p = _run_for(seconds, lambda a: P.accumulate(pt, a), None)
    left, right = image.to_srgb8(np.asarray(acc.image)), image.to_srgb8(np.asarray(st.image))
    both = Image.fromarray(np.concatenate([left, np.full((left.shape[0], 4, 3), 255, np.uint8), right], 1))
    draw = ImageDraw.Draw(both)
    draw.text((4, 2), f"path tracing, {4 * n_p} spp, {t_p:.0f} s", fill=(255, 255, 255))
    draw.text((left.shape[1] + 8, 2), f"SPPM, {n_s} passes, {t_s:.0f} s", fill=(255, 255, 255))
    both.save(out)
    print(f"wrote {out}: path {n_p} passes x 4 spp in {t_p:.1f} s, SPPM {n_s} passes x 100k photons in {t_s:.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--photons", type=int, default=65536)
    ap.add_argument("--passes", type=int, default=8)
    ap.add_argument("--equal-time", type=float, default=0.0, metavar="SECONDS")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--picture", metavar="OUT.png", help="only write the path-vs-SPPM picture at equal time")
    ap.add_argument("--seconds", type=float, default=40.0, help="rendering time of each half of --picture")
    a = ap.parse_args()
    if a.picture:
        picture(a.picture, a.seconds, a.size)
        return
    throughput(a.size, a.photons, a.passes)
    if a.equal_time > 0:
        equal_time(a.equal_time, a.ref_spp)


if __name__ == "__main__":
    main()
