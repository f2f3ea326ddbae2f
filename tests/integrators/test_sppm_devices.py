"""SPPM passes split over devices (`jaxrt._devices.sppm_program`, `integrators.sppm.pass_share`).

Each multi-device check runs in a fresh Python with four virtual CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=4``) and prints one JSON line. The reference is
the one-device pass (`integrators.sppm.step`), which traces the same photons and visible points: with
no bucket of its hash grid fuller than CELL_PHOTONS (checked) every photon within a radius is
gathered on either side, so the per-pixel photon counts agree exactly and the fluxes up to the
summation order of the per-device sums.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as R
from jaxrt.integrators import sppm

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def _run(code: str, *args: str, devices: int = 4, timeout: int = 600) -> dict:
    e = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], cwd=ROOT, env=e, capture_output=True,
                       text=True, timeout=timeout, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # about 12 s on the loaded 2-core CPU: two photon-tracing programs compile
def test_photon_shares_are_the_whole_pass_photons():
    """The deposits of the D shares of a pass (`trace_photons(..., share=(d, D))`) are those of the
    whole pass, photon for photon, for a D that does not divide the photon count (the padding
    deposits nothing)."""
    from tests.integrators.test_sppm import diffuse_scene

    scene = R.load_scene(diffuse_scene(width=8, height=6, photons=2001))
    key = jax.random.key(4)
    whole = jax.jit(sppm.trace_photons, static_argnums=2)(scene, key, 2001)
    part = jax.jit(lambda s, k, d: sppm.trace_photons(s, k, 2001, share=(d, 4)))
    shares = [part(scene, key, jnp.int32(d)) for d in range(4)]  # 501 photons each: 3 padded
    steps = scene.settings.max_depth - 1  # deposits after 1 .. max_depth - 1 scatterings

    def joined(name):
        return np.concatenate([np.asarray(getattr(x, name)).reshape(steps, 501, -1) for x in shares], axis=1)

    valid = np.asarray(whole.valid).reshape(steps, 2001)
    v = joined("valid")[..., 0]
    assert not v[:, 2001:].any() and not joined("power")[:, 2001:].any()  # padding: no deposit, no power
    np.testing.assert_array_equal(v[:, :2001], valid)
    for name in ("p", "wi", "power", "bounce"):  # the deposits (dead photons' slots hold anything)
        np.testing.assert_allclose(joined(name)[:, :2001][valid], np.asarray(getattr(whole, name)).reshape(
            steps, 2001, -1)[valid], rtol=1e-6, atol=1e-6, err_msg=name)
    assert np.asarray(whole.valid).sum() > 50  # photons do scatter and deposit


_PASSES = r"""
import json, sys
import numpy as np
import jax, jax.numpy as jnp
sys.path.insert(0, sys.argv[1])
import test_sppm as T
import jaxrt as R
from jaxrt import render_tiles
from jaxrt.integrators import sppm

kind, n_dev, photons, radius = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
make = T.glass_caustic_scene if kind == "glass" else T.diffuse_scene
# photon_aim 0: aimed photons crowd the caustic's grid cells past CELL_PHOTONS at this photon count, and
# a subsampled bucket is a different (unbiased) estimate on each device, not the same numbers
s = R.load_scene(make(width=16, height=12, photons=photons, radius=radius, spp=3, photon_aim=0.0))

@jax.jit
def fullest(scene, state):
    # the most deposits in one bucket that a visible point of the one-device pass reads (at least
    # CELL_PHOTONS: the subsampling weight n / CELL_PHOTONS is 1 below it)
    kvp, kph, kgrid = sppm.pass_keys(scene, state.passes)
    vp, _, _ = sppm.visible_points(scene, kvp, state.samples, state.passes)
    state, cell = sppm._radii(state, vp)
    g = sppm.build_grid(sppm.trace_photons(scene, kph, state.photons), cell, kgrid)
    _, _, scale = sppm._candidates(g, vp["p"], state.r2)
    return jnp.round(jnp.max(jnp.where(vp["found"][:, None], scale, 1.0)) * sppm.CELL_PHOTONS).astype(jnp.int32)

st, full = sppm.start(s), []
for _ in range(3):
    full.append(int(fullest(s, st)))
    st = sppm.step(s, st)
one = np.asarray(st.image, np.float64)
solo = render_tiles.render(s, memory="4G", devices=1)
many = np.asarray(render_tiles.render(s, memory="4G", devices=n_dev), np.float64)
d = np.abs(many - one)
print(json.dumps(dict(full=full, solo=bool(np.array_equal(solo, np.asarray(st.image))), max=float(one.max()),
                      diff=float(d.max()), beyond=float(np.mean(d > 1e-5 * (one.max() + np.abs(one)))),
                      m=float(np.mean(np.asarray(st.n))), tau=float(np.asarray(st.tau).max()))))
"""


@pytest.mark.slow  # 25-65 s on the loaded 2-core CPU: the one-device pass, a grid probe, the sharded pass
@pytest.mark.parametrize("kind, devices, photons, radius", [
    ("diffuse", 4, 3001, 0.2),  # point lights and an emissive quad; 4 does not divide 3001
    ("glass", 3, 2002, 0.1),  # an area light focused by a glass ball; 3 does not divide 2002
])
def test_sppm_passes_on_devices_equal_the_one_device_passes(kind, devices, photons, radius):
    out = _run(_PASSES, str(HERE), kind, str(devices), str(photons), str(radius))
    assert max(out["full"]) <= sppm.CELL_PHOTONS, out  # no bucket subsampled: the gathers must agree
    assert out["solo"]  # devices=1 is the one-device pass, bit for bit
    assert out["m"] > 0.3 and out["tau"] > 0 and out["max"] > 0.05, out  # photons are found: not a direct-only image
    # the same photons and visible points: per-pixel fluxes summed in another order (a few ulps)
    assert out["beyond"] == 0.0 and out["diff"] <= 1e-5 * out["max"], out


def test_bad_devices_of_an_sppm_render_are_one_line_errors():
    """A device count this host does not have is refused in one line before any pass is compiled."""
    from jaxrt import render_tiles
    from jaxrt.errors import InputError
    from tests.integrators.test_sppm import diffuse_scene

    scene = R.load_scene(diffuse_scene(width=8, height=6, photons=64))
    n = len(jax.devices())
    for bad in (n + 1, 0, "two"):
        with pytest.raises(InputError) as e:
            render_tiles.render(scene, memory="1G", devices=bad, should_stop=lambda: pytest.fail("a pass ran"))
        assert "devices=" in str(e.value) and "\n" not in str(e.value), str(e.value)
