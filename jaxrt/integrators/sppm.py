"""Stochastic progressive photon mapping (T. Hachisuka and H. W. Jensen, "Stochastic progressive
photon mapping", ACM TOG 28(5), 2009), the integrator that renders caustics of point lights.

`integrator = "sppm"`. A render is a sequence of passes; each pass has two halves:

* Camera pass: `[render] camera_samples` = k jittered camera rays per pixel (default 1) each
  follow mirror (δ lobe, chosen with probability δ)
  and glass (reflection with probability R, transmission otherwise) bounces as the path tracer does
  and stops at the first non-delta surface: the pixel's *visible point* for this pass (position,
  shading frame, wo, material, throughput β and its vertex count j). Emission met along the way
  (emissive triangles, the environment on escape) is added to the pixel's direct sum, and so is
  next-event estimation at the visible point: every point light and one sample of the emissive
  triangles or the environment, chosen as in the path tracer, light sampling only (no MIS: the
  visible point never continues a BSDF-sampled ray). Shadow rays are blocked by glass, as in the
  path tracer.
* Photon pass: `[render] photons` photons leave the lights, the light chosen by its power
  (luminance): a point light of intensity I emits 4π·I uniformly over the sphere, an emissive
  triangle of radiance L_e and area A emits π·L_e·A cosine-distributed on its emitting side, an
  environment sends π r²·∫L dω through the disk of the scene's bounding-sphere radius r facing each
  direction (directions from its importance sampler, as pbrt-v4's infinite lights). Each
  photon is traced through every BSDF (the models' `sample`/`pdf`, measured models included) and
  the delta materials for at most max_depth − 1 scatterings, without Russian roulette, and
  deposited at every non-delta hit *after its first scattering*: light reaching a surface straight
  from a light is the next-event estimate's, light arriving after any scattering (diffuse
  interreflection, caustics through glass) the photons'. A deposit after b scatterings counts at a
  visible point of vertex count j only when b + j ≤ max_depth, so the longest paths are those of
  the path tracer's max_depth (a scattering vertex count, pbrt's maxDepth).
* Photon aiming (projection maps, H. W. Jensen, "Global illumination using photon maps", EGWR
  1996, and "Realistic image synthesis using photon mapping", 2001, §5.3.1): a fraction f =
  `[render] photon_aim` of the point and area lights' photons is sent towards the glass and mirror
  objects, which make the caustics, instead of mostly onto diffuse surfaces whose direct light the
  camera pass already has. The direction is drawn from the mixture p(ω) = (1 − f)·p_emit(ω) +
  f·p_cone(ω): p_emit the unaimed density (uniform over the sphere for a point light, cos θ/π for an
  area light), p_cone uniform over the cone subtending the bounding sphere of one of the objects with
  a delta material (each chosen with the same probability; the density sums over all cones that
  contain ω, 0 outside them). Each photon carries L_e·cos θ/(p_A·p(ω)) (area) or I/p(ω) (point), so
  photons inside the cones carry less power, the others more, and the estimate stays unbiased.
  Default f = DEFAULT_PHOTON_AIM = 0.5 where the scene has glass or mirror materials, 0 (no aiming,
  the same photons bit for bit) otherwise; environment photons are not aimed.

Gathering uses a hash grid built with array operations, of L = `grid_levels` levels of cells (edges
c·2^l, c twice a low quantile of the radii of the visible points that receive photons, radii above
a high quantile clamped to it: `_radii`; every deposit is in every level and a visible point reads
the finest level whose cells are at least 2r wide), each deposit's cell hashed into a table of 2^k
buckets, the
deposits sorted by (bucket, a random key), bucket starts and ends by `searchsorted`. A
visible point reads the 8 cells its radius-r ball can touch and, of each bucket, the first
`CELL_PHOTONS` deposits; a bucket with n > CELL_PHOTONS deposits has its read deposits weighted by
n / CELL_PHOTONS (they are a uniform random subset of the bucket, thanks to the random key), so
the estimate of each cell's sum stays unbiased with static shapes. Deposits of another cell sharing
the bucket are rejected by their cell coordinates. L is `[render] grid_levels`, default
DEFAULT_GRID_LEVELS per backend: every level adds a copy of each deposit to the one sort.

Progressive statistics per pixel (Hachisuka & Jensen 2009, eqs. 5-8) with M the photons found in
radius r this pass and Φ = Σ β·f(wo, wi)·Φ_p their reflected flux:
N' = N + α·M, r'² = r²·(N + α·M)/(N + M), τ' = (τ + Φ)·r'²/r², α = `[render] alpha`, default `ALPHA` = 0.7.
The pixel's radiance after P passes of N_p photons each is direct/P + τ/(P·N_p·π·r²).

Several visible points per pixel (k > 1): each is a chain of its own with its own N, r and τ
(the statistics are per chain, S = H·W·k), all gathering the same pass's photons; the pixel's
radiance is the mean of its chains'. A pass's photons then serve k times as many camera samples,
which pays where the error is the camera side's (one jittered point per pixel on a sharp caustic)
rather than the photons'.

Passes per call: `step(scene, state, count)` runs `count` passes in one compiled call (a
`lax.fori_loop` over the one pass, `count` traced: one compilation for every count), the same
operations on the same random streams as `count` calls of one pass. A pass of a small frame is many
small kernels (the bounces, the sort, the gather), a few milliseconds on a GPU, where a call per pass
would add its dispatch and a synchronisation to each; renders run `passes_per_call` passes a call,
about CALL_SECONDS of work (the viewer less, to answer its sliders). Off the CPU the camera paths
and photons of `photon_batch` passes are traced as one batch each (a pass's random streams do not
depend on the statistics, only its grid and gather do), then each pass's grid, gather and update
run in turn: one traversal launch a bounce for several passes, where one pass alone fills a
fraction of a GPU (BENCHMARKS.md, "Photon mapping").

Defaults: photons per pass = the pixel count, within [2^12, 2^20]; initial radius RADIUS_PIXELS = 1
pixel footprint at each chain's first visible point (`initial_radius`); `[render] radius` sets one
radius for every pixel instead. The number of passes is `[render] spp`, so `jaxrt render --passes
N` and `--spp N` are the same setting.

Several devices (`pass_share`, run by `jaxrt._devices.sppm_program`): the visible points are
computed on every device from the pass's keys, the photons are split (photon count per pass padded
to a multiple of the device count with photons of zero power), each device gathers from its own
grid and M, Φ are summed over the devices before the update.

Not modelled: differentiation (the render is a Monte Carlo density estimate; gradients are not
meaningful), tiles (a pass is one whole-frame program).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float, Int

import brdfs
from jaxrt import camera, envmap
from jaxrt import lights as _lights
from jaxrt.errors import InputError
from jaxrt.integrators.common import (SEARCH, emitter_table, intersect_active, sample_area_light,
                                      sample_emitter_point)
from jaxrt.integrators.common import on_cpu as _on_cpu  # a name of this module's: tests patch it
from jaxrt.shading.aovs import build_aovs
from jaxrt.shading.material import at_hits, glass_split, hit_params, is_glass
from jaxrt.shading.surface import (dot, from_local, local_frame, mirror_dir, normalize, offset_scale, oriented,
                                   to_local)

#: radius reduction α of the progressive update (Hachisuka & Jensen 2009 use 0.7)
ALPHA = 0.7
#: deposits read per grid cell and visible point (more are subsampled, see the module docstring)
CELL_PHOTONS = 32
#: the default photons per pass: the pixel count, within these bounds
DEFAULT_PHOTONS = (1 << 12, 1 << 20)
#: upper bound of `[render] photons`
MAX_PHOTONS = 1 << 24
#: the default initial radius, in pixel footprints at the visible point (see `initial_radius`)
RADIUS_PIXELS = 1.0
#: radii above this quantile of the radii of the visible points that have received photons are
#: clamped to it (see `_radii`)
CELL_QUANTILE = 0.9
#: upper bound of `[render] camera_samples` (visible points per pixel per pass)
MAX_CAMERA_SAMPLES = 64
#: levels of the hash grid (cell edges c·2^l, c from the FINE_QUANTILE of the radii; `build_grid`) of a
#: scene that does not set `[render] grid_levels`, per JAX backend (`grid_levels`; measured in
#: BENCHMARKS.md, "Photon mapping"); other backends take the "cpu" entry
DEFAULT_GRID_LEVELS = {"cpu": 2, "gpu": 2}
#: upper bound of `[render] grid_levels`
MAX_GRID_LEVELS = 4
#: a render runs as many passes in one compiled call as take about this long (`passes_per_call`):
#: long enough that what a call costs besides its passes is a small part of it (on a GPU, where a
#: pass of a small frame takes milliseconds, the dispatch and synchronisation; on a CPU 8 passes a
#: call took 0.8x the CPU time of one a call at 64x48 and 96x72, BENCHMARKS.md "Photon mapping"),
#: short enough for the progress bar and Ctrl-C to answer within a second (the viewer asks for
#: less, `jaxrt.viewer`)
CALL_SECONDS = 0.5
#: upper bound of the passes of one call
MAX_PASSES_PER_CALL = 1024
#: the finest cells are 2x this quantile of the radii of the visible points that receive photons
FINE_QUANTILE = 0.1
#: the default `[render] photon_aim` of scenes with glass or mirror (δ > 0) materials (0 without them)
DEFAULT_PHOTON_AIM = 0.5
#: photons a GPU traces at once when passes are batched (`photon_batch`): a pass of 65k photons
#: traces a bounce in ~100 µs on an H200 at a fraction of its width (BENCHMARKS.md, "Photon mapping")
PHOTON_BATCH = 1 << 19
#: upper bound of the passes traced in one batch
MAX_PHOTON_BATCH = 8
#: objects aimed at one by one up to this many (each photon tests every cone); more share one sphere
MAX_AIM_OBJECTS = 16
_sg = lax.stop_gradient


class SPPMState(eqx.Module):
    """Progressive statistics of every visible-point chain, carried across passes: `samples` chains
    per pixel (S = H·W·samples, ordered (row, column, sample) as `camera.generate_rays`).

    n: (S,) accumulated photon count N; r2: (S,) squared radius r² (0 until the chain's first visible
    point sets it from its pixel footprint, `initial_radius`); tau: (S, 3) accumulated flux τ;
    direct: (S, 3) Σ over passes of the directly estimated radiance; passes: () passes done."""

    n: Float[Array, " S"]
    r2: Float[Array, " S"]
    tau: Float[Array, "S 3"]
    direct: Float[Array, "S 3"]
    passes: Int[Array, ""]
    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    photons: int = eqx.field(static=True)
    samples: int = eqx.field(static=True, default=1)

    @property
    def image(self) -> Float[Array, "H W 3"]:
        """The radiance estimate after the passes so far, (H, W, 3) linear, finite."""
        p = jnp.maximum(self.passes, 1).astype(jnp.float32)
        r2 = jnp.where(self.r2 > 0, self.r2, 1.0)
        indirect = jnp.where((self.r2 > 0)[:, None], self.tau / (p * self.photons * math.pi * r2)[:, None], 0.0)
        # a pixel's chains are independent estimates of its radiance: their mean
        img = (self.direct / p + indirect).reshape(self.height, self.width, self.samples, 3).mean(2)
        return jnp.where(jnp.isfinite(img), img, 0.0)


def photons_per_pass(scene) -> int:
    """Photons per pass (static): `[render] photons`, else the pixel count within DEFAULT_PHOTONS."""
    n = getattr(scene.settings, "photons", 0)
    if n:
        return int(n)
    lo, hi = DEFAULT_PHOTONS
    return int(min(max(scene.camera.num_pixels, lo), hi))


def initial_radius(scene) -> float:
    """The initial gather radius of every pixel, `[render] radius`; 0 (the default) for a radius per
    visible-point chain set at its first visible point: RADIUS_PIXELS pixel footprints there, the
    footprint being the camera ray's path length to the point (through mirrors and glass) times the
    angle a pixel subtends, 2·tan(vfov/2)/height (the width across the ray). One radius in scene
    units for every pixel is too large close to the camera or too small far away in a scene whose
    depth varies; Hachisuka & Jensen 2009 leave r0 to the user."""
    return float(getattr(scene.settings, "radius", 0.0))


def pixel_angle(cam) -> Float[Array, ""]:
    """The angle a pixel subtends at the image centre [rad]: 2·tan(vfov/2)/height."""
    return 2.0 * jnp.tan(jnp.deg2rad(cam.vfov) * 0.5) / cam.height


def grid_levels(scene) -> int:
    """Levels of the hash grid (static): `[render] grid_levels`, else DEFAULT_GRID_LEVELS of the
    default JAX backend. More levels serve a wider range of radii with cells close to each (fewer
    reads wasted on photons outside the radius), at the cost of one more copy of every deposit in
    the grid's sort."""
    n = getattr(scene.settings, "grid_levels", 0)
    return int(n) if n else DEFAULT_GRID_LEVELS.get(jax.default_backend(), DEFAULT_GRID_LEVELS["cpu"])


def alpha(scene) -> float:
    """The radius reduction α of the progressive update (static): `[render] alpha`, default ALPHA.

    α is the fraction of a pass's new photons a visible point keeps (N' = N + α·M): smaller α
    shrinks the radius faster, trading the blur (bias) of the density estimate for its noise
    (Hachisuka & Jensen 2009 use 0.7; Knaus & Zwicker 2011 show the mean squared error falls
    fastest, as passes^(-2/3), with α = 2/3 in the limit of many passes). At a short budget on
    a sharp caustic the blur dominates: `benchmarks/sppm.py --equal-time` on one GPU gave 2x lower
    error with α = 0.5 than with 0.7 at 0.25-2 s (BENCHMARKS.md)."""
    a = getattr(scene.settings, "alpha", 0.0)
    return float(a) if a else ALPHA


def camera_samples(scene) -> int:
    """Visible points per pixel per pass (static): `[render] camera_samples`, default 1."""
    return int(getattr(scene.settings, "camera_samples", 0) or 1)


def check(scene) -> None:
    """One-line InputError for an SPPM render that cannot run (before any JAX work on values)."""
    n = getattr(scene.settings, "photons", 0)
    if not isinstance(n, int) or n < 0 or n > MAX_PHOTONS:
        raise InputError(f"{scene.source}: [render] photons = {n!r}: allowed 1..{MAX_PHOTONS} (0: default)")
    r = getattr(scene.settings, "radius", 0.0)
    if not (isinstance(r, (int, float)) and math.isfinite(r) and r >= 0):
        raise InputError(f"{scene.source}: [render] radius = {r!r}: must be a positive finite length (0: default)")
    k = getattr(scene.settings, "camera_samples", 0)
    if not isinstance(k, int) or k < 0 or k > MAX_CAMERA_SAMPLES:
        raise InputError(f"{scene.source}: [render] camera_samples = {k!r}: allowed 1..{MAX_CAMERA_SAMPLES} "
                         "(0: default)")
    g = getattr(scene.settings, "grid_levels", 0)
    if not isinstance(g, int) or g < 0 or g > MAX_GRID_LEVELS:
        raise InputError(f"{scene.source}: [render] grid_levels = {g!r}: allowed 1..{MAX_GRID_LEVELS} (0: default)")
    a = getattr(scene.settings, "alpha", 0.0)
    if not (isinstance(a, (int, float)) and 0.0 <= a < 1.0 and math.isfinite(a)):
        raise InputError(f"{scene.source}: [render] alpha = {a!r}: allowed 0 < alpha < 1 (0: default {ALPHA})")
    f = photon_aim(scene)
    if not (isinstance(f, (int, float)) and 0.0 <= f < 1.0):
        raise InputError(f"{scene.source}: [render] photon_aim = {f!r}: allowed 0 <= photon_aim < 1")


def default_photon_aim(has_delta: bool) -> float:
    """The `[render] photon_aim` of a scene that does not set it: DEFAULT_PHOTON_AIM with glass or
    mirror materials, 0 (no aiming) without."""
    return DEFAULT_PHOTON_AIM if has_delta else 0.0


def photon_aim(scene) -> float:
    """The fraction f of the point and area lights' photons aimed at the delta objects (static)."""
    return float(getattr(scene.settings, "photon_aim", 0.0))


# ---------------------------------------------------------------------------------------------- BSDFs

def _models(mats):
    return [(k, brdfs.get(name)) for k, name in enumerate(mats.models) if not brdfs.get(name).delta]


def _params(mats, s, k: int) -> dict:
    uv = getattr(s, "uv", None)
    return hit_params(mats, s.material, k) if uv is None else hit_params(mats, s.material, k, uv)


def _eval_f(models, params, sel, wi_l, wo_l, extra_dims: int = 0):
    """f(wi, wo) of each slot's model; 0 where either direction is below the local horizon."""
    f = jnp.zeros(wi_l.shape)
    for kk, model in models:
        fk = at_hits(params[kk], lambda p, model=model: model.eval(p, wi_l, wo_l), extra_dims)
        m = sel[kk].reshape((-1,) + (1,) * extra_dims)
        f = jnp.where(m[..., None], fk, f)
    up = (wi_l[..., 2] > 0) & (wo_l[..., 2] > 0)
    return jnp.where(up[..., None], f, 0.0)


def _scatter(scene, models, s, d, found, u):
    """One scattering event of a batch of rays at their hits, as the path tracer samples it.

    Returns (new origin, new direction, throughput factor (B, 3), ok, delta): delta marks mirror
    and glass events (no visible point or deposit there)."""
    mats = scene.materials
    B = d.shape[0]
    ng, ns, _ = oriented(s, d)
    frame = local_frame(ns, s.tangent)
    wo = to_local(-d, frame)
    eps = offset_scale(s.p)
    glass = found & is_glass(mats, s.material)
    opaque = found & ~glass
    q = jnp.where(opaque, mats.delta[s.material], 0.0)
    params = {kk: _params(mats, s, kk) for kk, _ in models}
    sel = {kk: mats.model_id[s.material] == kk for kk, _ in models}
    wi_s = jnp.zeros((B, 3)).at[:, 2].set(1.0)
    pdf_s = jnp.zeros(B)
    for kk, model in models:
        wk, _, pk = at_hits(params[kk], lambda p, model=model: model.sample(p, wo, u[:, 1:3]))
        wi_s = jnp.where(sel[kk][:, None], wk, wi_s)
        pdf_s = jnp.where(sel[kk], pk, pdf_s)
    f_s = _eval_f(models, params, sel, wi_s, wo)
    ok_s = pdf_s > 0
    # the (1 - δ) of the BRDF part cancels the probability 1 - δ of choosing it
    fac_b = f_s * (jnp.maximum(wi_s[:, 2], 0.0) / jnp.where(ok_s, pdf_s, 1.0))[:, None]
    mirror = u[:, 0] < q
    origin = s.p + ng * eps
    new_d = jnp.where(mirror[:, None], mirror_dir(d, ng, ns), from_local(wi_s, frame))
    ok = (mirror | ok_s) & (dot(new_d, ng) > 0)
    fac = jnp.where(mirror[:, None], 1.0, fac_b)
    new_o = origin
    is_delta = opaque & mirror
    for kk, name in enumerate(mats.models):
        if not brdfs.get(name).delta:
            continue
        r, dr, dt, t_ok = glass_split(mats, s, d, kk)
        pick_r = (u[:, 0] < r) | ~t_ok
        here = glass & (mats.model_id[s.material] == kk)
        new_d = jnp.where(here[:, None], jnp.where(pick_r[:, None], dr, dt), new_d)
        new_o = jnp.where(here[:, None], jnp.where(pick_r[:, None], origin, s.p - ng * eps), new_o)
        # a Fresnel choice with probability R carries weight R / R = 1
        fac = jnp.where(here[:, None], 1.0, fac)
        ok = jnp.where(here, True, ok)
        is_delta = is_delta | here
    return new_o, normalize(new_d), fac, ok & found, is_delta


# ---------------------------------------------------------------------------------------------- lights

def _bounds(scene):
    """Centre and radius of the scene's bounding sphere (about its bounding box; detached)."""
    geo = _sg(scene.geometry)
    v = jnp.stack(geo.triangles(jnp.arange(geo.triangle_count)), 0).reshape(-1, 3)
    lo, hi = jnp.min(v, axis=0), jnp.max(v, axis=0)
    return 0.5 * (lo + hi), 0.5 * jnp.linalg.norm(hi - lo)


def environment_radiant_exitance(env) -> Float[Array, "3"]:
    """∫ L(ω) dω over the sphere of directions [W/m²] per channel: the power an environment sends
    through a unit disk facing each direction, summed over directions (4π·L for a constant one)."""
    tex = _sg(env.texels)
    if env.uniform:
        return 4.0 * math.pi * tex[0, 0]
    h, w = tex.shape[:2]
    theta = (jnp.arange(h) + 0.5) * (math.pi / h)
    d_omega = (2.0 * math.pi / w) * (math.pi / h) * jnp.sin(theta)
    return jnp.sum(tex * d_omega[:, None, None], axis=(0, 1))


def _light_choice(scene):
    """Selection weights of the photon sources by power (luminance): (L point lights, the emissive
    triangles as one entry, the environment as one entry), the emitter table (None without emissive
    triangles) and the bounding sphere (None without an environment)."""
    L = scene.lights.count
    w = [4.0 * math.pi * envmap.luminance(_sg(scene.lights.intensity))] if L else []
    table = sphere = None
    if scene.area_lights is not None and scene.area_lights.count > 0:
        table = emitter_table(scene)
        w.append(math.pi * table.total[None])
    env = getattr(scene, "environment", None)
    if env is not None:
        sphere = _bounds(scene)
        # the environment's photons cross a disk of the bounding sphere's radius facing them
        w.append((math.pi * sphere[1] ** 2 * envmap.luminance(environment_radiant_exitance(env)))[None])
    w = jnp.concatenate(w) if w else jnp.zeros(0)
    return w, table, sphere


def light_power(scene) -> Float[Array, "3"]:
    """Total emitted flux [W] per channel of the point lights (4π·I) and emissive triangles (π·L_e·A)."""
    total = 4.0 * math.pi * jnp.sum(scene.lights.intensity, axis=0)
    if scene.area_lights is not None and scene.area_lights.count > 0:
        geo, al = scene.geometry, scene.area_lights
        area = emitter_table(scene).area  # the areas the photon emission samples by
        total = total + math.pi * jnp.sum(area[:, None] * al.emission[geo.face_material(al.prims)], axis=0)
    return total


# ---------------------------------------------------------------------------------------------- aiming

class AimTargets(eqx.Module):
    """Bounding spheres of the objects with delta (glass or mirror) materials: centre (K, 3),
    radius (K,), active (K,) (False for objects without delta faces)."""

    centre: Float[Array, "K 3"]
    radius: Float[Array, " K"]
    active: Array


def aim_targets(scene) -> AimTargets:
    """The bounding sphere (about its bounding box's centre) of each object's glass and mirror
    (δ > 0) triangles, from the current values; one sphere of all of them beyond MAX_AIM_OBJECTS."""
    geo, mats = _sg(scene.geometry), _sg(scene.materials)
    K = len(geo.object_names)
    prim = jnp.arange(geo.triangle_count)
    v = jnp.stack(geo.triangles(prim), 1)  # (F, 3, 3)
    m = geo.face_material(prim)
    delta = is_glass(mats, m) | (mats.delta[m] > 0)
    obj = geo.face_object(prim)
    if K > MAX_AIM_OBJECTS:
        obj, K = jnp.zeros_like(obj), 1
    seg = jnp.where(delta, obj, K)  # non-delta faces belong to no target
    # (F, K) membership and masked reductions over the faces: K is at most MAX_AIM_OBJECTS, and a
    # segment reduction into K slots is a scatter whose every face updates one of a few addresses,
    # which a GPU serialises (atomics on the same words: ~0.5 ms for 20k faces into 4 slots)
    member = seg[:, None] == jnp.arange(K)[None, :]
    inf = jnp.asarray(jnp.inf, v.dtype)
    lo = jnp.min(jnp.where(member[:, :, None], jnp.min(v, 1)[:, None, :], inf), axis=0)
    hi = jnp.max(jnp.where(member[:, :, None], jnp.max(v, 1)[:, None, :], -inf), axis=0)
    active = jnp.any(member, axis=0)
    centre = jnp.where(active[:, None], 0.5 * (lo + hi), 0.0)
    dist = jnp.max(jnp.linalg.norm(v - centre[jnp.minimum(seg, K - 1)][:, None, :], axis=-1), axis=1)
    radius = jnp.max(jnp.where(member, dist[:, None], 0.0), axis=0)
    return AimTargets(centre, jnp.where(active, radius, 0.0), active)


def _cones(t: AimTargets, x):
    """Per origin x (n, 3) and target (K): the unit axis (n, K, 3) and 1 − cos θ_max (n, K) of the
    cone subtending the target's sphere (2: the whole sphere of directions, x inside it)."""
    axis = t.centre[None] - x[:, None, :]
    d2 = jnp.sum(axis * axis, -1)
    s2 = t.radius[None] ** 2 / jnp.where(d2 > 0, d2, 1.0)
    inside = s2 >= 1.0
    # 1 − cos θ_max = sin² / (1 + cos): no cancellation for small cones
    om = jnp.where(inside, 2.0, s2 / (1.0 + jnp.sqrt(jnp.maximum(1.0 - s2, 0.0))))
    return axis / jnp.sqrt(jnp.where(d2 > 0, d2, 1.0))[..., None], jnp.maximum(om, 1e-12)


def cone_pdf(t: AimTargets, x: Float[Array, "n 3"], w: Float[Array, "n 3"]) -> Float[Array, " n"]:
    """Solid-angle density of the aimed directions w from x: the mean over the active targets of the
    uniform density 1 / (2π(1 − cos θ_max)) inside each one's cone (0 outside every cone)."""
    axis, om = _cones(t, x)
    inside = jnp.sum(axis * w[:, None, :], -1) >= 1.0 - om
    k = jnp.sum(t.active)
    dens = jnp.where(inside & t.active[None], 1.0 / (2.0 * math.pi * om), 0.0)
    return jnp.sum(dens, -1) / jnp.maximum(k, 1)


def cone_sample(t: AimTargets, x: Float[Array, "n 3"], u: Float[Array, "n 3"]) -> Float[Array, "n 3"]:
    """Directions from x uniform in the cone of one active target (chosen uniformly by u[:, 0])."""
    axis, om = _cones(t, x)
    k = jnp.maximum(jnp.sum(t.active), 1)
    cdf = jnp.cumsum(t.active.astype(jnp.float32)) / k
    j = jnp.clip(jnp.sum(u[:, 0:1] >= cdf[None], -1), 0, t.active.shape[0] - 1)
    a = jnp.take_along_axis(axis, j[:, None, None], 1)[:, 0]
    o = jnp.take_along_axis(om, j[:, None], 1)[:, 0]
    one_minus = u[:, 1] * o
    cos = 1.0 - one_minus
    sin = jnp.sqrt(jnp.maximum(one_minus * (2.0 - one_minus), 0.0))
    phi = 2.0 * math.pi * u[:, 2]
    loc = jnp.stack([sin * jnp.cos(phi), sin * jnp.sin(phi), cos], -1)
    return normalize(from_local(loc, local_frame(a, jnp.zeros_like(a))))


def aim_pdf(t: AimTargets, f: float, x: Float[Array, "n 3"], normal: Float[Array, "n 3"] | None,
            w: Float[Array, "n 3"]) -> Float[Array, " n"]:
    """The emission density p(ω) = (1 − f)·p_emit(ω) + f·p_cone(ω) of directions w from x: p_emit
    uniform over the sphere (normal None: a point light) or cos θ/π about `normal` (an area light);
    p_emit alone where no target is active."""
    p_emit = (jnp.full(w.shape[0], 1.0 / (4.0 * math.pi)) if normal is None
              else jnp.maximum(dot(w, normal), 0.0) / math.pi)
    return jnp.where(jnp.any(t.active), (1.0 - f) * p_emit + f * cone_pdf(t, x, w), p_emit)


def photon_sources(scene):
    """What photon emission reads of the scene besides the random numbers: the lights' selection
    weights, the emitter table, the bounding sphere (`_light_choice`) and the aiming targets (None
    without aiming). The same for every pass of a render: `steps` makes it once per call and its
    passes read it (a face reduction over the whole mesh per pass otherwise)."""
    w, table, sphere = _light_choice(scene)
    aim = aim_targets(scene) if photon_aim(scene) > 0 else None
    return w, table, sphere, aim


def emit(scene, u: Float[Array, "n c"], sources=None):
    """Photons leaving the lights, one per row of uniforms u.

    Returns origins (n, 3), unit directions (n, 3) and powers (n, 3) [W], each photon's power its
    light's emitted flux over the probability density of the photon, so the mean power over photons
    is an unbiased estimate of `light_power` (exactly it for one light of one colour), plus, with an
    environment, π r²·∫L dω, the power it sends into the bounding sphere of radius r. u has 6
    columns, 10 with photon aiming (`photon_aim` > 0: the last 4 choose and sample the cones).
    sources: `photon_sources(scene)`, made here when None."""
    geo = _sg(scene.geometry)
    n = u.shape[0]
    w, table, sphere, aim = photon_sources(scene) if sources is None else sources
    nl = scene.lights.count
    tot = jnp.sum(w)
    if w.shape[0] == 0:
        z = jnp.zeros((n, 3))
        return z, z.at[:, 2].set(1.0), z
    cdf = jnp.concatenate([jnp.zeros(1), jnp.cumsum(w) / jnp.where(tot > 0, tot, 1.0)])
    pick = jnp.clip(jnp.searchsorted(cdf, u[:, 0], side="right", method=SEARCH) - 1, 0, w.shape[0] - 1)
    p_pick = jnp.where(tot > 0, w[pick] / jnp.where(tot > 0, tot, 1.0), 0.0)
    inv_p = jnp.where(p_pick > 0, 1.0 / jnp.where(p_pick > 0, p_pick, 1.0), 0.0)
    # uniform direction on the sphere (point lights)
    z = 1.0 - 2.0 * u[:, 4]
    rr = jnp.sqrt(jnp.maximum(1.0 - z * z, 0.0))
    phi = 2.0 * math.pi * u[:, 5]
    d_sph = jnp.stack([rr * jnp.cos(phi), rr * jnp.sin(phi), z], axis=-1)
    o = jnp.zeros((n, 3))
    d = d_sph
    power = jnp.zeros((n, 3))
    if nl:
        li = jnp.minimum(pick, nl - 1)
        o = _sg(scene.lights.position)[li]
        power = 4.0 * math.pi * _sg(scene.lights.intensity)[li] * inv_p[:, None]
    if table is not None:
        al = _sg(scene.area_lights)
        face, (v0, v1, v2), y, n_l = sample_emitter_point(geo, al, table, u[:, 1:4])
        # cosine-distributed about the emitting side's normal
        rc = jnp.sqrt(u[:, 4])
        loc = jnp.stack([rc * jnp.cos(phi), rc * jnp.sin(phi), jnp.sqrt(jnp.maximum(1.0 - u[:, 4], 0.0))], -1)
        t0 = normalize(v1 - v0)
        d_tri = from_local(loc, local_frame(n_l, t0))
        fp = table.face_pdf[face]
        p_tri = jnp.where(fp > 0, math.pi / jnp.where(fp > 0, fp, 1.0), 0.0)
        pw_tri = al.emission[geo.face_material(face)] * (p_tri * inv_p)[:, None]
        area = pick == nl
        o = jnp.where(area[:, None], y + n_l * offset_scale(y), o)
        d = jnp.where(area[:, None], d_tri, d)
        power = jnp.where(area[:, None], pw_tri, power)
    f = photon_aim(scene)
    if f > 0 and (nl or table is not None):
        if u.shape[1] < 10:
            raise ValueError(f"emit: photon aiming needs 10 uniforms per photon, got {u.shape[1]}")
        t = aim
        area = (pick == nl) if table is not None else jnp.zeros(n, bool)
        # the cone's apex: the point on the lamp (before the ray offset) or the point light
        x = jnp.where(area[:, None], y, o) if table is not None else o
        aimed = (u[:, 9] < f) & ((pick < nl) | area) & jnp.any(t.active)
        d = jnp.where(aimed[:, None], cone_sample(t, x, u[:, 6:9]), d)
        p_pt = aim_pdf(t, f, x, None, d)
        if nl:
            li = jnp.minimum(pick, nl - 1)
            pw_pt = _sg(scene.lights.intensity)[li] * (inv_p / p_pt)[:, None]
            power = jnp.where((pick < nl)[:, None], pw_pt, power)
        if table is not None:
            p_ar = aim_pdf(t, f, x, n_l, d)
            cos = dot(d, n_l)
            ok = (cos > 0) & (p_ar > 0) & (fp > 0)
            g = jnp.where(ok, cos / jnp.where(ok, fp * p_ar, 1.0), 0.0)
            power = jnp.where(area[:, None], al.emission[geo.face_material(face)] * (g * inv_p)[:, None], power)
    if sphere is not None:
        # from the environment (pbrt-v4's ImageInfiniteLight::SampleLe): a direction wi from the
        # map's importance sampler, a uniform point on the disk of the bounding sphere's radius
        # facing it, the photon travelling along −wi; power L(wi)·π r² / pdf(wi)
        env = _sg(scene.environment)
        centre, radius = sphere
        wi_e, le_e, pdf_e = envmap.sample(env, u[:, 4:6])
        t_e, b_e, _ = local_frame(wi_e, jnp.zeros_like(wi_e))
        rd = radius * jnp.sqrt(u[:, 2])
        ang = 2.0 * math.pi * u[:, 3]
        o_e = centre + radius * wi_e + (rd * jnp.cos(ang))[:, None] * t_e + (rd * jnp.sin(ang))[:, None] * b_e
        pw_e = le_e * (math.pi * radius**2 * jnp.where(pdf_e > 0, 1.0 / jnp.where(pdf_e > 0, pdf_e, 1.0), 0.0)
                       * inv_p)[:, None]
        sky = pick == w.shape[0] - 1
        o = jnp.where(sky[:, None], o_e, o)
        d = jnp.where(sky[:, None], -wi_e, d)
        power = jnp.where(sky[:, None], pw_e, power)
    return o, normalize(d), jnp.where(jnp.isfinite(power), power, 0.0)


# ---------------------------------------------------------------------------------------------- photons

class Deposits(eqx.Module):
    """Photon deposits, flattened over (scattering count, photon): position, wi (unit, towards
    where the photon came from), power [W], scatterings before the deposit, valid."""

    p: Float[Array, "N 3"]
    wi: Float[Array, "N 3"]
    power: Float[Array, "N 3"]
    bounce: Int[Array, " N"]
    valid: Array


def _share_rows(x, share):
    # this device's rows of a whole pass's array of per-photon random numbers: the array is drawn for
    # all n photons (so photon i's numbers are the one-device pass's whatever device traces it),
    # padded to D·ceil(n/D) rows and cut into D equal slices
    if share is None:
        return x
    d, count = share
    n = x.shape[0]
    per = -(-n // count)
    x = jnp.pad(x, ((0, per * count - n),) + ((0, 0),) * (x.ndim - 1))
    return lax.dynamic_slice_in_dim(x, d * per, per, 0)


def trace_photons(scene, key, n: int, share: tuple | None = None, sources=None) -> Deposits:
    """Emit `n` photons and trace them for max_depth − 1 scatterings; a deposit at every non-delta
    hit after the first scattering (see the module docstring).

    share: None (all n photons), or (d, D): device d's ceil(n/D) of the photons split over D devices
    (d traced, D static), photon i the same as in the whole pass (its random numbers are row i of the
    whole pass's); the last device's rows past photon n − 1 are padding with zero power, never traced.
    sources: `photon_sources(scene)` (made here when None)."""
    return jax.tree.map(lambda x: x[0], trace_photon_batch(scene, key[None], n, share, sources))


def trace_photon_batch(scene, keys, n: int, share: tuple | None = None, sources=None) -> Deposits:
    """`trace_photons` of several passes at once, one per key of `keys` (B,): every field gains a
    leading axis of B, and pass b's deposits are those `trace_photons(scene, keys[b], n)` makes (the
    same random streams), traced as one batch of B·n photons: each bounce is one traversal launch for
    all of them, where a GPU runs B small launches at a fraction of its width. `share` needs B = 1."""
    geo = _sg(scene.geometry)
    mats = _sg(scene.materials)
    scene = _sg(scene)
    D = scene.settings.max_depth
    models = _models(mats)
    B = keys.shape[0]
    if share is not None and B != 1:
        raise ValueError("trace_photon_batch: a device's share of the photons is traced one pass at a time")

    def rows(fn):  # per-pass random numbers (B, m, c) as the batch's rows (B·m, c)
        x = jax.vmap(fn)(keys)
        return x.reshape((-1,) + x.shape[2:])

    u = rows(lambda key: jax.random.uniform(jax.random.fold_in(key, 1 << 20), (n, 6)))
    if photon_aim(scene) > 0:
        u = jnp.concatenate([u, rows(lambda key: jax.random.uniform(jax.random.fold_in(key, (1 << 20) + 1),
                                                                    (n, 4)))], 1)
    o, d, power = emit(scene, _share_rows(u, share), sources)
    if share is not None:
        per = o.shape[0]
        real = share[0] * per + jnp.arange(per) < n
        power = jnp.where(real[:, None], power, 0.0)
    n_all, n = n, o.shape[0]
    alive = jnp.any(power > 0, axis=-1)

    def body(carry, k):
        o, d, alive, beta = carry

        def work(c):
            o, d, alive, beta = c
            u = _share_rows(rows(lambda key: jax.random.uniform(jax.random.fold_in(key, k), (n_all, 3))), share)
            hit = intersect_active(geo, o, d, alive)
            prim = jnp.where(alive, hit.prim, -1)
            found = prim >= 0
            s = geo.surface(prim, hit.u, hit.v)
            s = eqx.tree_at(lambda x: x.material, s, jnp.where(found, s.material, 0))
            no, nd, fac, ok, is_delta = _scatter(scene, models, s, d, found, u)
            dep_ok = found & ~is_delta & ~is_glass(mats, s.material) & (k >= 1) & (mats.delta[s.material] < 1.0)
            dep = (s.p, -d, beta, dep_ok)
            nb = beta * fac
            good = ok & (k < D - 1) & jnp.all(jnp.isfinite(nb), axis=-1) & jnp.any(nb > 0, axis=-1)
            return (no, nd, good, jnp.where(good[:, None], nb, 0.0)), dep

        def idle(c):
            z = jnp.zeros((o.shape[0], 3))
            return c, (z, z, z, jnp.zeros(o.shape[0], bool))

        if not _on_cpu():
            # a conditional on a GPU waits for the device to hand its predicate to the host, once a
            # bounce; the dead photons' work (masked) costs less than that at a pass's sizes
            return work((o, d, alive, beta))
        return lax.cond(jnp.any(alive), work, idle, (o, d, alive, beta))

    _, (p, wi, pw, ok) = lax.scan(body, (o, d, alive, power), jnp.arange(D))
    # the first hit never deposits (its light is the next-event estimate's): its slots are dropped,
    # which keeps them out of the grid's sort
    steps, m = D - 1, n // B  # m: the rows of one pass
    # (steps, B·m, ...) -> per pass (B, steps·m, ...), each pass's deposits in (bounce, photon) order
    per_pass = lambda x: jnp.swapaxes(x[1:].reshape((steps, B, m) + x.shape[2:]), 0, 1).reshape(  # noqa: E731
        (B, steps * m) + x.shape[2:])
    bounce = jnp.broadcast_to(jnp.arange(1, steps + 1, dtype=jnp.int32)[:, None], (steps, m)).reshape(-1)
    return Deposits(per_pass(p), per_pass(wi), per_pass(pw), jnp.broadcast_to(bounce, (B, steps * m)), per_pass(ok))


# ---------------------------------------------------------------------------------------------- grid

_CELL_RANGE = 1 << 20  # cell coordinates are clipped to ±2^20 (a 2^21-cell grid a side)


def _cells(p, cell):
    return jnp.clip(jnp.floor(p / cell), -_CELL_RANGE, _CELL_RANGE).astype(jnp.int32)


def _fmix(h):
    # MurmurHash3's 32-bit finaliser: a bijection whose every output bit depends on every input bit
    h = (h ^ (h >> 16)) * jnp.uint32(0x85EBCA6B)
    h = (h ^ (h >> 13)) * jnp.uint32(0xC2B2AE35)
    return h ^ (h >> 16)


def _hash(c, size: int):
    """Bucket of integer cells (..., 3) in a table of `size` (a power of two) buckets: the finaliser
    chained over the coordinates (offset to non-negative), so sign flips and permutations of a
    cell's coordinates land in unrelated buckets (a masked XOR of coordinate multiples, Teschner et
    al. 2003's hash for prime table sizes, maps (i, j, k) and (i, -j, -k) together for many cells)."""
    u = (c + _CELL_RANGE).astype(jnp.uint32)
    h = _fmix(u[..., -1] + jnp.uint32(0x9E3779B9))
    for i in reversed(range(c.shape[-1] - 1)):  # (x, y, z, level): the level first, then z, y, x
        h = _fmix(h ^ u[..., i])
    return (h & jnp.uint32(size - 1)).astype(jnp.int32)


class Grid(eqx.Module):
    """The valid deposits at every level, sorted by hash bucket (random order within a bucket):
    bucket (N,) sorted (`size` for invalid deposits, last), and each sorted entry's cell (x, y, z,
    level), position, wi, power and scattering count; the finest level's cell edge (), the table
    size and the number of levels L (static). N = L x the deposits."""

    bucket: Int[Array, " N"]
    cells: Int[Array, "N 4"]
    p: Float[Array, "N 3"]
    wi: Float[Array, "N 3"]
    power: Float[Array, "N 3"]
    bounce: Int[Array, " N"]
    cell: Float[Array, ""]
    size: int = eqx.field(static=True)
    levels: int = eqx.field(static=True, default=DEFAULT_GRID_LEVELS["cpu"])


def build_grid(dep: Deposits, cell, key, levels: int = DEFAULT_GRID_LEVELS["cpu"]) -> Grid:
    """The hash grid of the valid deposits, every deposit in each of the `levels` (static) levels of
    cells of edge cell·2^l: one sort by (bucket, a random 32-bit key), so that a bucket's first entries
    are a uniform random subset of it. A visible point reads the finest level whose cells are at
    least twice its radius (`_candidates`): where the radii span a wide range (a focused caustic's
    shrink fast, dim surfaces' slowly) the small ones read small cells, whose CELL_PHOTONS first
    entries are mostly within their radius, instead of a few among a large cell's many."""
    n, L = dep.p.shape[0], levels
    N = n * L
    size = 1 << max(int(2 * N - 1).bit_length(), 4)
    src = jnp.tile(jnp.arange(n, dtype=jnp.int32), L)
    level = jnp.repeat(jnp.arange(L, dtype=jnp.int32), n)
    edge = cell * jnp.exp2(level.astype(jnp.float32))  # exact: a power of two times the cell
    cells = jnp.concatenate([_cells(dep.p[src], edge[:, None]), level[:, None]], axis=1)
    b = jnp.where(dep.valid[src], _hash(cells, size), size)
    rand = jax.random.bits(key, (N,), jnp.uint32)
    b, order = _sort_by_bucket(b, rand)
    k = src[order]
    return Grid(b, cells[order], dep.p[k], dep.wi[k], dep.power[k], dep.bounce[k], cell, size, L)


def _sort_by_bucket(b, rand):
    """(b sorted, the order): b's entries in the order of (b, rand, index), lexicographically.

    On the CPU one sort of the three. Elsewhere two stable sorts of one 32-bit key and its index,
    by rand and then by b (a stable sort by the primary key after one by the secondary is the
    lexicographic order): XLA hands such key-value sorts to CUB's radix sort on GPUs (a handful of
    kernels), while a sort of two keys is its own sorting network (~25 kernels for 400k entries,
    a fifth of an SPPM pass at 96x72)."""
    n = b.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    if _on_cpu():
        b, _, order = lax.sort((b, rand, idx), num_keys=2, is_stable=True)
        return b, order
    _, by_rand = lax.sort((rand, idx), num_keys=1, is_stable=True)
    b, pos = lax.sort((b[by_rand], idx), num_keys=1, is_stable=True)
    return b, by_rand[pos]


def _candidates(grid: Grid, p, r2):
    """The sorted entries read for every point p (S, 3): their indices (S, 8, K), whether each lies
    in its cell and within radius r, and the bucket subsampling weight n / K of each cell (S, 8)."""
    K = CELL_PHOTONS
    N = grid.bucket.shape[0]
    # the finest level l with cell·2^l >= 2r (the coarsest for larger radii, which `_radii` clamps)
    ratio = 2.0 * jnp.sqrt(r2) / grid.cell
    level = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(ratio, 1e-30))), 0, grid.levels - 1)
    edge = grid.cell * jnp.exp2(level)
    x = p / edge[:, None]
    base = jnp.floor(x)
    lo = base - jnp.where(x - base < 0.5, 1.0, 0.0)  # the 2x2x2 cells the ball of radius cell/2 touches
    offs = jnp.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], jnp.float32)
    cells = jnp.clip(lo[:, None, :] + offs[None], -_CELL_RANGE, _CELL_RANGE).astype(jnp.int32)  # (S, 8, 3)
    cells = jnp.concatenate([cells, jnp.broadcast_to(level.astype(jnp.int32)[:, None, None], cells.shape[:2] + (1,))],
                            axis=-1)  # (S, 8, 4)
    hq = _hash(cells, grid.size)
    start = jnp.searchsorted(grid.bucket, hq, side="left", method=SEARCH)
    end = jnp.searchsorted(grid.bucket, hq, side="right", method=SEARCH)
    j = start[..., None] + jnp.arange(K)  # (S, 8, K)
    jc = jnp.clip(j, 0, N - 1)
    same = jnp.all(grid.cells[jc] == cells[:, :, None, :], axis=-1)
    dp = grid.p[jc] - p[:, None, None, :]
    near = jnp.sum(dp * dp, axis=-1) < r2[:, None, None]
    scale = (jnp.maximum(end - start, K) / K).astype(jnp.float32)
    return jc, (j < end[..., None]) & same & near, scale


def count_near(grid: Grid, p: Float[Array, "S 3"], r2: Float[Array, " S"], weighted: bool = False) -> Array:
    """Deposits read within radius r of every point, (S,): all of them where no bucket holds more
    than CELL_PHOTONS (r must not exceed the grid's cell / 2); with `weighted`, each read deposit
    counts n / CELL_PHOTONS for its bucket's n, the unbiased estimate the gather uses."""
    _, ok, scale = _candidates(grid, p, r2)
    if weighted:
        return jnp.sum(jnp.where(ok, scale[..., None], 0.0), axis=(1, 2))
    return jnp.sum(ok, axis=(1, 2))


def gather(scene, grid: Grid, vp: dict, r2: Float[Array, " S"]):
    """(M, Φ): photons found within radius r of every visible point (bucket subsampling weights
    included) and their reflected flux Σ β·f(wo, wi)·Φ_p, (S,) and (S, 3)."""
    mats = scene.materials
    models = _models(mats)
    D = scene.settings.max_depth
    K = CELL_PHOTONS
    p = vp["p"]
    S = p.shape[0]
    jc, ok, scale = _candidates(grid, p, r2)
    wi = grid.wi[jc]
    front = dot(wi, vp["ng"][:, None, None, :]) > 0
    short = grid.bounce[jc] + vp["depth"][:, None, None] <= D
    ok = ok & front & short & vp["found"][:, None, None]
    weight = jnp.where(ok, scale[..., None], 0.0).reshape(S, 8 * K)
    frame = vp["frame"]
    wi_l = to_local(wi.reshape(S, 8 * K, 3), tuple(a[:, None, :] for a in frame))
    s = vp["surface"]
    params = {kk: _params(mats, s, kk) for kk, _ in models}
    sel = {kk: mats.model_id[s.material] == kk for kk, _ in models}
    f = _eval_f(models, params, sel, wi_l, vp["wo"][:, None, :], extra_dims=1)
    phi = jnp.sum(weight[..., None] * f * grid.power[jc].reshape(S, 8 * K, 3), axis=1) * vp["beta"]
    m = jnp.sum(weight, axis=1)
    return m, jnp.where(jnp.isfinite(phi), phi, 0.0)


# ---------------------------------------------------------------------------------------------- camera

def subpixel_positions(scene, pass_index, samples: int) -> Float[Array, "H W k 2"]:
    """The positions in their pixels of pass `pass_index`'s `samples` camera samples, (H, W, k, 2):
    points n = pass_index·k + s of the R2 sequence (frac(n·(1/g, 1/g²)), g the plastic number
    1.3247..., M. Roberts 2018, a rank-1 lattice-like sequence whose successive points fill the
    square evenly), shifted per pixel by a uniform offset fixed for the whole render (a
    Cranley-Patterson rotation; R. Cranley and T. Patterson 1976). Every position is uniform in its
    pixel, and a pixel's positions over the passes cover it evenly instead of clumping as
    independent jitter does: the mean over passes of the visible points' estimates (each a density
    estimate at one position in the pixel) then converges faster than P^-1/2 wherever the light
    varies smoothly within the pixel, as a sharp caustic's smoothed by the gather radius does."""
    cam = scene.camera
    g = 1.32471795724474602596
    n = jnp.asarray(pass_index).astype(jnp.uint32) * jnp.uint32(samples) + jnp.arange(samples, dtype=jnp.uint32)
    # frac(n·a) in 32-bit fixed point: n·round(a·2^32) wraps modulo 2^32 exactly (float32 would
    # lose the fraction once n·a is large)
    a = jnp.array([round((1.0 / g) * 2**32), round((1.0 / (g * g)) * 2**32)], jnp.uint32)
    seq = (n[:, None] * a[None, :] >> jnp.uint32(8)).astype(jnp.float32) * 2.0**-24  # (k, 2)
    key = jax.random.fold_in(jax.random.key(jnp.asarray(scene.settings.seed, jnp.uint32)), jnp.uint32(0x5BD1E995))
    shift = jax.random.uniform(key, (cam.height, cam.width, 1, 2))
    return jnp.minimum(jnp.mod(shift + seq[None, None], 1.0), 1.0 - 2.0 ** -24)


def visible_points(scene, key, samples: int = 1, pass_index=None, table=None):
    """`samples` camera rays per pixel to their visible points, S = H·W·samples ordered (row,
    column, sample); returns (vp dict, direct (S, 3), first hits). With `pass_index` the rays' positions
    in their pixels are `subpixel_positions`', else independent uniform jitter. The vp dict's `foot`
    is the pixel footprint at the visible point (path length times `pixel_angle`). table: the emitter
    table of the next-event estimate (`emitter_table`; made there when None)."""
    pi = None if pass_index is None else jnp.asarray(pass_index)[None]
    out = visible_point_batch(scene, key[None], samples, pi, table)
    return jax.tree.map(lambda x: x[0], out)


def visible_point_batch(scene, keys, samples: int = 1, pass_index=None, table=None):
    """`visible_points` of several passes at once, one per key of `keys` (B,) (and pass index of
    `pass_index` (B,), if given): every output gains a leading axis of B, and pass b's are those of
    `visible_points(scene, keys[b], samples, pass_index[b])` (the same random streams), traced as one
    batch of B·S camera paths, one traversal launch a bounce for all of them."""
    st, cam, mats = scene.settings, _sg(scene.camera), _sg(scene.materials)
    geo = _sg(scene.geometry)
    scene = _sg(scene)
    D = st.max_depth
    B = keys.shape[0]
    S1 = cam.num_pixels * samples
    S = B * S1  # rows: pass b's are b·S1 ... (b + 1)·S1 − 1
    models = _models(mats)
    al = scene.area_lights
    has_tri = al is not None and al.count > 0
    env = getattr(scene, "environment", None)
    kcam, kpath, knee = jnp.moveaxis(jax.vmap(lambda k: jax.random.split(k, 3))(keys), 1, 0)

    def rows(x):  # (B, S1, ...) -> (B·S1, ...)
        return x.reshape((S,) + x.shape[2:])

    def rays(kc, pi):
        sub = None if pi is None else subpixel_positions(scene, pi, samples)
        return camera.generate_rays(cam, samples, jax.random.bits(kc, (), jnp.uint32), True, subpixel=sub)

    if pass_index is None:
        o, d = jax.vmap(lambda kc: rays(kc, None))(kcam)
    else:
        o, d = jax.vmap(rays)(kcam, pass_index)
    o, d = rows(o), normalize(rows(d))
    s0 = geo.surface(jnp.zeros(S, jnp.int32), jnp.zeros(S), jnp.zeros(S))
    vp = dict(surface=s0, p=jnp.zeros((S, 3)), ng=jnp.zeros((S, 3)), wo=jnp.zeros((S, 3)).at[:, 2].set(1.0),
              frame=(jnp.zeros((S, 3)),) * 3, beta=jnp.zeros((S, 3)), depth=jnp.zeros(S, jnp.int32),
              found=jnp.zeros(S, bool), foot=jnp.zeros(S))
    first = dict(prim=jnp.full(S, -1, jnp.int32), u=jnp.zeros(S), v=jnp.zeros(S), t=jnp.zeros(S), d=d)
    alive = jnp.ones(S, bool)
    beta = jnp.ones((S, 3))
    emitted = jnp.zeros((S, 3))
    dist = jnp.zeros(S)  # path length from the camera, through the delta bounces
    ang = pixel_angle(cam)
    for k in range(D + 1):  # static: D is small and the camera chain usually ends at the first hit
        u = rows(jax.vmap(lambda kp: jax.random.uniform(jax.random.fold_in(kp, k), (S1, 3)))(kpath))
        hit = intersect_active(geo, o, d, alive)
        prim = jnp.where(alive, hit.prim, -1)
        found = prim >= 0
        if k == 0:
            first = dict(prim=prim, u=hit.u, v=hit.v, t=jnp.where(found, hit.t, 0.0), d=d)
        dist = dist + jnp.where(found, hit.t, 0.0)
        s = geo.surface(prim, hit.u, hit.v)
        s = eqx.tree_at(lambda x: x.material, s, jnp.where(found, s.material, 0))
        if env is not None:
            emitted = emitted + jnp.where((alive & ~found)[:, None], beta * envmap.radiance(env, d), 0.0)
        if has_tri:
            lit = found & (-dot(d, s.ng) > 0)
            emitted = emitted + jnp.where(lit[:, None], beta * al.emission[s.material], 0.0)
        if k == D:
            break
        no, nd, fac, ok, is_delta = _scatter(scene, models, s, d, found, u)
        here = found & ~is_delta
        ng, ns, _ = oriented(s, d)
        frame = local_frame(ns, s.tangent)
        new = dict(surface=s, p=s.p, ng=ng, wo=to_local(-d, frame), frame=frame, beta=beta,
                   depth=jnp.full(S, k + 1, jnp.int32), found=here, foot=dist * ang)
        vp = jax.tree.map(lambda a, b: jnp.where(here.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), new, vp)
        alive = found & is_delta & ok
        beta = jnp.where(alive[:, None], beta * fac, 0.0)
        o, d = no, nd
    direct = emitted + vp["beta"] * _nee(scene, vp, models, knee, table)
    per_pass = lambda x: x.reshape((B, S1) + x.shape[1:])  # noqa: E731
    return jax.tree.map(per_pass, (vp, jnp.where(jnp.isfinite(direct), direct, 0.0), first))


def _nee(scene, vp, models, keys, table=None):
    """Direct light at the visible points: every point light and one sample of the emissive
    triangles or the environment (probability 1/2 each when both exist), light sampling only.
    keys (B,): the passes' keys, whose rows the visible points are in turn (`visible_point_batch`).
    table: the emitter table (`emitter_table`; made here when None)."""
    geo, mats = scene.geometry, scene.materials
    s = vp["surface"]
    S = s.p.shape[0]
    ng, frame, wo, found = vp["ng"], vp["frame"], vp["wo"], vp["found"]
    eps = offset_scale(s.p)
    origin = s.p + ng * eps
    params = {kk: _params(mats, s, kk) for kk, _ in models}
    sel = {kk: mats.model_id[s.material] == kk for kk, _ in models}
    al, env = scene.area_lights, getattr(scene, "environment", None)
    has_tri = al is not None and al.count > 0
    n_cls = int(has_tri) + int(env is not None)
    p_tri = (1.0 / n_cls) if has_tri else 0.0
    u = jax.vmap(lambda k: jax.random.uniform(k, (S // keys.shape[0], 4)))(keys).reshape(S, 4)
    out = jnp.zeros((S, 3))
    rays_o, rays_d, rays_t, contrib = [], [], [], []
    nl = scene.lights.count
    if nl:
        wi_p, dist_p, scale_p = _lights.incident(scene.lights, s.p)
        lit = found[:, None] & (dot(wi_p, ng[:, None, :]) > 0)
        wi_pl = to_local(wi_p, tuple(x[:, None, :] for x in frame))
        f_p = _eval_f(models, params, sel, wi_pl, wo[:, None, :], extra_dims=1)
        contrib.append((f_p * jnp.maximum(wi_pl[..., 2], 0.0)[..., None] * scale_p).reshape(-1, 3))
        rays_o.append(jnp.broadcast_to(origin[:, None, :], wi_p.shape).reshape(-1, 3))
        rays_d.append(wi_p.reshape(-1, 3))
        rays_t.append(jnp.where(lit, dist_p - 2.0 * eps, -1.0).reshape(-1))
    if n_cls:
        wi_c = jnp.zeros((S, 3)).at[:, 2].set(1.0)
        le_c = jnp.zeros((S, 3))
        p_c = jnp.zeros(S)
        dist_c = jnp.full(S, jnp.inf)
        pick_tri = u[:, 0] < p_tri
        if has_tri:
            table = emitter_table(scene) if table is None else table
            wi_t, le_t, p_t, dist = sample_area_light(geo, al, table, origin, u[:, 1:4], p_tri)
            wi_c = jnp.where(pick_tri[:, None], wi_t, wi_c)
            le_c = jnp.where(pick_tri[:, None], le_t, le_c)
            p_c = jnp.where(pick_tri, p_t, p_c)
            dist_c = jnp.where(pick_tri, dist, dist_c)
        if env is not None:
            wi_e, le_e, pdf_e = envmap.sample(env, u[:, 2:4])
            wi_c = jnp.where(pick_tri[:, None], wi_c, wi_e)
            le_c = jnp.where(pick_tri[:, None], le_c, le_e)
            p_c = jnp.where(pick_tri, p_c, (1.0 - p_tri) * pdf_e)
        wi_cl = to_local(wi_c, frame)
        f_c = _eval_f(models, params, sel, wi_cl, wo)
        lit_c = found & (dot(wi_c, ng) > 0) & (p_c > 0)
        contrib.append(f_c * (jnp.maximum(wi_cl[:, 2], 0.0) / jnp.where(p_c > 0, p_c, 1.0))[:, None] * le_c)
        rays_o.append(origin)
        rays_d.append(wi_c)
        rays_t.append(jnp.where(lit_c, dist_c - 2.0 * eps[:, 0], -1.0))
    if rays_o:
        tmax = jnp.concatenate(rays_t)
        occ = geo.occluded(jnp.concatenate(rays_o), jnp.concatenate(rays_d), tmax)
        vis = ((tmax > 0) & ~occ)[:, None]
        c = jnp.where(vis, jnp.concatenate(contrib), 0.0)
        if nl:
            out = out + jnp.sum(c[: S * nl].reshape(S, nl, 3), axis=1)
        if n_cls:
            out = out + c[S * nl:]
    return out


# ---------------------------------------------------------------------------------------------- passes

def start(scene) -> SPPMState:
    """The statistics before the first pass: N = 0, r = `[render] radius` (0: set at each chain's
    first visible point, see `initial_radius`), τ = 0."""
    cam = scene.camera
    k = camera_samples(scene)
    S = cam.num_pixels * k
    r0 = initial_radius(scene)
    return SPPMState(jnp.zeros(S), jnp.full(S, r0 * r0, jnp.float32), jnp.zeros((S, 3)), jnp.zeros((S, 3)),
                     jnp.asarray(0, jnp.int32), cam.height, cam.width, photons_per_pass(scene), k)


def pass_keys(scene, passes) -> Array:
    """Pass P's random keys, (3,): fold_in(key(seed), P) split between camera, photons and the grid."""
    key = jax.random.fold_in(jax.random.key(jnp.asarray(scene.settings.seed, jnp.uint32)),
                             jnp.asarray(passes).astype(jnp.uint32))
    return jax.random.split(key, 3)


def _radii(state: SPPMState, vp, levels: int = DEFAULT_GRID_LEVELS["cpu"]):
    """The radii this pass gathers with and the grid's finest cell edge: (state, cell).

    A chain without a radius yet (r² = 0) takes RADIUS_PIXELS pixel footprints at its visible point.
    The radii that matter are those of this pass's visible points that have received photons before
    (all of them before any has): points that never receive any (in shadow, facing away from every
    light) keep their initial radius, and cells sized by them would be wide, where a bright
    caustic's cells then hold far more deposits than the CELL_PHOTONS read of each. A radius above
    r_c, the CELL_QUANTILE quantile of those, is clamped to it with N and τ scaled by the area ratio,
    the uniform-density step of the progressive update itself (Hachisuka & Jensen 2009: the density
    N/(πr²) and the radiance τ/(πr²) stay the same), so the estimate stays consistent. The finest
    cells are twice the FINE_QUANTILE quantile, or 2·r_c / 2^(L − 1) where that is larger (L = `levels`),
    so that the coarsest level's cells are at least 2·r_c."""
    found = vp["found"]
    r2 = jnp.where((state.r2 > 0) | ~found, state.r2, jnp.square(RADIUS_PIXELS * vp["foot"]))
    rec = found & (state.n > 0)
    rec = jnp.where(jnp.any(rec), rec, found)
    cnt = jnp.sum(rec)
    srt = jnp.sort(jnp.where(rec, r2, jnp.inf))

    def quantile(q):
        return jnp.where(cnt > 0, srt[jnp.clip(jnp.ceil(q * cnt).astype(jnp.int32) - 1, 0, r2.shape[0] - 1)], 0.0)

    rc2 = quantile(CELL_QUANTILE)
    clamp = found & (r2 > rc2) & (rc2 > 0)
    ratio = jnp.where(clamp, rc2 / jnp.where(clamp, r2, 1.0), 1.0)
    state = SPPMState(state.n * ratio, r2 * ratio, state.tau * ratio[:, None], state.direct, state.passes,
                      state.height, state.width, state.photons, state.samples)
    # the finest level's cells: 2x the FINE_QUANTILE radius, unless the coarsest would then be
    # smaller than 2·r_c
    fine = jnp.maximum(jnp.sqrt(quantile(FINE_QUANTILE)), jnp.sqrt(rc2) * 2.0 ** (1 - levels))
    return state, jnp.maximum(2.0 * fine, 1e-6)


def _update(state: SPPMState, m, phi, direct, a: float) -> SPPMState:
    # the progressive update of Hachisuka & Jensen 2009 (module docstring) with this pass's M and Φ
    n_new = state.n + a * m
    ratio = jnp.where(state.n + m > 0, n_new / jnp.where(state.n + m > 0, state.n + m, 1.0), 1.0)
    r2_new = state.r2 * ratio
    tau = (state.tau + phi) * ratio[:, None]
    return SPPMState(n_new, r2_new, tau, state.direct + direct, state.passes + 1, state.height, state.width,
                     state.photons, state.samples)


def _pass(scene, state: SPPMState, with_first: bool = False, sources=None, dep: Deposits | None = None,
          vis=None):
    # dep, vis: this pass's deposits and (visible points, direct light, first hits) when traced
    # beforehand (`_passes` batches them over passes off the CPU)
    kvp, kph, kgrid = pass_keys(scene, state.passes)
    if vis is None:
        vis = visible_points(scene, kvp, state.samples, state.passes, table=None if sources is None else sources[1])
    vp, direct, first = vis
    levels = grid_levels(scene)
    state, cell = _radii(state, vp, levels)
    if dep is None:
        dep = trace_photons(scene, kph, state.photons, sources=sources)
    grid = build_grid(dep, cell, kgrid, levels)
    m, phi = gather(scene, grid, vp, state.r2)
    new = _update(state, m, phi, direct, alpha(scene))
    return (new, first) if with_first else new


def pass_share(scene, state: SPPMState, axis: str, count: int, sources=None) -> SPPMState:
    """One pass with its photons split over the `count` devices of mesh axis `axis`, to run inside
    `shard_map` with the scene and the state replicated: every device computes the same visible
    points (the pass's camera keys), traces its share of the photons (`trace_photons`' share: photon
    i the one-device pass's photon i; ceil(n/count) per device, the padding carrying no power),
    builds its own hash grid of its deposits and gathers at every visible point; M and Φ are summed
    over the devices (`psum`) before the progressive update, which every device then applies alike.

    Equal to `step` up to the summation order of M and Φ (and the rounding of a differently compiled
    program) wherever no bucket of the one-device grid holds more than CELL_PHOTONS deposits: then
    every deposit within a radius is read on either side. A fuller bucket is subsampled on each
    device among that device's deposits, which is another unbiased estimate of the same sum."""
    kvp, kph, kgrid = pass_keys(scene, state.passes)
    vp, direct, _ = visible_points(scene, kvp, state.samples, state.passes,
                                   table=None if sources is None else sources[1])
    levels = grid_levels(scene)
    state, cell = _radii(state, vp, levels)
    d = lax.axis_index(axis)
    dep = trace_photons(scene, kph, state.photons, share=(d, count), sources=sources)
    grid = build_grid(dep, cell, jax.random.fold_in(kgrid, d), levels)
    m, phi = lax.psum(gather(scene, grid, vp, state.r2), axis)
    return _update(state, m, phi, direct, alpha(scene))


def photon_batch(scene, photons: int) -> int:
    """Passes whose photons `steps` traces in one batch (static): 1 on the CPU (where a batch's
    bounce state would leave the caches), else as many as keep PHOTON_BATCH photons in flight, at most
    MAX_PHOTON_BATCH; 1 where one pass's photons alone fill that."""
    if _on_cpu():
        return 1
    return int(max(1, min(MAX_PHOTON_BATCH, PHOTON_BATCH // max(int(photons), 1))))


def _passes(scene, state: SPPMState, count) -> SPPMState:
    # `count` (traced) passes in a loop whose body is the one pass: P passes in one call are the same
    # operations on the same random streams (the pass index is the state's) as P calls of one pass
    sources = photon_sources(scene)  # once, outside the loop
    G = photon_batch(scene, state.photons)
    if G == 1:
        return lax.fori_loop(0, count, lambda i, st: _pass(scene, st, sources=sources), state)

    def group(g, st):
        # the next G passes' camera paths and photons, each in one batch (their random streams are
        # the passes' own, so the passes are those of one pass a call), then each pass's grid,
        # gather and update in turn
        index = st.passes + jnp.arange(G)
        keys = jax.vmap(lambda i: pass_keys(scene, i))(index)  # (G, 3): camera, photons, grid
        vis = visible_point_batch(scene, keys[:, 0], st.samples, index, sources[1])
        deps = trace_photon_batch(scene, keys[:, 1], st.photons, sources=sources)
        pick = lambda j: (lambda x: x[j])  # noqa: E731
        return lax.fori_loop(0, G, lambda j, s2: _pass(scene, s2, sources=sources, dep=jax.tree.map(pick(j), deps),
                                                       vis=jax.tree.map(pick(j), vis)), st)

    # whole batches, then the rest one pass at a time (no photons traced for nothing)
    state = lax.fori_loop(0, count // G, group, state)
    return lax.fori_loop(0, count % G, lambda i, st: _pass(scene, st, sources=sources), state)


#: `count` passes (camera pass, photon pass, hash grid, gather, progressive update each), compiled once
#: per scene structure: `steps(scene, state, count)` -> the `SPPMState` after them; `count` an int32
#: scalar, traced like the pass index, so no pass count compiles anything new. `step` is the way to call it.
steps = jax.jit(_passes)


def pass_count(count) -> Array:
    """`count` as the int32 scalar `steps` takes: the same argument type for every count (a Python int
    would be weakly typed, a second compilation)."""
    return jnp.asarray(count, jnp.int32)


def step(scene, state: SPPMState, count: int = 1) -> SPPMState:
    """`count` passes after `state` in one compiled call (`steps`): equal to `count` calls of one pass."""
    return steps(scene, state, pass_count(count))


def passes_per_call(seconds_per_pass: float, remaining: int, target: float = CALL_SECONDS) -> int:
    """How many passes the next call should run: as many as take about `target` seconds at the
    measured `seconds_per_pass` (nan or 0 before any was measured: 1), at least 1 and at most
    `remaining` and MAX_PASSES_PER_CALL. The passes a call runs never change the image (`steps`)."""
    fit = target / seconds_per_pass if seconds_per_pass > 0 else 1.0
    return int(max(1, min(remaining, MAX_PASSES_PER_CALL, math.floor(fit) if math.isfinite(fit) else 1)))


def _first_aovs(scene):
    key = jax.random.fold_in(jax.random.key(jnp.asarray(scene.settings.seed, jnp.uint32)), jnp.uint32(0))
    _, _, first = visible_points(scene, jax.random.split(key, 3)[0], 1, 0)
    cam = scene.camera
    return build_aovs(scene, *(first[k] for k in ("prim", "u", "v", "t", "d")), shape=(cam.height, cam.width))


#: The AOVs (depth, normal, albedo, object_id) of the first pass's camera hits, compiled.
first_aovs = jax.jit(_first_aovs)


def accumulate(scene, state: SPPMState | None = None, passes: int = 1) -> SPPMState:
    """Add `passes` passes to `state` (None: start) in one compiled call; the compiled program is
    reused for every pass index and count (both traced)."""
    if state is None:
        check(scene)
        state = start(scene)
    return step(scene, state, passes)


def render(scene, *, aovs: bool = False, window: camera.Window | None = None):
    """`settings.spp` passes of SPPM in one program: the (H, W, 3) image; with `aovs` a pair (image,
    AOVs of the first pass's camera hits). SPPM has no tiles (a pass is one whole-frame program)."""
    if window is not None:
        raise InputError(f"{scene.source}: integrator 'sppm' renders whole frames, not tiles")
    check(scene)
    state0 = start(scene)
    sources = photon_sources(scene)
    state, first = _pass(scene, state0, with_first=True, sources=sources)
    state = lax.fori_loop(1, scene.settings.spp, lambda i, st: _pass(scene, st, sources=sources), state)
    img = state.image
    if not aovs:
        return img
    cam = scene.camera
    # each pixel's first camera sample (the samples of a pixel are consecutive)
    first = {k: v[:: state.samples] for k, v in first.items()}
    return img, build_aovs(scene, *(first[k] for k in ("prim", "u", "v", "t", "d")), shape=(cam.height, cam.width))
