"""GPU image == CPU image: render shipped scenes on the default backend and on the CPU backend of the
same process and compare (run on the GPU machine; on a CPU-only machine both sides are the CPU).

    JAXRT_DATA=../shared/data/meshes python benchmarks/gpu_check.py [--size 64] [--scenes ...]

Prints, per scene: max |GPU − CPU| relative to the image's maximum, the fraction of pixels that differ by
more than 1e-3 of the maximum (a ray that grazes an edge may pick the neighbouring triangle on the other
backend), and whether every pixel is finite.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import jaxrt as R
from jaxrt import scene as S

SCENES = ("spheres", "bunny", "dragon", "cornell", "showcase")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    args = ap.parse_args()
    dev = jax.devices()[0]
    cpu = jax.devices("cpu")[0]
    print(f"default device: {dev.device_kind}; reference: {cpu.device_kind}; jax {jax.__version__}")
    print(f"{'scene':<10} {'max rel diff':>12} {'pixels > 1e-3':>14} {'finite':>7}")
    worst = 0.0
    for name in args.scenes:
        sc = S.load(name, overrides={"camera.width": args.size, "camera.height": args.size})
        a = np.asarray(R.frame(jax.device_put(sc, dev)))
        with jax.default_device(cpu):
            b = np.asarray(R.frame(jax.device_put(sc, cpu)))
        scale = max(float(np.abs(b).max()), 1e-12)
        d = np.abs(a - b).max(axis=-1) / scale
        frac = float(np.mean(d > 1e-3))
        worst = max(worst, frac)
        print(f"{name:<10} {float(d.max()):>12.2e} {frac:>14.4%} {str(bool(np.isfinite(a).all())):>7}")
    return 0 if worst < 0.01 else 1


if __name__ == "__main__":
    raise SystemExit(main())
