"""SPPM photon aiming (`[render] photon_aim`, jaxrt.integrators.sppm): photons sent towards the glass
and mirror objects from the mixture p(ω) = (1 − f)·p_emit(ω) + f·p_cone(ω).

Independent references: the solid-angle measure of the sphere (4π) for the density's integral; the
mixture's bin probabilities written out in closed form (uniform sphere + uniform cone, the cone's
half-angle from the scene's numbers) for the sampled directions' histogram; the unaimed photons
(f = 0) for the flux reaching the glass and for the SPPM image; a float64 ray/sphere test of
cosine-distributed photons from the lamp for that flux.
"""

from __future__ import annotations

import math
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import jaxrt as R
from jaxrt.errors import InputError
from jaxrt.integrators import sppm

BALL_C, BALL_R = (0.0, 0.5, 0.0), 0.5
LAMP_Y, LAMP_SIDE, LAMP_L = 2.5, 0.2, 40.0
POINT = (0.0, 2.5, -1.5)


def glass_scene(width=16, height=12, point=False, lamp=True, glass=True, **render):
    """A glass (or Lambert) ball on a Lambert floor under a small emissive square and/or a point light."""
    materials = {"floor": {"model": "lambert", "rho_d": 0.7},
                 "ball": {"model": "glass", "n_t": 1.5} if glass else {"model": "lambert", "rho_d": 0.5}}
    objects = [{"name": "floor", "primitive": "plane", "size": [6.0, 6.0], "material": "floor"},
               {"name": "ball", "primitive": "sphere", "radius": BALL_R, "subdivisions": 3,
                "translate": list(BALL_C), "material": "ball"}]
    if lamp:
        materials["lamp"] = {"model": "lambert", "rho_d": 0.0, "emission": LAMP_L}
        objects.append({"name": "lamp", "primitive": "plane", "size": [LAMP_SIDE, LAMP_SIDE],
                        "rotate": [180.0, 0.0, 0.0], "translate": [0.0, LAMP_Y, -1.5], "material": "lamp"})
    return {
        "camera": {"position": [0.0, 2.0, 3.0], "look_at": [0.0, 0.3, -0.3], "vfov": 40.0,
                   "width": width, "height": height},
        "lights": [{"position": list(POINT), "intensity": [1.0, 1.0, 1.0]}] if point else [],
        "materials": materials, "objects": objects,
        "render": {"integrator": "sppm", "max_depth": 4, **render},
    }


def _uniforms(n, seed):
    k = jax.random.key(seed)
    return jnp.concatenate([jax.random.uniform(k, (n, 6)), jax.random.uniform(jax.random.fold_in(k, 1), (n, 4))], 1)


# ---------------------------------------------------------------------------------------------- settings

def test_default_aims_only_with_delta_objects():
    assert R.load_scene(glass_scene()).settings.photon_aim == sppm.DEFAULT_PHOTON_AIM == 0.5
    assert R.load_scene(glass_scene(glass=False)).settings.photon_aim == 0.0
    mirror = glass_scene(glass=False)
    mirror["materials"]["ball"]["delta"] = 0.3
    assert R.load_scene(mirror).settings.photon_aim == 0.5
    assert R.load_scene(glass_scene(photon_aim=0.25)).settings.photon_aim == 0.25
    assert R.load_scene(glass_scene(photon_aim=0)).settings.photon_aim == 0.0


@pytest.mark.parametrize("value", [-0.1, 1.0, 1.5, "half", float("nan")])
def test_bad_photon_aim_is_a_one_line_error(value):
    with pytest.raises(InputError) as e:
        R.load_scene(glass_scene(photon_aim=value))
    msg = str(e.value)
    assert "\n" not in msg and "photon_aim" in msg and "render" in msg


def test_cli_bad_photon_aim_exit_2(tmp_path):
    r = subprocess.run([sys.executable, "-m", "jaxrt.cli", "render", "caustics", "--photon-aim", "1",
                        "-o", str(tmp_path / "x.exr")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "photon_aim" in lines[0]
    assert not (tmp_path / "x.exr").exists()


def test_targets_are_the_delta_objects_bounding_spheres():
    t = sppm.aim_targets(R.load_scene(glass_scene()))
    np.testing.assert_array_equal(np.asarray(t.active), [False, True, False])
    np.testing.assert_allclose(np.asarray(t.centre)[1], BALL_C, atol=1e-5)
    np.testing.assert_allclose(float(t.radius[1]), BALL_R, rtol=1e-5)  # the icosphere's vertices lie on it


# ---------------------------------------------------------------------------------------------- the density

def test_mixture_pdf_integrates_to_one():
    """∫ p(ω) dω over the sphere = 1 for a point light and an area light (cos θ/π about its normal),
    with two overlapping cones, a third containing the origin (the whole sphere) and an inactive
    one: Monte Carlo over 2^21 uniform directions, 4π·mean(p), within 4 standard errors + 1e-4."""
    t = sppm.AimTargets(centre=jnp.array([[0.0, 0.0, 3.0], [0.3, 0.0, 2.5], [0.1, 0.0, 0.0], [5.0, 5.0, 5.0]]),
                        radius=jnp.array([0.4, 1.2, 0.5, 1.0]), active=jnp.array([True, True, False, False]))
    t_in = sppm.AimTargets(t.centre, t.radius, jnp.array([True, True, True, False]))
    n = 1 << 21
    w = jax.random.normal(jax.random.key(0), (n, 3))
    w = w / jnp.linalg.norm(w, axis=1, keepdims=True)
    x = jnp.zeros((n, 3))
    normal = jnp.broadcast_to(jnp.array([0.0, 0.6, 0.8]), (n, 3))
    for targets in (t, t_in):
        for nrm in (None, normal):
            p = np.asarray(jax.jit(sppm.aim_pdf, static_argnums=1)(targets, 0.5, x, nrm, w), np.float64)
            v = 4 * math.pi * p
            assert abs(v.mean() - 1.0) < 4 * v.std() / math.sqrt(n) + 1e-4, (v.mean(), v.std() / math.sqrt(n))


def test_aimed_point_light_directions_match_the_mixture():
    """Directions of a point light's photons (f = 0.5, one glass ball): histogram in (cos to the
    ball's centre, azimuth) bins against the closed-form mixture (1 − f)/(4π) + f·[cos ≥ cos θ_max]
    / (2π(1 − cos θ_max)), sin θ_max = R / distance; Pearson chi-square p > 1e-4."""
    scene = R.load_scene(glass_scene(point=True, lamp=False))
    n, f = 200_000, 0.5
    o, d, power = jax.jit(sppm.emit)(scene, _uniforms(n, 2))
    d, power = np.asarray(d, np.float64), np.asarray(power, np.float64)
    axis = np.subtract(BALL_C, POINT)
    dist = np.linalg.norm(axis)
    axis /= dist
    c_max = math.sqrt(1 - (BALL_R / dist) ** 2)
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    c = d @ axis
    phi = np.arctan2(d @ e2, d @ e1) % (2 * math.pi)
    c_edges = np.concatenate([np.linspace(-1, c_max, 9), np.linspace(c_max, 1, 6)[1:]])
    n_phi = 6
    obs, _, _ = np.histogram2d(c, phi, bins=[c_edges, np.linspace(0, 2 * math.pi, n_phi + 1)])
    lo, hi = c_edges[:-1], c_edges[1:]
    in_cone = np.clip(hi, c_max, 1) - np.clip(lo, c_max, 1)
    p_bin = ((1 - f) * (hi - lo) / 2 + f * in_cone / (1 - c_max)) / n_phi
    expected = np.repeat(p_bin[:, None], n_phi, 1) * n
    stat = np.sum((obs - expected) ** 2 / expected)
    assert stats.chi2.sf(stat, obs.size - 1) > 1e-4, stat
    # and each photon carries I / p(ω) (I = 1): 1 / ((1 − f)/(4π) + f/(2π(1 − cos θ_max))) inside the cone
    inside = c > c_max + 1e-4
    np.testing.assert_allclose(power[inside, 0], 1 / ((1 - f) / (4 * math.pi) + f / (2 * math.pi * (1 - c_max))),
                               rtol=1e-4)
    np.testing.assert_allclose(power[c < c_max - 1e-4, 0], 1 / ((1 - f) / (4 * math.pi)), rtol=1e-5)


# ---------------------------------------------------------------------------------------------- photons

def _hits_on_ball(scene, n, seed):
    o, d, power = jax.jit(sppm.emit)(scene, _uniforms(n, seed))
    hit = jax.jit(lambda g, o, d: g.intersect(o, d, 0.0, jnp.full(o.shape[0], jnp.inf)))(scene.geometry, o, d)
    prim = np.asarray(hit.prim)
    ball = (prim >= 0) & (np.asarray(scene.geometry.face_object(jnp.asarray(prim))) == 1)
    return ball, np.asarray(power, np.float64)[:, 0]


def test_aiming_sends_more_photons_to_the_glass_with_the_same_flux():
    """An area lamp above a glass ball: with f = 0.5 about half the photons hit the ball (f = 0: a
    few per cent), nearly all of those from the cone; the flux reaching the ball (mean of power ×
    hit) is the same (within 4 combined standard errors) and matches a float64 ray/sphere estimate;
    the mean power is still the lamp's π·L·A."""
    n = 400_000
    got = {}
    for f in (0.0, 0.5):
        scene = R.load_scene(glass_scene(photon_aim=f))
        ball, power = _hits_on_ball(scene, n, 3)
        flux = power * ball
        got[f] = (ball.mean(), flux.mean(), flux.std() / math.sqrt(n))
        lamp_power = math.pi * LAMP_L * LAMP_SIDE**2
        assert abs(power.mean() - lamp_power) < 4 * power.std() / math.sqrt(n) + 1e-5 * lamp_power
    (frac0, flux0, se0), (frac5, flux5, se5) = got[0.0], got[0.5]
    assert frac0 < 0.15 and frac5 > 0.45 and frac5 > 4 * frac0, (frac0, frac5)
    from_cone = (frac5 - 0.5 * frac0) / frac5  # the unaimed half hits as often as all photons at f = 0
    assert from_cone > 0.85, from_cone
    assert se5 < 0.5 * se0  # the point of aiming: a less noisy flux estimate
    assert abs(flux5 - flux0) < 4 * math.hypot(se0, se5), (flux0, flux5, se0, se5)
    # float64: cosine-distributed rays from the lamp square against the exact sphere
    rng = np.random.default_rng(0)
    m = 2_000_000
    x = np.stack([rng.uniform(-0.1, 0.1, m), np.full(m, LAMP_Y), -1.5 + rng.uniform(-0.1, 0.1, m)], 1)
    u, v = rng.random(m), rng.random(m)
    d = np.stack([np.sqrt(u) * np.cos(2 * math.pi * v), -np.sqrt(1 - u), np.sqrt(u) * np.sin(2 * math.pi * v)], 1)
    oc = x - BALL_C
    b = np.sum(oc * d, 1)
    hit = (b * b - (np.sum(oc * oc, 1) - BALL_R**2) > 0) & (b < 0)
    p = hit.mean()
    want, se_w = p * lamp_power, math.sqrt(p * (1 - p) / m) * lamp_power
    # the icosphere (subdivisions 3) lies inside the exact sphere: up to ~1.5 % less cross-section
    assert -4 * math.hypot(se5, se_w) - 0.015 * want < flux5 - want < 4 * math.hypot(se5, se_w), (flux5, want)


def test_no_delta_objects_no_aiming_photons_unchanged():
    """Without glass or mirrors the default is no aiming: the photons are the 6-uniform emission's,
    bit for bit (extra uniforms unused); with glass and aiming on, 6 uniforms are refused."""
    plain = R.load_scene(glass_scene(glass=False))
    assert plain.settings.photon_aim == 0.0
    u = _uniforms(1000, 4)
    a = jax.jit(sppm.emit)(plain, u[:, :6])
    b = jax.jit(sppm.emit)(plain, u)  # extra uniforms ignored without aiming
    for x, y in zip(a, b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError):
        sppm.emit(R.load_scene(glass_scene()), u[:, :6])


# ---------------------------------------------------------------------------------------------- images

@pytest.mark.slow
def test_aimed_sppm_image_equals_unaimed_within_errors():
    """The SPPM image of the glass ball under the lamp with f = 0.5 and f = 0: over 5 seeds each,
    the image mean and the 4 quadrant means agree within 4 combined standard errors (seed spread).
    (Same seed, same camera passes: the direct light is identical, the photons' part differs.)"""
    imgs = {}
    for f in (0.0, 0.5):
        out = []
        for seed in range(5):
            scene = R.load_scene(glass_scene(photon_aim=f, photons=4096, radius=0.06, spp=4, seed=seed))
            out.append(np.asarray(R.render(scene), np.float64))
        imgs[f] = np.stack(out)
    h, w = imgs[0.0].shape[1:3]

    def stats_of(a):
        q = [a[:, :h // 2, :w // 2], a[:, :h // 2, w // 2:], a[:, h // 2:, :w // 2], a[:, h // 2:, w // 2:], a]
        m = np.array([x.mean(axis=(1, 2, 3)) for x in q])  # (5, seeds)
        return m.mean(1), m.std(1, ddof=1) / math.sqrt(m.shape[1])

    (m0, s0), (m5, s5) = stats_of(imgs[0.0]), stats_of(imgs[0.5])
    assert np.all(np.isfinite(imgs[0.5]))
    assert np.all(np.abs(m5 - m0) < 4 * np.hypot(s0, s5)), (m0, m5, s0, s5)
    assert m0[-1] > 0
