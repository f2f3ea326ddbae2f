"""Whitted shadow rays through glass carry the Fresnel transmittance (jaxrt.shading.shadows).

A point light above a thin horizontal glass slab over a Lambert floor, seen from a camera between
slab and floor: under the slab each floor pixel is the unshadowed radiance ρ/π·I·cosθ/d² times
T(θ)², T = 1 − F(θ) for the slab's two parallel faces, with F from the Fresnel equations or
Schlick's approximation written out here in float64 (independent of brdfs.glass).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_glass_fresnel import fresnel_exact, schlick
from test_render_util import pinhole_rays

import jaxrt as R
from jaxrt import scene as S
from jaxrt.errors import InputError
from jaxrt.integrators import whitted

N_T, RHO, LIGHT, INTENSITY, W, H = 1.5, 0.7, np.array([0.3, 1.8, -0.2]), 5.0, 24, 16
SLAB_Y, SLAB_T, SLAB_HALF = 1.0, 0.05, 1.0  # bottom face height, thickness, half width
CAM = dict(position=[0.0, 0.9, 0.0], look_at=[0.0, 0.0, 0.0], up=[0.0, 0.0, -1.0], vfov=150.0)


def scene_dict(fresnel=None, glass_shadows=None):
    glass = {"model": "glass", "n_t": N_T}
    if fresnel is not None:
        glass["fresnel"] = fresnel
    render = {"max_depth": 2}
    if glass_shadows is not None:
        render["glass_shadows"] = glass_shadows
    return {
        "camera": dict(CAM, width=W, height=H),
        "lights": [{"position": LIGHT.tolist(), "intensity": INTENSITY}],
        "materials": {"floor": {"model": "lambert", "rho_d": RHO}, "glass": glass},
        "objects": [
            {"name": "floor", "primitive": "plane", "size": [20.0, 20.0], "material": "floor"},
            {"name": "slab", "primitive": "box", "size": [2 * SLAB_HALF, SLAB_T, 2 * SLAB_HALF],
             "translate": [0.0, SLAB_Y + SLAB_T / 2, 0.0], "material": "glass"},
        ],
        "render": render,
    }


def _floor():
    """Per pixel: unshadowed floor radiance, cos θ of the light's direction, and whether the shadow
    ray crosses both horizontal faces of the slab well inside them."""
    o, d = pinhole_rays(CAM["position"], CAM["look_at"], CAM["vfov"], W, H, up=CAM["up"])
    t = -o[:, 1] / d[:, 1]
    p = o + t[:, None] * d
    wl = LIGHT - p
    dist = np.linalg.norm(wl, axis=1)
    wl = wl / dist[:, None]
    cos = wl[:, 1]
    unshadowed = RHO / np.pi * INTENSITY * cos / dist**2
    under = np.ones(len(p), bool)
    for y in (SLAB_Y, SLAB_Y + SLAB_T):
        q = p + ((y - p[:, 1]) / wl[:, 1])[:, None] * wl
        under &= (np.abs(q[:, 0]) < SLAB_HALF - 0.02) & (np.abs(q[:, 2]) < SLAB_HALF - 0.02)
    return unshadowed, cos, under & (t > 0)


@pytest.mark.parametrize("fresnel", ["exact", "schlick"])
def test_floor_under_a_glass_slab_gets_the_light_times_t_squared(fresnel):
    unshadowed, cos, under = _floor()
    assert under.sum() > 0.2 * under.size and (~under).sum() > 20
    assert np.degrees(np.arccos(cos[under])).max() > 40  # a range of incidences, not just normal
    f = fresnel_exact(cos, N_T) if fresnel == "exact" else schlick(cos, N_T)
    expected = np.where(under, unshadowed * (1 - f) ** 2, unshadowed)
    img = np.asarray(R.frame(S.load(scene_dict(fresnel))), np.float64).reshape(-1, 3)
    # pixels whose shadow ray passes the slab's edges are left out; the rest are lit or transmitted
    near_edge = ~under & (_floor_near_slab())
    ok = ~near_edge
    err = np.abs(img[ok] - expected[ok, None]) / expected[ok, None]
    assert err.max() < 2e-5, err.max()


def _floor_near_slab(margin=0.04):
    o, d = pinhole_rays(CAM["position"], CAM["look_at"], CAM["vfov"], W, H, up=CAM["up"])
    p = o + (-o[:, 1] / d[:, 1])[:, None] * d
    wl = LIGHT - p
    wl = wl / np.linalg.norm(wl, axis=1, keepdims=True)
    near = np.zeros(len(p), bool)
    for y in (SLAB_Y, SLAB_Y + SLAB_T):
        q = p + ((y - p[:, 1]) / wl[:, 1])[:, None] * wl
        near |= (np.abs(q[:, 0]) < SLAB_HALF + margin) & (np.abs(q[:, 2]) < SLAB_HALF + margin)
    return near


def test_opaque_option_restores_opaque_glass_shadows():
    _, _, under = _floor()
    img = np.asarray(R.frame(S.load(scene_dict(glass_shadows="opaque"))), np.float64).reshape(-1, 3)
    assert np.all(img[under] == 0.0)
    assert np.all(img[~_floor_near_slab()] > 0)


def test_scenes_without_glass_keep_boolean_shadows_bit_identical():
    # the slab made opaque (Lambert): no glass, so the shadow test is the unchanged boolean any-hit one
    doc = scene_dict()
    doc["materials"]["glass"] = {"model": "lambert", "rho_d": 0.2}
    sc = S.load(doc)
    assert not whitted.transmits(sc)
    assert jax.eval_shape(whitted.trace, sc).visible.dtype == bool
    img = np.asarray(R.frame(sc))
    assert np.array_equal(img, np.asarray(R.frame(S.load(dict(doc, render={"max_depth": 2,
                                                                         "glass_shadows": "opaque"})))))
    # and its shadow is where the geometry puts it: black under the slab, lit away from it
    unshadowed, _, under = _floor()
    floor = img.reshape(-1, 3)
    assert np.all(floor[under] == 0.0) and np.allclose(floor[~_floor_near_slab()], unshadowed[~_floor_near_slab(), None],
                                                      rtol=2e-5)


def test_bad_glass_shadows_is_a_one_line_error():
    with pytest.raises(InputError) as e:
        S.load(scene_dict(glass_shadows="translucent"))
    msg = str(e.value)
    assert "\n" not in msg and "render" in msg and "glass_shadows" in msg, msg
