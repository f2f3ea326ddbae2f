"""The fit G-buffer (`fitting.compact`) must reproduce the full renderer's shading exactly.

Checked on the default scene, where the fitted sphere is also seen in the mirror sphere and the
floor (δ > 0 paths), against `jaxrt.integrators.shade` for random parameter sets of several models.
"""

import jax
import numpy as np
import pytest

import brdfs
from fitting import compact
from fitting import setup as fit_setup
from jaxrt.cli.fit import hidden_params

OVERRIDES = {"camera.width": 64, "camera.height": 48, "render.max_depth": 3}


@pytest.mark.parametrize("name", ["ward"])
def test_compact_shading_equals_full_renderer(name):
    model = brdfs.get(name)
    setup = fit_setup.prepare("spheres", model, object="ward", overrides=[OVERRIDES])
    # the sphere shows up in more pixels than its own (mirror sphere): the tree is really used
    fb = setup.fitbuffer
    assert np.unique(np.asarray(fb.pixel)).size > setup.mask.sum()
    full = fit_setup.shader(setup.model_index, setup.row)
    fast = compact.shader(name)
    for seed in range(3):
        p = model.params(**hidden_params(model, seed))
        a = np.asarray(full(p, (setup.gbuffers, setup.scenes)))
        b = np.asarray(jax.jit(fast)(p, fb))
        np.testing.assert_allclose(b, a, rtol=2e-5, atol=2e-6 * float(a.max()))
