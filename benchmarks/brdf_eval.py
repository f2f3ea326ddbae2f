"""BRDF evaluation throughput: evaluations per second per model on this machine.

    .venv/bin/python benchmarks/brdf_eval.py [--n 1000000] [--repeats 7]

For each model: jit(eval) over N random direction pairs (both in the upper hemisphere, default
parameters), one warm-up call (compilation, excluded), then the median wall time of `repeats`
calls, each ended by block_until_ready. Also jit(sample) (which evaluates f and the mixture pdf)
over N (wo, u) pairs; for glass, sample only (it has no eval).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp

import brdfs


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _median_time(fn, *args, repeats: int) -> tuple[float, float]:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times), compile_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)

    def hemi(key):
        d = jax.random.normal(key, (args.n, 3))
        d = d.at[:, 2].set(jnp.abs(d[:, 2]))
        return d / jnp.linalg.norm(d, axis=-1, keepdims=True)

    wi, wo = hemi(k1), hemi(k2)
    u = jax.random.uniform(k3, (args.n, 2))
    print(f"machine: {_cpu_model()} ({os.cpu_count()} CPUs, {platform.system()}) | python {platform.python_version()} | "
          f"jax {jax.__version__} | devices {jax.devices()}")
    print(f"N = {args.n:,} direction pairs, median of {args.repeats} runs after one warm-up call, float32")
    print(f"{'model':<18} {'eval ms':>9} {'eval Mevals/s':>14} {'sample ms':>10} {'sample Msamples/s':>18} {'compile s':>10}")
    for name in brdfs.names():
        m = brdfs.get(name)
        p = m.params()
        ev_ms = ev_rate = "-"
        comp = 0.0
        if m.eval is not None:
            t, c = _median_time(jax.jit(m.eval), p, wi, wo, repeats=args.repeats)
            ev_ms, ev_rate, comp = f"{t * 1e3:9.1f}", f"{args.n / t / 1e6:14.1f}", c
        t, c = _median_time(jax.jit(m.sample), p, wo, u, repeats=args.repeats)
        print(f"{name:<18} {ev_ms:>9} {ev_rate:>14} {t * 1e3:10.1f} {args.n / t / 1e6:18.1f} {max(comp, c):10.2f}")


if __name__ == "__main__":
    main()
