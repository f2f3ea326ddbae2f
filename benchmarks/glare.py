"""Time the glare post-process (`jaxrt.glare.apply`) on random HDR images.

    python benchmarks/glare.py                              # 512² and 1024², PSF 255 and 63 px, 5 repeats
    python benchmarks/glare.py --sizes 2048 --psf-sizes 255 --repeats 3
    python benchmarks/glare.py --figure docs/glare.png     # the README's figure instead (320x240 panels)

For each image size and PSF width: the first call (compilation included), then the median of the
repeats of `apply` (the PSF computed inside the same compiled program: three FFTs of
(4·size)² for the aperture, and the padded FFT convolution of the image) and of `psf` alone, on
the default device. Settings are the defaults (6-blade polygon, f/16, 4 µm pixels, threshold 0)
with the PSF width changed.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxrt import glare  # noqa: E402


def _time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


# The README figure: `spheres` with a small bright lamp added (Whitted shows emitters), then four
# panels: no glare | 6 blades, f/16, threshold 0 (every pixel diffracts) | circle, f/32, threshold 2 |
# 5 blades rotated 90°, f/32, threshold 2; all with 2 µm pixels and a 255-px PSF.
LAMP = """
[materials.lamp]
model = "lambert"
rho_d = 0.0
emission = [400.0, 380.0, 330.0]

[[objects]]
name = "lamp"
primitive = "sphere"
radius = 0.06
subdivisions = 2
translate = [1.6, 1.9, -1.2]
material = "lamp"
"""
PANELS = (None, glare.Glare(blades=6, f_number=16.0, pixel_pitch=2.0),
          glare.Glare(aperture="circle", f_number=32.0, pixel_pitch=2.0, threshold=2.0),
          glare.Glare(blades=5, rotation=90.0, f_number=32.0, pixel_pitch=2.0, threshold=2.0))


def figure(path):
    import tempfile

    import jaxrt
    from jaxrt import image, scene
    from PIL import Image

    with tempfile.TemporaryDirectory() as d:
        toml = Path(d) / "spheres_lamp.toml"
        toml.write_text(scene.find_scene("spheres").read_text() + LAMP)
        img = np.asarray(jaxrt.render(toml, overrides={"camera.width": 320, "camera.height": 240}))
    tiles = [image.to_srgb8(np.asarray(glare.apply(img, g)) if g is not None else img) for g in PANELS]
    grid = np.concatenate([np.concatenate(tiles[:2], 1), np.concatenate(tiles[2:], 1)], 0)
    Image.fromarray(grid).save(path, optimize=True)
    print(f"wrote {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024], help="square image sizes")
    ap.add_argument("--psf-sizes", type=int, nargs="+", default=[255, 63], help="PSF widths (odd)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--figure", metavar="OUT.png", help="write the README's figure instead of timing")
    args = ap.parse_args(argv)
    if args.figure:
        return figure(args.figure)
    dev = jax.devices()[0]
    print(f"# {dev.platform} {dev.device_kind}, {os.cpu_count()} host cores, {platform.processor() or platform.machine()}, "
          f"jax {jax.__version__}, load average {os.getloadavg()[0]:.1f}")
    print("| image | PSF px | first call s (compile) | apply ms (median) | psf ms (median) |")
    print("|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for n in args.sizes:
        img = jax.device_put((rng.random((n, n, 3)) ** 8 * 10).astype(np.float32))
        for k in args.psf_sizes:
            g = glare.Glare(size=k)
            t0 = time.perf_counter()
            jax.block_until_ready(glare.apply(img, g))
            first = time.perf_counter() - t0
            jax.block_until_ready(glare.psf(g))
            t_apply = _time(lambda: glare.apply(img, g), args.repeats)
            t_psf = _time(lambda: glare.psf(g), args.repeats)
            print(f"| {n}² | {k} | {first:.2f} | {1e3 * t_apply:.0f} | {1e3 * t_psf:.0f} |", flush=True)


if __name__ == "__main__":
    main()
