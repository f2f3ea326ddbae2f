"""Stochastic progressive photon mapping on caustics: throughput, a converged path-traced reference,
and SPPM against the path tracer at equal wall time.

Commands. On one NVIDIA H200 the two GPU lines take about 3.5 minutes together (start-up, BVH build
and compilation included: the reference stops after 100 s of rendering, the table renders 4 s per
integrator plus 3 x 4 s for the bias check); the CPU line (2 cores) about 3 minutes plus compilation,
with the reference file made on the GPU:

    # GPU: the reference (the last 100 s only around the caustic), then the equal-time table and the bias check
    python benchmarks/sppm.py --make-reference 1073741824 --max-seconds 100 --chunk-spp 4096 --crop 3 \
        --crop-after 32 --out caustic_ref.npz
    python benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 --reference caustic_ref.npz
    # the same without photon aiming (the scene's default aims half the photons at the glass)
    python benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 --reference caustic_ref.npz --photon-aim 0 --bias-seeds 0
    # CPU, with the GPU's caustic_ref.npz (the scene and settings are checked on load)
    python benchmarks/sppm.py --equal-time 5,10,20,40 --reference caustic_ref.npz --bias-seeds 0
    # CPU alone: a 64x48 reference, 3,072 spp of full frames then only the caustic's window, 30 minutes
    python benchmarks/sppm.py --size 64 --make-reference 1073741824 --chunk-spp 256 --crop 3 --crop-after 12 \
        --max-seconds 1800 --out caustic_ref64.npz
    python benchmarks/sppm.py --size 64 --equal-time 5,10,20 --reference caustic_ref64.npz --bias-seeds 0
    # CPU alone at the GPU's 96x72: 2,048 spp of full frames, then the window; 25 minutes
    python benchmarks/sppm.py --make-reference 1073741824 --chunk-spp 256 --crop 3 --crop-after 8 \
        --max-seconds 1500 --out caustic_ref96.npz
    python benchmarks/sppm.py --size 96 --equal-time 5,10,20 --reference caustic_ref96.npz --bias-seeds 0
    # several passes a call against one (SPPM's per-pass cost and what a call costs besides its passes)
    python benchmarks/sppm.py --throughput-scene equal-time --size 96 --photons 4096 --passes 12 --passes-per-call 8
    # throughput on the shipped scene; the README's picture
    python benchmarks/sppm.py                                   # 128x96, 65536 photons, 8 passes
    python benchmarks/sppm.py --picture docs/caustics.png --seconds 40 --size 192

Throughput (no other mode): compile time of the passes' program (`jaxrt.integrators.sppm.steps`),
then, interleaved in three rounds, `passes` calls of one pass and `passes` calls of --passes-per-call
passes (default `sppm.passes_per_call`'s choice for the measured pass, at least 2), block_until_ready
after each call: the median wall and CPU seconds per pass; passes/s = 1 / median; photons/s = photons
per pass / median (the whole pass: camera pass, photon pass, hash grid, gather); the photon pass
alone (`sppm.trace_photons`, compiled separately) gives photons traced/s. --throughput-scene
equal-time measures the equal-time comparison's frame instead of the shipped scene.

The equal-time scene (`caustic_doc`): scenes/caustics.toml without its point light (the path tracer
cannot render a point light's caustic at all), its 0.3 m lamp moved behind the sphere (to where the
point light is: the lamp's caustic then lands on the floor in front of the sphere, in view, instead
of under it) and the camera closer, max_depth 6, --size x 3/4 pixels (default 96x72). The floor in
the sphere's shadow gets its light only through the glass, which the path tracer reaches only by
BSDF sampling (its shadow rays stop at glass): fireflies.

--make-reference SPP --out FILE: the path tracer's image of that scene with SPP samples per pixel,
in chunks of --chunk-spp (one pass each, pass indices from 2^20 on so they never coincide with the
equal-time runs' 0, 1, ...), with a progress bar. Saved (numpy .npz): the per-pixel mean, the
per-pixel standard error (the spread of the chunk means / sqrt(chunks)), the means of its even and
odd chunks (a second estimate of its error, `_split_noise`), a direct-light-only image
(max_depth 1, chunks of the same size, 1/16 as many, 2..64), the fraction of each pixel's first hits on the floor,
and the settings (the scene as JSON, spp, chunks, device, time, versions). With --max-seconds it
stops after that much rendering and saves the chunks done (the file records their number); so does
Ctrl-C. With --crop PIXELS, after --crop-after full chunks only the bounding box of those chunks'
caustic region grown by PIXELS is rendered (`camera.Window`, the same paths as the full frame's
pixels there): all the samples go where the error is measured, 25x more a second at 64x48. The
file records the window; the region is cut to it, and the pixels outside hold the full chunks alone.

The caustic region (`caustic_region`, computed from the reference when it is loaded): pixels whose
first hit is always the floor and whose light after at least one scattering (the reference minus its
direct-only image, luminance) exceeds REGION_FACTOR = 5 times the median floor pixel's: the core of
the light focused onto the floor by the glass (up to ~150 times the median at 96x72). The directly lit
floor, the dim interreflection in the shadow and the caustic's faint aberrated halo stay out of it.
Pixels picked by the reference's own noise bias its region mean upwards: negligible once the
reference has converged (its relative standard error there a few per cent), which the rows need anyway.

--equal-time T1,T2,... --reference FILE: checks that FILE was made for this very scene (resolution,
max_depth, every scene value; one line and exit status 2 otherwise), then runs SPPM (--photons per
pass, --camera-samples visible points per pixel per pass, initial radius --radius (default: the
integrator's, one pixel footprint), --photon-aim F: the fraction of photons aimed at the glass, default
the scene's 0.5; aiming changes the estimator, not the expected image, so the reference's check
ignores it; so do --grid-levels and --passes-per-call, default `sppm.passes_per_call`'s choice for
calls of at most a tenth of the shortest budget, as a render's within `sppm.CALL_SECONDS`) and the path tracer (--path-spp samples per pass) each once for
max(T) seconds of rendering after compilation (excluded), taking their images when the time passed
reaches each T. For each T it prints the relative RMS error over the caustic region
(sqrt(mean (image − reference)²) / mean reference, over the region's pixels and channels), the same
with the reference's own noise removed (sqrt(e² − s²), s the reference's relative RMS error, which
adds to e² on average: the larger of the chunks' standard error and the error estimated from the
difference of its even and odd chunks), and the ratio path / SPPM. A row counts ("judged") only where s is
below a third of both errors. Then the bias check: --bias-seeds independent SPPM runs of max(T)
seconds; the mean of their region means against the reference's region mean, with the combined
standard error (the runs' spread / sqrt(runs) and the reference's).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import statistics
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxrt import camera  # noqa: E402
from jaxrt import scene as S  # noqa: E402
from jaxrt.integrators import path as P  # noqa: E402
from jaxrt.integrators import sppm  # noqa: E402

#: the equal-time scene's lamp position (behind the sphere) and camera (see the module docstring)
LAMP = [0.0, 3.0, -3.0]
CAMERA = {"position": [0.0, 3.0, 5.0], "look_at": [0.0, 0.4, 0.7], "vfov": 30.0}
MAX_DEPTH = 6
#: --equal-time's SPPM visible points per pixel per pass and photons per pass on a GPU and on a CPU
#: (the CPU's measured: its error hardly depends on the photons a pass, 2,048 to 16,384, at a given
#: number of passes, so the fewest that keep a pass's fixed costs small; the GPU's from a sweep on an
#: H200 of 1/4/16 points and 65,536/262,144 photons: 4 and 65,536 were best or near it at 0.25-4 s)
GPU_CAMERA_SAMPLES, CPU_CAMERA_SAMPLES = 4, 1
GPU_PHOTONS, CPU_PHOTONS = 1 << 16, 1 << 12
#: pass indices of the reference's chunks start here (the equal-time runs use 0, 1, ...)
REF_PASS0 = 1 << 20
#: the caustic region's threshold, in median floor radiances (see the module docstring)
REGION_FACTOR = 5.0
#: the reference file's format version (a file of another version is refused); format 1 files (without
#: the even and odd chunks' means) are still read, their error estimated from the chunks' spread alone
REF_FORMAT = 2
_READS_FORMATS = (1, 2)


def _per_pass(run, state, count: int, calls: int):
    """Median wall and CPU seconds per pass of `calls` calls of `count` passes (`run(state, count)`,
    synchronised after each call, as a render's loop); returns (state, wall, cpu)."""
    wall, cpu = [], []
    for _ in range(calls):
        t0, c0 = time.perf_counter(), time.process_time()
        state = run(state, count)
        state.passes.block_until_ready()
        wall.append((time.perf_counter() - t0) / count)
        cpu.append((time.process_time() - c0) / count)
    return state, statistics.median(wall), statistics.median(cpu)


def throughput(size: int, photons: int, passes: int, per_call: int | None = None, levels: int = 0,
               scene: str = "caustics", samples: int = 1) -> None:
    """Compile time, then passes/s and photons/s of one pass a call and, interleaved in the same
    process, of `per_call` passes a call (default: `sppm.passes_per_call` from the one-pass time, at
    least 2), each the median of `passes` calls' per-pass times; `scene` "caustics" (the shipped one)
    or "equal-time" (the equal-time comparison's, `caustic_doc`)."""
    w, h = size, size * 3 // 4
    over = {"photons": photons, "camera_samples": samples}
    if levels:
        over["grid_levels"] = levels
    if scene == "equal-time":
        scn = _build(caustic_doc(size), **over)
    else:
        scn = S.load(scene, overrides={"camera.width": w, "camera.height": h,
                                       **{f"render.{k}": v for k, v in over.items()}})
    t0 = time.perf_counter()
    st = sppm.accumulate(scn)
    st.passes.block_until_ready()
    compile_s = time.perf_counter() - t0
    run = lambda s, k: sppm.step(scn, s, k)  # noqa: E731
    st, med, cpu = _per_pass(run, st, 1, 2)  # warm
    per_call = per_call or max(2, sppm.passes_per_call(med, 1 << 30))
    rows = {1: ([], []), per_call: ([], [])}
    idle = []
    for _ in range(3):  # interleaved: one call per pass, then per_call passes a call, then a call of none
        t0 = time.perf_counter()
        st = run(st, 0)
        st.passes.block_until_ready()
        idle.append(time.perf_counter() - t0)
        for k in rows:
            st, m, c = _per_pass(run, st, k, max(passes // 3, 1))
            rows[k][0].append(m)
            rows[k][1].append(c)
    med = statistics.median(rows[1][0])
    trace = jax.jit(sppm.trace_photons, static_argnums=2)
    key = jax.random.key(1)
    trace(scn, key, photons).valid.block_until_ready()
    pt = []
    for i in range(passes):
        t0 = time.perf_counter()
        trace(scn, jax.random.fold_in(key, i), photons).valid.block_until_ready()
        pt.append(time.perf_counter() - t0)
    img = np.asarray(st.image)
    print(f"device {_device()}; {scene} {scn.camera.width}x{scn.camera.height}, {photons} photons/pass, "
          f"{samples} visible points/pixel/pass, grid levels {sppm.grid_levels(scn)}, max_depth "
          f"{scn.settings.max_depth}, {scn.geometry.triangle_count} triangles")
    print(f"  compile+first pass {compile_s:.1f} s; photon pass alone {statistics.median(pt) * 1e3:.1f} ms = "
          f"{photons / statistics.median(pt) / 1e6:.3f} M photons traced/s; image finite: "
          f"{bool(np.isfinite(img).all())}")
    print(f"  a call of 0 passes (what a call costs besides its passes): {statistics.median(idle) * 1e3:.2f} ms")
    for k, (wall, cpu) in rows.items():
        m, c = statistics.median(wall), statistics.median(cpu)
        print(f"  {k} pass{'es' if k > 1 else ''} a call: {m * 1e3:.2f} ms a pass (CPU {c * 1e3:.2f} ms), "
              f"{1 / m:.1f} passes/s, {photons / m / 1e6:.3f} M photons/s (whole pass); per round "
              f"{', '.join(f'{x * 1e3:.1f}' for x in wall)} ms")


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


def picture(out: str, seconds: float, size: int, name: str = "caustics") -> None:
    """A shipped caustic scene (`name`), path tracer (left) and SPPM (right), each for `seconds` of
    rendering after compilation, side by side with labels, sRGB PNG."""
    from PIL import Image, ImageDraw

    from jaxrt import image

    over = {"camera.width": size, "camera.height": size * 3 // 4}
    sp = S.load(name, overrides={**over, "render.photons": 100_000})
    pt = S.load(name, overrides={**over, "render.integrator": "path", "render.spp": 4})
    st, n_s, t_s = _run_for(seconds, lambda s: sppm.accumulate(sp, s), None)
    acc, n_p, t_p = _run_for(seconds, lambda a: P.accumulate(pt, a), None)
    left, right = image.to_srgb8(np.asarray(acc.image)), image.to_srgb8(np.asarray(st.image))
    both = Image.fromarray(np.concatenate([left, np.full((left.shape[0], 4, 3), 255, np.uint8), right], 1))
    draw = ImageDraw.Draw(both)
    draw.text((4, 2), f"path tracing, {4 * n_p} spp, {t_p:.0f} s", fill=(255, 255, 255))
    draw.text((left.shape[1] + 8, 2), f"SPPM, {n_s} passes, {t_s:.0f} s", fill=(255, 255, 255))
    both.save(out)
    print(f"wrote {out}: path {n_p} passes x 4 spp in {t_p:.1f} s, SPPM {n_s} passes x 100k photons in {t_s:.1f} s")


def caustic_doc(size: int, max_depth: int = MAX_DEPTH, lamp: float | None = None) -> dict:
    """The equal-time scene as a scene dict: scenes/caustics.toml without its point light, the lamp
    at LAMP, the camera at CAMERA, size x size*3/4 pixels. `lamp`: the lamp's side in metres (default
    the shipped 0.3 m), its radiance scaled by the inverse area so that its power stays the same: a
    smaller lamp only makes the path tracer's BSDF-sampled caustic paths hit it less often."""
    with open(S.find_scene("caustics"), "rb") as f:
        doc = tomllib.load(f)
    doc.pop("lights", None)
    doc.pop("description", None)
    doc["camera"] = {**doc["camera"], **CAMERA, "width": size, "height": size * 3 // 4}
    doc["render"] = {**doc["render"], "max_depth": max_depth}
    for o in doc["objects"]:
        if o["name"] == "lamp":
            o["translate"] = list(LAMP)
            if lamp is not None:
                scale = (o["size"][0] * o["size"][1]) / (lamp * lamp)
                o["size"] = [lamp, lamp]
                mat = doc["materials"][o["material"]]
                mat["emission"] = [e * scale for e in mat["emission"]]
    return doc


def _build(doc: dict, **render) -> "S.Scene":
    return S.build(S.parse({**doc, "render": {**doc["render"], **render}}))


def _canonical(doc: dict) -> str:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


def _git_commit() -> str:
    try:
        r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10,
                           cwd=Path(__file__).resolve().parents[1])
        return r.stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def _device() -> str:
    d = jax.devices()[0]
    return d.device_kind if d.device_kind.lower().startswith(d.platform) else f"{d.platform} {d.device_kind}"


def _default(gpu_value, cpu_value):
    return gpu_value if jax.devices()[0].platform == "gpu" else cpu_value


def _lum(img):
    return img @ np.array([0.2126, 0.7152, 0.0722])


def _fail(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(2)


class _Lines:
    """A stand-in for tqdm's bar: prints a line at every tenth of the total."""

    def __init__(self, total, desc="", **_):
        self.total, self.desc, self.n, self.t0, self.next = total, desc, 0, time.perf_counter(), 0.1

    def update(self, k):
        self.n += k
        if self.n >= self.next * self.total:
            print(f"{self.desc}: {self.n}/{self.total} after {time.perf_counter() - self.t0:.0f} s", file=sys.stderr)
            self.next += 0.1

    def close(self):
        pass


class _Welford:
    """Per-pixel running mean and sum of squared deviations of chunk images (float64)."""

    def __init__(self):
        self.n, self.mean, self.m2 = 0, None, None

    def add(self, x):
        x = np.asarray(x, np.float64)
        if self.mean is None:
            self.mean, self.m2 = np.zeros_like(x), np.zeros_like(x)
        self.n += 1
        d = x - self.mean
        self.mean += d / self.n
        self.m2 += d * (x - self.mean)

    @property
    def se(self):
        return np.sqrt(self.m2 / max(self.n - 1, 1) / max(self.n, 1))


def make_reference(spp: int, out: str, size: int, chunk_spp: int | None, max_seconds: float | None,
                   lamp: float | None = None, crop: int | None = None, crop_after: int = 32) -> None:
    """The path-traced reference of the equal-time scene (see the module docstring), saved to `out`.
    With `crop` (pixels) the chunks after the first `crop_after` render only the window around the
    caustic region of those (its bounding box grown by `crop` pixels on every side): all the samples
    go where the error is measured; the file records the window, and the region is cut to it."""
    try:
        from tqdm import tqdm
    except ImportError:  # a bare machine: a line every 10% instead of a bar
        tqdm = _Lines
    chunk_spp = chunk_spp or _default(1024, 16)
    if spp < 2 * chunk_spp:
        _fail(f"--make-reference {spp}: needs at least 2 chunks of --chunk-spp {chunk_spp} (a standard error)")
    doc = caustic_doc(size, lamp=lamp)
    scn = _build(doc, integrator="path", spp=chunk_spp)
    direct_scn = _build(doc, integrator="path", spp=chunk_spp, max_depth=1)
    floor = scn.geometry.object_names.index("floor")
    chunks = spp // chunk_spp
    n_direct = min(max(2, chunks // 16), 64)
    t0 = time.perf_counter()
    jax.block_until_ready(P.render_jit(scn, REF_PASS0, jitter=True))
    jax.block_until_ready(P.render_jit(direct_scn, REF_PASS0, jitter=True, aovs=True))
    compile_s = time.perf_counter() - t0
    direct, on_floor = _Welford(), _Welford()
    for i in range(n_direct):
        img, aov = P.render_jit(direct_scn, REF_PASS0 + i, jitter=True, aovs=True)
        direct.add(img)
        on_floor.add(np.asarray(aov["object_id"]) == floor)
    ref, halves = _Welford(), (_Welford(), _Welford())
    bar = tqdm(total=chunks * chunk_spp, unit="spp", unit_scale=True, desc="reference", dynamic_ncols=True,
               file=sys.stderr)
    full, win, box = [], None, None  # the full chunks (until the crop), the window and its (r0, c0, h, w)
    t0 = time.perf_counter()
    try:
        for i in range(chunks):
            if crop is not None and win is None and i == crop_after:
                box = _crop_box(caustic_region(ref.mean, direct.mean, on_floor.mean), crop)
                if box is not None:
                    r0, c0, h, w = box
                    win = camera.Window(jnp.int32(r0), jnp.int32(c0), jnp.int32(0), jnp.int32(chunk_spp), h, w,
                                        chunk_spp)
                    # the window's statistics restart from the full chunks' pixels in it
                    ref, halves = _Welford(), (_Welford(), _Welford())
                    for j, f in enumerate(full):
                        ref.add(f[r0:r0 + h, c0:c0 + w])
                        halves[j % 2].add(f[r0:r0 + h, c0:c0 + w])
                    print(f"\ncropped to rows {r0}..{r0 + h - 1}, columns {c0}..{c0 + w - 1} after {i} chunks",
                          file=sys.stderr)
            if win is None:
                img = np.asarray(P.render_jit(scn, REF_PASS0 + i, jitter=True))
                if crop is not None:
                    full.append(img)
            else:
                img = np.asarray(P.render_jit(scn, REF_PASS0 + i, jitter=True, window=win))
            ref.add(img)
            halves[i % 2].add(img)
            bar.update(chunk_spp)
            if max_seconds and time.perf_counter() - t0 > max_seconds and ref.n >= 2:
                break
    except KeyboardInterrupt:
        print("\ninterrupted: saving the chunks done", file=sys.stderr)
    bar.close()
    seconds = time.perf_counter() - t0
    if ref.n < 2:
        _fail("fewer than 2 chunks rendered: no standard error; nothing saved")
    mean, se, even, odd = ref.mean, ref.se, halves[0].mean, halves[1].mean
    if box is not None:  # the window's statistics over the full chunks' (the pixels outside: those alone)
        r0, c0, h, w = box
        outside = _Welford(), (_Welford(), _Welford())
        for j, f in enumerate(full):
            outside[0].add(f)
            outside[1][j % 2].add(f)
        parts = []
        for whole, part in ((outside[0].mean, mean), (outside[0].se, se), (outside[1][0].mean, even),
                            (outside[1][1].mean, odd)):
            whole = whole.copy()
            whole[r0:r0 + h, c0:c0 + w] = part
            parts.append(whole)
        mean, se, even, odd = parts
    meta = {"format": REF_FORMAT, "scene": _canonical(doc), "width": doc["camera"]["width"],
            "height": doc["camera"]["height"], "max_depth": doc["render"]["max_depth"], "spp": ref.n * chunk_spp,
            "chunk_spp": chunk_spp, "chunks": ref.n, "direct_chunks": direct.n, "seconds": seconds,
            "compile_s": compile_s, "device": _device(), "jax": jax.__version__, "commit": _git_commit(),
            "made": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    if box is not None:
        meta.update(window=list(box), full_chunks=len(full))
    tmp = Path(out).with_suffix(".tmp.npz")
    np.savez_compressed(tmp, mean=mean, se=se, direct=direct.mean, floor=on_floor.mean,
                        even=even, odd=odd, meta=np.array(json.dumps(meta)))
    tmp.replace(out)
    region = caustic_region(mean, direct.mean, on_floor.mean, meta.get("window"))
    m = mean[region].mean()
    rate = ref.n * chunk_spp * ref.mean.shape[0] * ref.mean.shape[1] / seconds / 1e6
    print(f"wrote {out}: {meta['width']}x{meta['height']}, {meta['spp']} spp in {ref.n} chunks of {chunk_spp}, "
          f"{seconds:.1f} s ({rate:.2f} Msamples/s) after {compile_s:.1f} s compiling, on {meta['device']}")
    print(f"  caustic region {int(region.sum())} px, mean radiance {m:.4g}; reference relative RMS standard error "
          f"there {_ref_noise(mean, se, region):.4f} from the chunks' spread, "
          f"{_split_noise(mean, even, odd, region):.4f} from its even and odd chunks' "
          f"difference (its region mean's: {_region_mean_se(se, region) / m:.2e})"
          + (f"; window {box} ({len(full)} full chunks before it)" if box is not None else ""))


def _crop_box(region, margin: int):
    """(row0, col0, height, width) of the region's bounding box grown by `margin` pixels, in the image."""
    if not region.any():
        return None
    rows, cols = np.nonzero(region)
    h, w = region.shape
    r0, c0 = max(int(rows.min()) - margin, 0), max(int(cols.min()) - margin, 0)
    r1, c1 = min(int(rows.max()) + margin, h - 1), min(int(cols.max()) + margin, w - 1)
    return r0, c0, r1 - r0 + 1, c1 - c0 + 1


def caustic_region(mean, direct, on_floor, window=None):
    """Pixels whose first hit is always the floor and whose light after at least one scattering
    (mean − direct, luminance) exceeds REGION_FACTOR times the median luminance of the floor's pixels;
    inside `window` (row0, col0, height, width) where the reference was cropped to one."""
    floor = on_floor >= 1.0
    if not floor.any():
        return floor
    threshold = REGION_FACTOR * np.median(_lum(mean)[floor])
    region = floor & (_lum(mean - direct) > threshold)
    if window is not None:
        r0, c0, h, w = window
        inside = np.zeros_like(region)
        inside[r0:r0 + h, c0:c0 + w] = True
        region &= inside
    return region


def _region_mean_se(se, region):
    """Standard error of the region mean (over pixels and channels): pixels are independent (their
    own paths), a pixel's three channels counted as fully correlated (the same paths)."""
    return float(np.sqrt(np.sum(se[region].mean(-1) ** 2)) / region.sum())


def _split_noise(mean, even, odd, region):
    """The reference's relative RMS error over the region estimated from its two halves (even and odd
    chunks): E(even − odd)² = 4 E(mean − truth)² for halves of equal size, an independent check of
    the chunks' spread, which underestimates the error when rare, very bright samples dominate."""
    return float(np.sqrt(np.mean((even[region] - odd[region]) ** 2)) / 2 / mean[region].mean())


def _ref_noise(mean, se, region):
    """The reference's relative RMS standard error over the region (normalised as the errors are)."""
    return float(np.sqrt(np.mean(se[region] ** 2)) / mean[region].mean())


def load_reference(path: str, size: int, lamp: float | None = None) -> dict:
    """The reference file, checked against this run's scene; one line and exit 2 if it differs."""
    try:
        z = np.load(path)
        meta = json.loads(str(z["meta"]))
        ref = {k: z[k] for k in ("mean", "se", "direct", "floor")}
        ref.update({k: z[k] for k in ("even", "odd") if k in z.files})
    except (OSError, KeyError, ValueError) as e:
        _fail(f"{path}: not a reference file of benchmarks/sppm.py --make-reference ({e})")
    if meta.get("format") not in _READS_FORMATS:
        _fail(f"{path}: reference format {meta.get('format')!r}, this script reads {_READS_FORMATS}; remake it")
    doc = caustic_doc(size, lamp=lamp)
    if meta["scene"] != _canonical(doc):
        made = json.loads(meta["scene"])
        diff = _diff(made, doc)
        _fail(f"{path}: made for another scene or settings ({diff}); remake it with --make-reference, or "
              f"pass --size {made['camera']['width']} if only the resolution differs")
    return {**ref, "meta": meta, "doc": doc}


def _diff(a, b, where="") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if a.get(k) != b.get(k):
                return _diff(a.get(k), b.get(k), f"{where}.{k}" if where else k)
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            if x != y:
                return _diff(x, y, f"{where}[{i}]")
    return f"{where}: file {a!r}, this run {b!r}"


def _run_until(marks, step, per_call=None):
    """Run `step` (state -> state; None starts) for max(marks) seconds after a first, compiling call
    (excluded); returns [(state, passes, seconds)] taken when each mark's time has passed. With
    `per_call` (seconds per pass so far, passes so far -> passes for the next call), `step` is
    (state, count) -> state and runs that many passes a call."""
    jax.block_until_ready(step(None) if per_call is None else step(None, 1))
    out, marks = [], sorted(marks)
    t0, n, state = time.perf_counter(), 0, None
    while marks:
        if per_call is None:
            state, k = step(state), 1
        else:
            k = per_call((time.perf_counter() - t0) / n if n else float("nan"), n)
            state = step(state, k)
        jax.block_until_ready(state)
        n += k
        t = time.perf_counter() - t0
        while marks and t >= marks[0]:
            out.append((state, n, t))
            marks.pop(0)
    return out


def equal_time(marks, ref_path: str, size: int, photons: int | None, radius: float, path_spp: int | None,
               bias_seeds: int, lamp: float | None = None, aim: float | None = None,
               samples: int | None = None, levels: int = 0, per_call: int = 0, alpha: float | None = None) -> None:
    ref = load_reference(ref_path, size, lamp)
    meta, doc = ref["meta"], ref["doc"]
    photons = photons or _default(GPU_PHOTONS, CPU_PHOTONS)
    path_spp = path_spp or _default(256, 16)
    mean, se = ref["mean"], ref["se"]
    region = caustic_region(mean, ref["direct"], ref["floor"], meta.get("window"))
    if region.sum() == 0:
        _fail(f"{ref_path}: empty caustic region")
    m = mean[region].mean()
    s_chunks = _ref_noise(mean, se, region)
    s_split = _split_noise(mean, ref["even"], ref["odd"], region) if "even" in ref else float("nan")
    s_ref = s_chunks if math.isnan(s_split) else max(s_chunks, s_split)

    def err(img):
        return float(np.sqrt(np.mean((np.asarray(img, np.float64)[region] - mean[region]) ** 2)) / m)

    # photon aiming changes the estimator, not the expected image: it is passed beside the scene
    # document that the reference was checked against
    extra = {} if aim is None else {"photon_aim": aim}
    if radius:
        extra["radius"] = radius
    samples = samples or _default(GPU_CAMERA_SAMPLES, CPU_CAMERA_SAMPLES)
    extra["camera_samples"] = samples
    if levels:
        extra["grid_levels"] = levels
    if alpha:
        extra["alpha"] = alpha
    sp = _build(doc, photons=photons, **extra)
    pt = _build(doc, integrator="path", spp=path_spp)
    # SPPM's passes a call: --passes-per-call, else as a render picks them (`sppm.passes_per_call`)
    # for calls of at most a tenth of the shortest budget, so that the images are taken close to it
    target = min(sppm.CALL_SECONDS, min(marks) / 10)
    calls = ((lambda sec, n: per_call) if per_call else
             (lambda sec, n: sppm.passes_per_call(sec, sppm.MAX_PASSES_PER_CALL, target)))
    runs_s = _run_until(marks, lambda s, k: sppm.accumulate(sp, s, k), calls)
    runs_p = _run_until(marks, lambda a: P.accumulate(pt, a))
    print(f"device {_device()}; equal time on the caustic scene (area light only) {meta['width']}x{meta['height']}, "
          f"max_depth {meta['max_depth']}; SPPM {photons} photons/pass, {samples} visible points/pixel/pass, "
          f"initial radius {radius or f'{sppm.RADIUS_PIXELS:g} pixel footprint'}, photon_aim "
          f"{sp.settings.photon_aim:g}, grid levels {sppm.grid_levels(sp)}, alpha {sppm.alpha(sp):g}, passes a call "
          f"{per_call or f'adaptive (~{target:g} s a call)'}; path {path_spp} spp/pass")
    print(f"reference {ref_path}: {meta['spp']} spp ({meta['chunks']} chunks) on {meta['device']}, commit "
          f"{meta['commit']}; caustic region {int(region.sum())} px, mean {m:.4g}; its relative RMS error "
          f"s = {s_ref:.4f} (the larger of {s_chunks:.4f} from its chunks' spread and "
          f"{'(not in this file)' if math.isnan(s_split) else f'{s_split:.4f}'} from its halves)")
    print("| T s | SPPM passes (s) | SPPM rel. RMS error (noise of ref. removed) | path spp (s) | "
          "path rel. RMS error (removed) | path / SPPM | judged (s < errors / 3) |")
    print("|---|---|---|---|---|---|---|")
    for T, (st, n_s, t_s), (acc, n_p, t_p) in zip(sorted(marks), runs_s, runs_p):
        e_s, e_p = err(st.image), err(acc.image)
        c_s, c_p = (math.sqrt(max(e * e - s_ref * s_ref, 0.0)) for e in (e_s, e_p))
        ok = s_ref < min(e_s, e_p) / 3
        print(f"| {T:g} | {n_s} ({t_s:.2f}) | {e_s:.4f} ({c_s:.4f}) | {n_p * path_spp} ({t_p:.2f}) | {e_p:.4f} "
              f"({c_p:.4f}) | {e_p / e_s:.2f} ({c_p / c_s if c_s > 0 else float('inf'):.2f}) | "
              f"{'yes' if ok else 'no'} |")
    if bias_seeds < 2:
        return
    T = max(marks)
    means = [float(np.asarray(runs_s[-1][0].image, np.float64)[region].mean())]
    for seed in range(1, bias_seeds):
        sp_k = _build(doc, photons=photons, seed=seed, **extra)
        means.append(float(np.asarray(_run_until([T], lambda s, k: sppm.accumulate(sp_k, s, k), calls)[0][0].image,
                                      np.float64)[region].mean()))
    mu = statistics.fmean(means)
    se_s = statistics.stdev(means) / math.sqrt(len(means))
    se_r = _region_mean_se(se, region)
    comb = math.hypot(se_s, se_r)
    print(f"bias: SPPM region mean after {T:g} s over {len(means)} seeds {mu:.4g} ± {se_s:.2g}, reference {m:.4g} ± "
          f"{se_r:.2g}: difference {(mu - m) / m:+.2%} of the reference, {(mu - m) / comb:+.1f} combined standard "
          f"errors ({'within' if abs(mu - m) <= 3 * comb else 'NOT within'} 3)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=None,
                    help="image width (height = 3/4 of it); throughput and picture 128, reference and equal time 96")
    ap.add_argument("--photons", type=int, default=None,
                    help="photons per SPPM pass (throughput 65536; equal time: %d on a GPU, %d on a CPU)"
                    % (GPU_PHOTONS, CPU_PHOTONS))
    ap.add_argument("--passes", type=int, default=8, help="throughput: calls timed per variant")
    ap.add_argument("--passes-per-call", type=int, default=0, metavar="P",
                    help="SPPM passes per compiled call (throughput: compared with 1; equal time: fixed instead "
                         "of sppm.passes_per_call's choice)")
    ap.add_argument("--grid-levels", type=int, default=0, metavar="L",
                    help="SPPM [render] grid_levels (default: the integrator's for this backend)")
    ap.add_argument("--throughput-scene", default="caustics", choices=("caustics", "equal-time"),
                    help="throughput on the shipped caustics scene or on the equal-time comparison's")
    ap.add_argument("--make-reference", type=int, default=0, metavar="SPP",
                    help="render the path-traced reference with SPP samples per pixel into --out")
    ap.add_argument("--out", default="caustic_ref.npz")
    ap.add_argument("--chunk-spp", type=int, default=None, help="reference samples per chunk (GPU 1024, CPU 16)")
    ap.add_argument("--max-seconds", type=float, default=None, help="stop the reference after this much rendering")
    ap.add_argument("--crop", type=int, default=None, metavar="PIXELS",
                    help="after --crop-after chunks, render the reference only in the caustic region's bounding "
                         "box grown by PIXELS (all the samples where the error is measured)")
    ap.add_argument("--crop-after", type=int, default=32, metavar="CHUNKS", help="full chunks before --crop")
    ap.add_argument("--equal-time", default="", metavar="T1,T2,...", help="wall budgets in seconds")
    ap.add_argument("--reference", metavar="FILE", help="the --make-reference file for --equal-time")
    ap.add_argument("--radius", type=float, default=0.0,
                    help="SPPM initial radius for --equal-time [m] (default 0: the integrator's, per pixel)")
    ap.add_argument("--camera-samples", type=int, default=None, metavar="K",
                    help="SPPM visible points per pixel per pass for --equal-time (GPU %d, CPU %d)"
                    % (GPU_CAMERA_SAMPLES, CPU_CAMERA_SAMPLES))
    ap.add_argument("--photon-aim", type=float, default=None, metavar="F",
                    help="SPPM [render] photon_aim for --equal-time (default: the scene's, 0.5 with its glass)")
    ap.add_argument("--path-spp", type=int, default=None, help="path samples per pass (GPU 256, CPU 16)")
    ap.add_argument("--lamp", type=float, default=None, metavar="METRES",
                    help="side of the equal-time scene's square lamp (default 0.3 as shipped; same power)")
    ap.add_argument("--bias-seeds", type=int, default=4, help="SPPM runs of the longest time for the bias check")
    ap.add_argument("--picture", metavar="OUT.png", help="only write the path-vs-SPPM picture at equal time")
    ap.add_argument("--seconds", type=float, default=40.0, help="rendering time of each half of --picture")
    ap.add_argument("--scene", default="caustics", help="the shipped scene of --picture (caustics, caustics_dragon)")
    ap.add_argument("--alpha", type=float, default=None,
                    help="SPPM [render] alpha for --equal-time (radius reduction, default %g)" % sppm.ALPHA)
    ap.add_argument("--radius-pixels", type=float, default=None,
                    help="study: the default initial radius in pixel footprints (`sppm.RADIUS_PIXELS`, default %g); "
                         "same caveat as --alpha" % sppm.RADIUS_PIXELS)
    a = ap.parse_args()
    if a.alpha is not None and not 0.0 < a.alpha < 1.0:
        _fail(f"--alpha {a.alpha}: must be in (0, 1)")
    if a.radius_pixels is not None:
        if not 0.0 < a.radius_pixels <= 64.0:
            _fail(f"--radius-pixels {a.radius_pixels}: must be in (0, 64]")
        sppm.RADIUS_PIXELS = a.radius_pixels
        print(f"# study: sppm.RADIUS_PIXELS = {a.radius_pixels:g}")
    if a.picture:
        picture(a.picture, a.seconds, a.size or 128, a.scene)
    elif a.make_reference:
        make_reference(a.make_reference, a.out, a.size or 96, a.chunk_spp, a.max_seconds, a.lamp, a.crop,
                       a.crop_after)
    elif a.equal_time:
        try:
            marks = [float(t) for t in a.equal_time.split(",")]
        except ValueError:
            marks = []
        if not marks or min(marks) <= 0:
            _fail(f"--equal-time {a.equal_time!r}: expected positive seconds separated by commas")
        if not a.reference:
            _fail("--equal-time needs --reference FILE (made with --make-reference)")
        equal_time(marks, a.reference, a.size or 96, a.photons, a.radius, a.path_spp, a.bias_seeds, a.lamp,
                   a.photon_aim, a.camera_samples, a.grid_levels, a.passes_per_call, a.alpha)
    else:
        throughput(a.size or 128, a.photons or 65536, a.passes, a.passes_per_call or None, a.grid_levels,
                   a.throughput_scene, a.camera_samples or 1)


if __name__ == "__main__":
    main()
