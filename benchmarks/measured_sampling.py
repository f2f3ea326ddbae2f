"""Variance of the measured models' importance sampler against cosine-weighted sampling.

    JAXRT_DATA=../shared/data .venv/bin/python benchmarks/measured_sampling.py [--n 262144] [--angles 5 25 45 65 85]
        [--materials all|merl|rgl|nielsen] [--json out.json]

For each neural material (brdfs.nbrdf, Sztrajman et al. 2021) and view angle θo, the per-sample
variance of the one-sample estimator of the directional albedo (channel mean of f cos θi / pdf):

    ours:    wi ~ the model's sampler (cosine + tabulated half-vector lobe)   Var = E[w²] - a²
    cosine:  wi ~ cos θi / π                                                  Var = π ∫ f² cos θi dω - a²

Both second moments are estimated from the same n samples of *our* sampler (the cosine one as
E[(f cos)² / (pdf_cos pdf_ours)], an unbiased importance-sampling estimate), because sampling a
near-mirror lobe with cosine samples hits the peak too rarely for its sample variance to converge.
The ratio Var_cos / Var_ours is the factor by which cosine sampling needs more samples for the same
noise. Also printed: the time per sample (jit(sample) with eval inside) of both samplers, so that the
gain per unit of time can be judged.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from brdfs import _common as C
from brdfs import _measured_sampling as S
from brdfs import measured, nbrdf

NAMED = ("merl/chrome", "merl/alum-bronze", "merl/blue-acrylic", "merl/gold-metallic-paint", "merl/white-paint",
         "rgl/cg_sunflower_rgb", "nielsen/paintedmetal")


@jax.jit
def _moments(p, wo, u):
    """(albedo, E_ours[w²], E_cos[w²]) of the channel-mean estimator at one view direction."""
    m = nbrdf.MODEL
    wi, _, pdf = m.sample(p, wo, u)
    f = jnp.mean(m.eval(p, wi, wo), axis=-1)
    ci = jnp.maximum(wi[..., 2], 0.0)
    fc = f * ci
    ok = pdf > 0
    wl = jnp.where(ok, C.safe_div(fc, pdf), 0.0)
    pcos = ci / math.pi
    m2cos = jnp.where(ok & (pcos > 0), C.safe_div(fc * fc, pcos * pdf), 0.0)
    return jnp.mean(wl), jnp.mean(wl * wl), jnp.mean(m2cos)


def _time_per_sample(p, wo, n, cosine: bool) -> float:
    u = jax.random.uniform(jax.random.PRNGKey(9), (n, 2))

    def ours(u):
        return nbrdf.MODEL.sample(p, wo, u)[1]

    def cos(u):
        wi = C.cosine_sample(u)
        return nbrdf.MODEL.eval(p, wi, wo) * math.pi

    fn = jax.jit(cos if cosine else ours)
    jax.block_until_ready(fn(u))
    t = []
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(u))
        t.append(time.perf_counter() - t0)
    return float(np.median(t)) / n


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1 << 18)
    # (between the sampler's view-angle nodes, where its tables are interpolated)
    ap.add_argument("--angles", type=float, nargs="+", default=[5.0, 25.0, 45.0, 65.0, 85.0])
    ap.add_argument("--materials", default="all", choices=["all", "merl", "rgl", "nielsen"])
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    names = measured.names(None if a.materials == "all" else a.materials)
    u = jax.random.uniform(jax.random.PRNGKey(0), (a.n, 2))
    rows = {}
    for name in names:
        _, p = measured.load(name)
        r = []
        for th in a.angles:
            t = math.radians(th)
            wo = jnp.array([math.sin(t), 0.0, math.cos(t)], jnp.float32)
            alb, m2, m2c = (float(x) for x in _moments(p, wo, u))
            v_ours, v_cos = max(m2 - alb**2, 0.0), max(m2c - alb**2, 0.0)
            r.append({"theta_o": th, "albedo": alb, "var_ours": v_ours, "var_cos": v_cos,
                      "ratio": v_cos / v_ours if v_ours > 0 else float("inf"),
                      "ps": float(S.lobe_prob(p, wo))})
        rows[name] = r
    print(f"variance of the albedo estimator (channel mean), n = {a.n} samples per material and angle")
    print(f"{'material':32s} " + " ".join(f"{'θo=' + format(th, 'g') + '°':>22s}" for th in a.angles))
    print(f"{'':32s} " + " ".join(f"{'a  Var_cos/Var_ours':>22s}" for _ in a.angles))
    for name in [n for n in NAMED if n in rows]:
        print(f"{name:32s} " + " ".join(f"{x['albedo']:8.3f} {x['ratio']:12.3g} " for x in rows[name]))
    ratios = np.array([[x["ratio"] for x in r] for r in rows.values()])
    print(f"\nall {len(rows)} materials: Var_cos / Var_ours per view angle")
    for k, th in enumerate(a.angles):
        q = np.percentile(ratios[:, k], [0, 25, 50, 75, 100])
        worse = int(np.sum(ratios[:, k] < 1))
        print(f"  θo = {th:4g}°: min {q[0]:.3g}  q25 {q[1]:.3g}  median {q[2]:.3g}  q75 {q[3]:.3g}  max {q[4]:.3g}"
              f"  (worse than cosine: {worse})")
    _, p = measured.load(names[0] if "merl/alum-bronze" not in names else "merl/alum-bronze")
    wo = jnp.array([math.sin(0.5), 0.0, math.cos(0.5)], jnp.float32)
    t_o, t_c = _time_per_sample(p, wo, a.n, False), _time_per_sample(p, wo, a.n, True)
    print(f"\ntime per sample on {jax.devices()[0].platform}: ours {t_o * 1e9:.0f} ns, cosine {t_c * 1e9:.0f} ns "
          f"(ratio {t_o / t_c:.2f})")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"n": a.n, "rows": rows, "ns_per_sample": {"ours": t_o * 1e9, "cosine": t_c * 1e9}}, fh,
                      indent=1)


if __name__ == "__main__":
    main()
