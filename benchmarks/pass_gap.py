"""Whether host work between passes slows the next GPU pass: the path tracer's Cornell box pass
(`benchmarks/path.py`'s scene, 512², 16 spp, depth 4) in loops of 7 passes, alternating a loop that
copies each pass's per-sample radiance (50 MB) to the host after it (outside the timed region) with a
loop that runs the passes back to back, for 3 rounds; prints each loop's median and its passes.

    python benchmarks/pass_gap.py              # on a GPU; on a CPU it runs but means little
    python benchmarks/pass_gap.py --size 128
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--passes", type=int, default=7)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    exr = bench.sky_exr(Path(tempfile.mkdtemp()) / "sky.exr")
    sc = bench.load("cornell", args.size, 16, 4, exr, "dragon")
    P.samples_jit(sc, 0, jitter=True).block_until_ready()
    for r in range(args.rounds):
        for copy in (True, False):
            ts = []
            for i in range(1, args.passes + 1):
                t = time.perf_counter()
                out = P.samples_jit(sc, i, jitter=True)
                out.block_until_ready()
                ts.append(time.perf_counter() - t)
                if copy:
                    assert np.all(np.isfinite(np.asarray(out)))
            label = "copy between passes" if copy else "back to back"
            print(f"round {r}  {label:20s} median {statistics.median(ts) * 1e3:6.2f} ms  "
                  f"passes {[round(x * 1e3, 2) for x in ts]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
