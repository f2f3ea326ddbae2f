"""How many paths each compacted bounce of a GPU pass shades, measured on any machine: the share of a
pass's paths alive when each compacted bounce starts (`jaxrt.integrators.path._compacted`), and the
chunks a pass of `path.GPU_CHUNKS` chunks would run for them (a chunk costs its whole size, dead or
alive), with each bounce tracing its own rays first and with the rays traced where they are made
(`path.GPU_TRACE_AHEAD`).

    JAXRT_DATA=... python benchmarks/path_live.py --size 64        # the environment-lit dragon
    JAXRT_DATA=... python benchmarks/path_live.py --scene cornell

The pass runs the GPU's route on whatever backend JAX has (`path._on_cpu` answered False, as the tests
do), so its compaction is the GPU's; scenes are `benchmarks/path.py`'s (16 spp, max_depth 4). The counts
are read with `jax.debug.callback` while the pass runs; the images of both routes are printed (means).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import path as bench  # noqa: E402  (benchmarks/path.py: the scenes)
from jaxrt.integrators import path as P  # noqa: E402


def live_shares(sc, ahead: bool) -> tuple[list[float], float]:
    """(share of the pass's paths alive at each compacted bounce, image mean) with GPU_TRACE_AHEAD = ahead."""
    counts = []
    saved = P._on_cpu, P._compacted, P.GPU_TRACE_AHEAD, P.GPU_COMPACT_MIN_TRIANGLES
    orig = P._compacted

    def counted(fn, carry, *a):
        jax.debug.callback(lambda n: counts.append(int(n)), jnp.sum(carry[2]))
        return orig(fn, carry, *a)

    try:
        P._on_cpu, P._compacted, P.GPU_TRACE_AHEAD = (lambda: False), counted, ahead
        P.GPU_COMPACT_MIN_TRIANGLES = 0  # every scene compacted, as the GPU compacts meshes
        L = jax.jit(lambda s: P.samples(s, 1, jitter=True))(sc)
        L.block_until_ready()
    finally:
        P._on_cpu, P._compacted, P.GPU_TRACE_AHEAD, P.GPU_COMPACT_MIN_TRIANGLES = saved
    n = L.shape[0] * L.shape[1]
    return [c / n for c in counts], float(L.mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="dragon", choices=["cornell", "dragon"])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--chunks", type=int, default=P.GPU_CHUNKS, help="chunks of a pass (path.GPU_CHUNKS)")
    args = ap.parse_args(argv)
    exr = bench.sky_exr(Path(tempfile.mkdtemp()) / "sky.exr")
    sc = bench.load(args.scene, args.size, 16, 4, exr, "dragon")
    for ahead in (False, True):
        shares, mean = live_shares(sc, ahead)
        chunks = [math.ceil(s * args.chunks - 1e-9) for s in shares]
        print(f"{args.scene} {args.size}², trace ahead {str(ahead):5s}: live at each compacted bounce "
              f"{' '.join(f'{s:.3f}' for s in shares)}; chunks in a {args.chunks}-chunk pass {chunks} = "
              f"{sum(chunks)}; image mean {mean:.5f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
