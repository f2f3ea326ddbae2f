"""The same diffuse scene with a point light and hard shadows rendered by Mitsuba 3 (scalar_rgb).

Mitsuba gets the geometry from its own analytic shapes (rectangle, cube), not from jaxrt's
triangles. jaxrt shoots one ray through each pixel centre while Mitsuba averages 64 samples over
the pixel (box filter), so the two agree per pixel only where the image is smooth; at shadow and
silhouette edges they differ by up to the pixel's edge coverage. Stated tolerance: in smooth
pixels (3x3 neighbourhood varies by < 20%, ~85% of the image) every channel within 1% relative
(measured: 0.3%); the image means within 3% (measured 2%, all of it from edge pixels); the
fully shadowed fraction of the image within 2 percentage points.
"""

from __future__ import annotations

import numpy as np
import pytest

from test_render_util import BOX_HI, BOX_LO, BOX_RHO, FLOOR_RHO, LIGHT_I, LIGHT_POS, RES, VIEWS, lab_dict

pytestmark = pytest.mark.mitsuba


def _mitsuba_top(spp=64):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    T = mi.ScalarTransform4f
    v = VIEWS["top"]
    c = (BOX_LO + BOX_HI) / 2
    half = (BOX_HI - BOX_LO) / 2
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective", "fov": v["vfov"], "fov_axis": "y",
            "to_world": T().look_at(origin=v["position"], target=v["look_at"], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": RES[0], "height": RES[1], "rfilter": {"type": "box"},
                     "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "light": {"type": "point", "position": LIGHT_POS.tolist(),
                  "intensity": {"type": "rgb", "value": LIGHT_I.tolist()}},
        # no environment: Mitsuba's direct integrator would light the floor with it (every view ray
        # of this camera hits the floor, so jaxrt's background never shows)
        # the 20 x 20 floor: Mitsuba's rectangle is [-1,1]^2 in xy with normal +z
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": FLOOR_RHO.tolist()}}},
        "box": {"type": "cube", "to_world": T().translate(c.tolist()).scale(half.tolist()),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": BOX_RHO.tolist()}}},
    })
    return np.asarray(mi.render(scene), np.float64)[..., :3]


def test_diffuse_shadow_scene_agrees_with_mitsuba():
    import jaxrt as R
    from jaxrt import scene as S

    ours = np.asarray(R.frame(S.load(lab_dict("top")), aovs=True)[0], np.float64)
    ref = _mitsuba_top()
    assert ref.shape == ours.shape
    pad = np.pad(ours, ((1, 1), (1, 1), (0, 0)), mode="edge")
    win = np.stack([pad[i:i + RES[1], j:j + RES[0]] for i in range(3) for j in range(3)])
    smooth = np.all(win.max(0) <= 1.2 * win.min(0) + 1e-6, axis=-1)
    assert smooth.mean() > 0.6
    rel = np.abs(ours - ref)[smooth] / np.maximum(ref[smooth], 1e-3)
    assert rel.max() < 0.01, f"smooth pixels differ from Mitsuba by up to {rel.max():.3%}"
    assert abs(ours.mean() / ref.mean() - 1) < 0.03
    dark_ours = (ours.sum(-1) < 1e-3).mean()
    dark_ref = (ref.sum(-1) < 1e-3).mean()
    assert dark_ours > 0.05 and abs(dark_ours - dark_ref) < 0.02, (dark_ours, dark_ref)
