"""Camera rays against the textbook look-at construction, the thin-lens focus property and seeds."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from test_render_util import pinhole_rays

import jax

from jaxrt import camera as C
from jaxrt.camera import Camera

generate_rays = jax.jit(C.generate_rays, static_argnames=("spp", "jitter"))


def _cam(aperture=0.0, focus=5.0, w=8, h=6):
    f = jnp.float32
    return Camera(position=jnp.array([1.0, 2.0, 3.0], f), look_at=jnp.array([0.0, 0.5, -1.0], f),
                  up=jnp.array([0.0, 1.0, 0.0], f), vfov=jnp.asarray(35.0, f), aperture=jnp.asarray(aperture, f),
                  focus_distance=jnp.asarray(focus, f), width=w, height=h)


def test_pinhole_matches_float64_reference():
    o, d = generate_rays(_cam(), spp=1)
    ro, rd = pinhole_rays([1.0, 2.0, 3.0], [0.0, 0.5, -1.0], 35.0, 8, 6)
    np.testing.assert_allclose(np.asarray(o), ro, atol=1e-6)
    np.testing.assert_allclose(np.asarray(d), rd, atol=2e-7)


def test_vertical_field_of_view_spans_vfov():
    # top edge of the top pixel row and bottom edge of the bottom row subtend exactly vfov: with
    # H = 1 row and jitter off the centre ray is the view axis; check the angular extent through
    # pixel centres instead, tan(a) = (1 - 1/H) tan(vfov/2).
    cam = _cam(w=1, h=101)
    _, d = generate_rays(cam, spp=1)
    d = np.asarray(d, np.float64)
    axis = np.array([-1.0, -1.5, -4.0]) / np.linalg.norm([-1.0, -1.5, -4.0])
    ang = np.degrees(np.arccos(np.clip(d @ axis, -1, 1)))
    expect = np.degrees(np.arctan((1 - 1 / 101) * np.tan(np.radians(17.5))))
    assert abs(ang[0] - expect) < 1e-4 and abs(ang[-1] - expect) < 1e-4 and ang[50] < 1e-3


def test_thin_lens_rays_of_a_pixel_meet_on_the_focus_plane():
    cam = _cam(aperture=0.4, focus=4.0, w=3, h=3)
    o, d = generate_rays(cam, spp=64, jitter=False)  # same image point, many lens points
    o = np.asarray(o, np.float64).reshape(9, 64, 3)
    d = np.asarray(d, np.float64).reshape(9, 64, 3)
    axis = np.array([-1.0, -1.5, -4.0]) / np.linalg.norm([-1.0, -1.5, -4.0])
    # intersect each ray with the plane at distance 4 along the axis from the camera position
    c = np.array([1.0, 2.0, 3.0]) + 4.0 * axis
    t = np.sum((c - o) * axis, -1) / np.sum(d * axis, -1)
    p = o + t[..., None] * d
    spread = np.max(np.linalg.norm(p - p[:, :1], axis=-1))
    assert spread < 1e-5
    lens = np.linalg.norm(o - np.array([1.0, 2.0, 3.0]), axis=-1)
    assert lens.max() <= 0.2 + 1e-6 and lens.max() > 0.1  # samples fill the lens disk of radius 0.2


@pytest.mark.parametrize("spp", [4])
def test_jitter_is_reproducible_from_the_seed_and_stays_in_the_pixel(spp):
    cam = _cam(w=4, h=4)
    _, d1 = generate_rays(cam, spp=spp, seed=7)
    _, d2 = generate_rays(cam, spp=spp, seed=7)
    _, d3 = generate_rays(cam, spp=spp, seed=8)
    assert np.array_equal(np.asarray(d1), np.asarray(d2)) and not np.allclose(np.asarray(d1), np.asarray(d3))
    # every sample's direction lies within its pixel's footprint: project to the image plane
    _, corners = generate_rays(_cam(w=4, h=4), spp=1)
    d = np.asarray(d1, np.float64).reshape(4, 4, spp, 3)
    c = np.asarray(corners, np.float64).reshape(4, 4, 3)
    ang_pix = np.degrees(np.arccos(np.clip(np.sum(d * c[:, :, None], -1), -1, 1)))
    assert ang_pix.max() < 35.0 / 4 * 0.75  # within ~half a pixel diagonal of the centre


@pytest.mark.parametrize("aperture, spp", [(0.0, 1), (0.0, 3), (0.3, 2)])
def test_rays_made_in_a_given_order_are_those_rays(aperture, spp):
    """`order` makes the rays at those indices (pinhole centres directly, jittered or lens rays
    from permuted random numbers), with and without a window: the rays made without it, permuted,
    within rounding (the two programs may contract a·b + c into FMAs differently: a few ulps of the
    terms, so of 1 for a unit direction's components, which cancel to ~0 in some)."""
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=0, atol=4 * 2.0**-24)  # noqa: E731
    cam = _cam(aperture, w=13, h=7)
    perm = np.random.default_rng(spp).permutation(13 * 7 * spp)
    o, d = (np.asarray(x) for x in jax.jit(lambda c: C.generate_rays(c, spp, 4))(cam))
    oo, do = (np.asarray(x) for x in jax.jit(lambda c: C.generate_rays(c, spp, 4, order=perm))(cam))
    assert not np.array_equal(d, d[perm])  # the permutation moves rays
    np.testing.assert_array_max_ulp(oo, o[perm], maxulp=4)
    close(do, d[perm])
    win = C.Window(jnp.int32(2), jnp.int32(3), jnp.int32(0), jnp.int32(spp), 4, 6, spp)
    wperm = np.random.default_rng(7).permutation(4 * 6 * spp)
    ow, dw = (np.asarray(x) for x in jax.jit(lambda c, w: C.generate_rays(c, spp, 4, window=w))(cam, win))
    gen = jax.jit(lambda c, w: C.generate_rays(c, spp, 4, window=w, order=wperm))
    owo, dwo = (np.asarray(x) for x in gen(cam, win))
    np.testing.assert_array_max_ulp(owo, ow[wperm], maxulp=4)
    close(dwo, dw[wperm])


@pytest.mark.parametrize("aperture", [0.0, 0.3])
def test_jittered_rays_use_jax_random_uniform_of_each_samples_key(aperture):
    # Sample s of pixel (r, c) is jittered by elements (r, c, 0:2) of jax.random.uniform(k_s, (h, w, 4))
    # with k_s = fold_in(key(seed), s), and with a lens its point on the lens disk by (r, c, 2:4). A pinhole
    # makes only the jitter's numbers (on the CPU), a lens all four: both must be these numbers. Reference:
    # the same rays made from those uniforms in float64 (pixel point -> image plane -> lens).
    h, w, spp, seed = 5, 7, 3, 11
    cam = _cam(aperture, focus=4.0, w=w, h=h)
    o, d = (np.asarray(x, np.float64).reshape(h, w, spp, 3) for x in generate_rays(cam, spp=spp, seed=seed, jitter=True))
    key = jax.random.key(seed)
    u = np.stack([np.asarray(jax.random.uniform(jax.random.fold_in(key, s), (h, w, 4), jnp.float32), np.float64)
                  for s in range(spp)], axis=2)  # (h, w, spp, 4)
    pos, at, up = np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.5, -1.0]), np.array([0.0, 1.0, 0.0])
    f = (at - pos) / np.linalg.norm(at - pos)
    r = np.cross(f, up); r /= np.linalg.norm(r)
    v = np.cross(r, f)
    t = np.tan(np.radians(35.0) / 2)
    cols, rows = np.arange(w)[None, :, None], np.arange(h)[:, None, None]
    x = (2 * (cols + u[..., 0]) / w - 1) * t * w / h
    y = (1 - 2 * (rows + u[..., 1]) / h) * t
    target = pos + 4.0 * (x[..., None] * r + y[..., None] * v + f)  # the pixel point on the focus plane
    lr, phi = 0.5 * aperture * np.sqrt(u[..., 2]), 2 * np.pi * u[..., 3]
    lens = pos + (lr * np.cos(phi))[..., None] * r + (lr * np.sin(phi))[..., None] * v
    ref_d = (target - lens) / np.linalg.norm(target - lens, axis=-1, keepdims=True)
    np.testing.assert_allclose(o, lens, atol=2e-6)
    np.testing.assert_allclose(d, ref_d, atol=2e-6)
