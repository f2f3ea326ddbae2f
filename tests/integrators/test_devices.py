"""Renders spread over several devices (`jaxrt._devices`, `render_tiles.render(devices=...)`).

The sharded renders run in one fresh Python with four virtual CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=4``), which checks everything that needs several
devices and prints one JSON line; the tests below read their parts of it. References: the
one-device renderer (`integrators.frame`, the whole image in one compiled call) and the renders on
other device counts. On any number of devices ≥ 2 the per-device program is the same partitioned
module, so those images are equal bit for bit; against one device they differ by the rounding of
a different XLA module (`jaxrt._devices`), held to the tiled renderer's tolerance.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jaxrt import render_tiles
from jaxrt import scene as S
from jaxrt.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"

_MULTI = r"""
import contextlib, io, json, sys, tempfile
from pathlib import Path
import numpy as np
import jax
sys.path.insert(0, sys.argv[1])
import test_tiles as T
from jaxrt import cli, image, integrators, render_tiles, scene as S
from jaxrt.errors import InputError

def close(a, b):
    # the fraction of pixels beyond 1e-4 relative, and the mean |difference| over the mean value
    a, b = (x.reshape(x.shape[0], x.shape[1], -1).astype(np.float64) for x in (a, b))
    d = np.abs(a - b).max(-1)
    rel = d / np.maximum(np.abs(b).max(-1), 1e-2)
    return {"beyond": float(np.mean(rel > 1e-4)), "mean": float(d.mean() / max(np.abs(b).mean(), 1e-3))}

class Bar:
    total, done = 0, 0
    def update(self, n): self.done += n
    def set_description_str(self, s): pass

out = {"devices": len(jax.devices())}

# Whitted: the spheres scene, 40x30: 40 tiles, which 3 devices do not divide; the last row of tiles overlaps
sc = S.load("spheres", overrides={"camera.width": 40, "camera.height": 30})
p4 = render_tiles.plan(sc, memory="8G", devices=4)
p3 = render_tiles.plan(sc, memory="8G", devices=3)
bar = Bar()
w4 = render_tiles.render(sc, use_plan=p4, progress=bar)
w3 = render_tiles.render(sc, use_plan=p3)
w1 = np.asarray(integrators.frame(sc))
out["whitted"] = dict(shape4=p4.shape, shape3=p3.shape, tiles=p4.tiles, devices4=len(p4.devices),
                      bar=[bar.total, bar.done], equal43=bool(np.array_equal(w4, w3)), max=float(w1.max()),
                      vs1=close(w4, w1), finite=bool(np.isfinite(w4).all()))

# path tracing with AOVs at 4 spp: 15 tiles, so the last call leaves one of the 4 devices without a tile
ps = S.load(T.path_doc(w=24, h=18, spp=4))
q4 = render_tiles.plan(ps, memory="8G", aovs=True, devices=4)
i4, a4 = render_tiles.render(ps, aovs=True, use_plan=q4)
i1, a1 = integrators.frame(ps, aovs=True)
i1 = np.asarray(i1)
out["path"] = dict(shape=q4.shape, tiles=q4.tiles, spp=ps.settings.spp, max=float(i1.max()),
                   vs1=close(i4, i1), ids=float(np.mean(a4["object_id"] != np.asarray(a1["object_id"]))),
                   depth=close(a4["depth"], np.asarray(a1["depth"])))

# the budget is per device, and on a CPU the virtual devices share it: a budget with room for about
# 4 x 200 pixels gives tiles of at most 200 pixels on 4 devices
big = S.load("spheres", overrides={"camera.width": 400, "camera.height": 300})
cost = sum(render_tiles.tile_cost(big))
fixed = render_tiles.plan(big, memory="8G", devices=4).fixed
pb = render_tiles.plan(big, memory=fixed + 4 * 200 * cost, devices=4)
out["budget"] = dict(pixels=pb.shape[0] * pb.shape[1], tile_room=pb.tile_room, cost=cost)

# bad values: one line naming the argument or the flag and what is allowed
errs = {}
d0 = jax.devices()[0]
for name, bad in [("zero", 0), ("five", 5), ("negative", -1), ("bool", True), ("text", "x"), ("empty", []),
                  ("twice", [d0, d0]), ("float", 2.5)]:
    try:
        render_tiles.plan(sc, memory="8G", devices=bad)
        errs[name] = None
    except InputError as e:
        errs[name] = str(e)
out["errors"] = errs
cli_errs = {}
for bad in ("0", "5", "abc"):
    f = io.StringIO()
    with contextlib.redirect_stderr(f):
        rc = cli.main(["render", "spheres", "--width", "40", "--height", "30", "-q", "--devices", bad,
                       "-o", str(Path(tempfile.mkdtemp()) / "x.exr")])
    cli_errs[bad] = [rc, f.getvalue()]
out["cli_errors"] = cli_errs

# the CLI on 2 devices writes the image of 4 devices bit for bit
d = Path(tempfile.mkdtemp())
rc = cli.main(["render", "spheres", "--width", "40", "--height", "30", "-q", "--devices", "2", "-o", str(d / "a.exr")])
exr = image.read_exr(d / "a.exr")
out["cli"] = dict(rc=rc, equal=bool(np.array_equal(exr, w4)))
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def multi():
    """The four-device checks, run once (six compilations)."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(_MULTI), str(TESTS)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["devices"] == 4
    return out


def _within_tiling_tolerance(c):
    # `tests/test_tiles.py`'s bound for two program shapes of the same arithmetic: 99 % of the pixels
    # within 1e-4 relative and the mean difference at rounding level; wrong tiles, random numbers or
    # pixels fail both (their noise differs everywhere)
    assert c["beyond"] <= 0.01 and c["mean"] <= 1e-5, c


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_whitted_on_4_and_3_devices_is_one_image_and_the_one_device_image(multi):
    w = multi["whitted"]
    assert w["devices4"] == 4 and w["shape4"] == w["shape3"] and w["finite"] and w["max"] > 0.1
    assert w["tiles"] % 3 and w["tiles"] >= 4 * 4  # 3 devices do not divide the tiles; several per device
    assert w["equal43"]  # the same pixels bit for bit on any number of devices >= 2
    _within_tiling_tolerance(w["vs1"])
    assert w["bar"] == [w["tiles"], w["tiles"]]  # progress over tiles


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_path_tracing_with_aovs_on_4_devices_with_an_idle_device_in_the_last_call(multi):
    p = multi["path"]
    assert p["shape"][2] == p["spp"] == 4 and p["tiles"] % 4 and p["max"] > 0.1  # all samples in a tile
    _within_tiling_tolerance(p["vs1"])
    assert p["ids"] <= 0.01
    _within_tiling_tolerance(p["depth"])


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_the_budget_is_shared_by_virtual_cpu_devices(multi):
    b = multi["budget"]
    assert b["pixels"] <= 200 and b["pixels"] * b["cost"] <= b["tile_room"]


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_bad_device_values_are_one_line_input_errors(multi):
    errs = multi["errors"]
    for name, msg in errs.items():
        assert msg is not None and "\n" not in msg and msg.startswith("devices="), (name, msg)
    for name in ("zero", "five", "negative", "text", "bool", "float"):
        assert "from 1 to 4" in errs[name] or "1 or more" in errs[name], errs[name]
    assert "distinct devices" in errs["twice"] and "distinct devices" in errs["empty"]
    for bad, (rc, err) in multi["cli_errors"].items():
        err = err.strip()
        assert rc == 2 and err.startswith("jaxrt render: error: --devices") and "\n" not in err, (bad, err)
    assert "from 1 to 4" in multi["cli_errors"]["5"][1]


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_cli_devices_2_writes_the_4_device_image(multi):
    assert multi["cli"] == {"rc": 0, "equal": True}


# ---- one device (this process) ----------------------------------------------------------------------

def test_one_device_keeps_the_one_device_renderer():
    """With the default device alone (or devices=1) the plan is the one-device plan: no mesh, the
    whole frame when it fits, and `devices` beyond the host's count is refused before any work."""
    import jax

    sc = S.load("spheres", overrides={"camera.width": 40, "camera.height": 30})
    n = len(jax.devices())
    if n != 1:
        pytest.skip("this process has several devices")
    for d in (None, 1, "all", [jax.devices()[0]]):
        p = render_tiles.plan(sc, memory="8G", devices=d)
        assert p.devices == () and p.shape is None and p.tiles == 1
    with pytest.raises(InputError, match=r"^devices=2: must be 'all' or a number from 1 to 1"):
        render_tiles.plan(sc, memory="8G", devices=2)
    import jaxrt

    with pytest.raises(InputError, match=r"^devices=0"):
        jaxrt.render(sc, devices=0)
