"""Where a path-tracing pass's wall time goes beyond its kernels, as `benchmarks/path.py` times it beside
Mitsuba: one process, `benchmarks/path.py`'s scene (default the Cornell box, 512², 16 spp, depth 4),
loops of --passes passes, each loop's median:

  samples        `path.samples_jit` back to back, waiting for each (the per-sample radiance stays on the device)
  render         `path.render_jit` back to back, waiting for each (the image averaged on the device)
  render+copy    the same, the image copied to the host in the timed region (what path.py times)
  +check         and between passes the host's check of the image (finite, mean), as path.py does
  dispatch       the time `render_jit` takes to return (the work is queued, not finished)
  copy           copying an image already on the device (a fresh array each time) to the host
  copy via pinned   the same through page-locked host memory (`jax.device_put` to memory kind pinned_host)
  render to pinned+copy   render+copy with the program writing its image to pinned host memory
  render_host    `path.render_host` (what `benchmarks/path.py` times)
  mean ...       `render` with the samples averaged in other ways (an optimisation barrier before the
                 mean; a sum of slices; a matrix product at full precision; sum then multiply)

    python benchmarks/pass_parts.py            # on a GPU
    python benchmarks/pass_parts.py --scene dragon --size 256
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

import path as bench  # noqa: E402  (benchmarks/path.py)
from jaxrt.integrators import path as P  # noqa: E402


def loop(fn, passes: int, between=None) -> float:
    ts = []
    for i in range(1, passes + 1):
        t = time.perf_counter()
        out = fn(i)
        ts.append(time.perf_counter() - t)
        if between is not None:
            between(out)
    return statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="cornell", choices=["cornell", "dragon"])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--passes", type=int, default=9)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    exr = bench.sky_exr(Path(tempfile.mkdtemp()) / "sky.exr")
    sc = bench.load(args.scene, args.size, 16, 4, exr, "dragon")
    P.samples_jit(sc, 0, jitter=True).block_until_ready()
    np.asarray(P.render_jit(sc, 0, jitter=True))
    plus = jax.jit(lambda x, i: x + i)
    img = P.render_jit(sc, 0, jitter=True)
    plus(img, 0.0).block_until_ready()

    def check(a):
        assert np.all(np.isfinite(a))
        a.mean()

    def dispatch(i):
        out = P.render_jit(sc, i, jitter=True)
        return out

    def copy_only(i):
        x = plus(img, float(i))
        x.block_until_ready()
        t = time.perf_counter()
        np.asarray(x)
        return time.perf_counter() - t

    dev = jax.devices()[0]
    # the image written to page-locked host memory by the program itself (XLA copies it out at the end)
    pinned = jax.sharding.SingleDeviceSharding(dev, memory_kind="pinned_host")
    try:
        render_pinned = jax.jit(P.render, static_argnames=("aovs", "jitter"), out_shardings=pinned)
        np.asarray(render_pinned(sc, 0, jitter=True))
    except Exception as e:  # noqa: BLE001 -- a backend without that memory kind: reported
        print(f"pinned_host output: {type(e).__name__}: {str(e)[:200]}")
        render_pinned = None

    def copy_pinned(i):
        x = plus(img, float(i))
        x.block_until_ready()
        t = time.perf_counter()
        np.asarray(jax.device_put(x, pinned))
        return time.perf_counter() - t

    # other ways to average a pixel's samples (the per-sample radiance is (pixels, spp, 3))
    import jax.numpy as jnp

    def mean_slices(L):
        return sum(L[:, k] for k in range(L.shape[1])) / L.shape[1]

    def mean_matmul(L):
        a = jnp.tile(jnp.eye(3, dtype=L.dtype), (L.shape[1], 1)) / L.shape[1]
        return jnp.matmul(L.reshape(L.shape[0], -1), a, precision=jax.lax.Precision.HIGHEST)

    means = {"mean barrier": lambda L: jnp.mean(jax.lax.optimization_barrier(L), axis=1),
             "mean slices": mean_slices, "mean matmul": mean_matmul,
             "mean sum*": lambda L: jnp.sum(L, axis=1) * (1.0 / L.shape[1])}
    mean_fns = {k: jax.jit(lambda s, i, m=m: m(P.samples(s, i, jitter=True))) for k, m in means.items()}
    ref = np.asarray(P.render_jit(sc, 3, jitter=True)).reshape(-1, 3)
    for k, f in mean_fns.items():
        d = np.abs(np.asarray(f(sc, 3)) - ref)
        print(f"{k}: max |difference| from render's image {d.max():.3e}")

    print(f"{getattr(dev, 'device_kind', dev.platform)}, jax {jax.__version__}; {args.scene} {args.size}², 16 spp, "
          f"depth 4; medians of {args.passes} passes, ms")
    for r in range(args.rounds):
        row = {
            "samples": loop(lambda i: P.samples_jit(sc, i, jitter=True).block_until_ready(), args.passes),
            "render": loop(lambda i: P.render_jit(sc, i, jitter=True).block_until_ready(), args.passes),
            "render+copy": loop(lambda i: np.asarray(P.render_jit(sc, i, jitter=True)), args.passes),
            "+check": loop(lambda i: np.asarray(P.render_jit(sc, i, jitter=True)), args.passes, check),
            "dispatch": loop(dispatch, args.passes, lambda out: out.block_until_ready()),
            "copy": statistics.median(copy_only(i) for i in range(args.passes)),
            "copy via pinned": statistics.median(copy_pinned(i) for i in range(args.passes)),
        }
        for k, f in mean_fns.items():
            row[k] = loop(lambda i, f=f: f(sc, i).block_until_ready(), args.passes)
        if render_pinned is not None:
            row["render to pinned+copy"] = loop(lambda i: np.asarray(render_pinned(sc, i, jitter=True)), args.passes)
        row["render_host"] = loop(lambda i: P.render_host(sc, i, jitter=True), args.passes)
        print(f"round {r}: " + "  ".join(f"{k} {v * 1e3:.3f}" for k, v in row.items()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
