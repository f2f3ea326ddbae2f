"""The Whitted integrator, split into a non-differentiable trace and a differentiable shade.

Radiance (Größler & Zettwitz, "An interactive ray tracing system based on Nvidia OptiX", 2015, eqs. 2, 3 and 23), for a hit on an opaque material with mirror
coefficient δ, and on glass with Fresnel reflectance R:

    L(x, wo) = δ·L(x, ω_r) + (1 − δ)·Σ_lights f_r(wi, wo)·I·cosθ_i / d² · V(x, light)
    L(x, wo) = R·L(x, ω_r) + (1 − R)·L(x, ω_t)   (glass: Schlick or exact Fresnel R, Snell ω_t)

Rays that escape return the background radiance, or the environment's (`jaxrt.envmap`) if the
scene has one.

Trace once, shade many
----------------------
`trace(scene) -> GBuffer` follows the ray tree level by level and records, for every ray, only
what does not depend on material values: hit primitive and barycentrics, direction, the parent ray
and which branch (mirror / glass reflection / glass transmission) produced it, the pixel, and the
shadow-ray visibility of every light. `shade(gbuffer, scene)` re-evaluates the hit surfaces from
primitive ids (differentiably), evaluates the BRDFs and Fresnel terms and sums the tree into an
image. Gradients flow to material parameters, δ, glass n_t (through R only: the traced paths stay
fixed) and light positions/intensities (visibility stays fixed). Fitting caches the GBuffer and
calls `shade` only.

`whitted(scene)` (what `render.frame` runs) is `shade(trace(scene), scene)` in one pass: the trace
loop (`_trace_loop`, shared with `trace`) also adds each level's contribution, the carried path
throughput times the local radiance of the same hit surface and shadow rays, into the image as it
goes, so surfaces are evaluated once and no GBuffer is written; the loop's only per-level device
predicates are its own condition and, in scenes with glass, the overflow test before dropping
branches. The carried throughput is the product of δ, R and 1 − R that `shade` rebuilds from the
parents, so the image is the same up to float summation order. Gradients (a custom VJP) are
the two-pass composition's: differentiated, `whitted` runs `trace` and `shade` and pulls back
through `shade`. Forward-mode autodiff is not defined through `whitted`.

The ray tree in static shapes
-----------------------------
Each level of the tree is a fixed-width array of B = ray_budget · H·W·spp ray slots. A ray spawns
at most two children (a mirror bounce, or glass reflection + transmission). Children are written
densely into the next level's slots by a prefix sum, in parent order (which keeps rays of
neighbouring pixels together). If a level would need more than B slots, the branches with the
smallest path throughput are dropped first (every ray's dominant branch fits, since a level has
at most B parents); the GBuffer counts dropped branches. Scenes without glass never branch, so
ray_budget = 1 loses nothing; the default is 2 for scenes with glass. The levels are a
`lax.while_loop` that stops as soon as no ray is alive, so a scene without mirrors traces one
level whatever max_depth is (max_depth 1, direct light only, runs its one level without a loop).
A child whose weight is zero at trace time (δ = 0) is not traced.

Surfaces
--------
Rays leave hit points offset along the geometric normal (`jaxrt.shading.surface`). Surfaces are
two-sided for opaque materials; glass decides inside/outside from the geometric normal of each hit (no nested
media: glass inside glass is treated as glass in air). Shadow rays through glass carry its Fresnel
transmittance, unrefracted (`jaxrt.shading.shadows`; `[render] glass_shadows = "opaque"` restores
the opaque shadows of Whitted's model); the GBuffer's `visible` is then that transmittance (float)
and, like visibility, fixed at trace time (no gradient to n_t through shadows).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

import brdfs
from jaxrt import camera
from jaxrt import lights as _lights
from jaxrt.integrators.common import intersect_surface_active, sample_order_arrays
from jaxrt.shading.aovs import build_aovs
from jaxrt.shading import shadows as _shadows
from jaxrt.shading.direct import local_radiance
from jaxrt.shading.material import delta_and_glass, glass_split, is_glass
from jaxrt.shading.surface import dot, mirror_dir, normalize, offset_scale, oriented

MIRROR, GLASS_R, GLASS_T = 0, 1, 2


def transmits(scene) -> bool:
    """Whether shadow rays carry glass's Fresnel transmittance (static): scenes with glass whose
    `[render] glass_shadows` is "transmit" (the default). Scenes without glass keep the boolean
    any-hit shadow test, so their images are the ones they were before glass let light through."""
    return (getattr(scene.settings, "glass_shadows", "transmit") == "transmit"
            and any(brdfs.get(m).delta for m in scene.materials.models))


class GBuffer(eqx.Module):
    """Everything shading needs that does not depend on material or light values.

    Arrays are (D, B, ...) for D = max_depth levels of B ray slots (see module docstring).
    active: ray exists; prim: hit face or -1 (escaped); u, v: barycentrics; t: hit distance;
    direction: unit ray direction; parent: slot in the previous level (-1 on level 0);
    branch: MIRROR / GLASS_R / GLASS_T; pixel: flat pixel index; visible: (D, B, L) shadow rays
    (bool, or the float transmittance where glass transmits: `transmits`);
    weight: path throughput reaching the ray (product of δ, R, 1 − R along its branches) for the
    material values at trace time (`shade` recomputes it from the current values).
    dropped: () number of branches dropped for lack of slots.
    """

    active: Bool[Array, "D B"]
    prim: Int[Array, "D B"]
    u: Float[Array, "D B"]
    v: Float[Array, "D B"]
    t: Float[Array, "D B"]
    direction: Float[Array, "D B 3"]
    parent: Int[Array, "D B"]
    branch: Int[Array, "D B"]
    pixel: Int[Array, "D B"]
    visible: Bool[Array, "D B L"]
    weight: Float[Array, "D B"]
    dropped: Int[Array, ""]


def _trace_loop(scene, *, record: bool, image: bool, aovs: bool = False, window: camera.Window | None = None):
    """The ray-tree loop shared by `trace` and the fused `whitted` forward pass.

    record: fill a GBuffer; image: accumulate each level's contribution (path throughput ·
    `local_radiance`) into the image as the level is traced; aovs: keep the level-0 hit of each
    pixel's first sample for `build_aovs`. The flags are static: a pass that does not record carries
    no GBuffer at all (not relying on XLA to drop dead loop state).

    window: None for the whole image, else one tile (`camera.Window`): its pixels and its run of
    samples, the rest of the loop unchanged (ray slots, budget and image are the tile's). Every
    slot's arithmetic depends on its own ray only, and a pixel's samples and their children keep
    their relative slot order, so a tile holding all spp samples of its pixels adds each pixel's
    contributions in the whole image's order (the same floats wherever the compiler evaluates both
    program shapes alike: `jaxrt.render_tiles`). Samples past the window's `count` start inactive.

    Returns:
        (GBuffer or None, image (H, W, 3) or None, AOV dict or None), with the window's (height,
        width) for H, W; the image is divided by the scene's spp (a window's share of the pixel
        mean). Not differentiable (the whole scene is under stop_gradient); `whitted` supplies the
        gradients.
    """
    scene = jax.lax.stop_gradient(scene)
    geo, mats, cam, st = scene.geometry, scene.materials, scene.camera, scene.settings
    D = st.max_depth
    th, tw, spp = (cam.height, cam.width, st.spp) if window is None else (window.height, window.width, window.spp)
    npix = th * tw
    n = npix * spp
    B = st.ray_budget * n
    L = scene.lights.count
    # the throughput's dtype follows the scene's values (float64 when a test asks for it)
    wdtype = jnp.result_type(mats.delta.dtype, jnp.float32)
    glass_shadows = transmits(scene)
    # on the CPU with Embree the traversal traces each hit's shadow rays in the same call (the same
    # segments, made in the kernel; `shadow_segments`): no shadow-ray arrays, one pass over the rays
    native_shadows = not glass_shadows and geo.shadows_in_traversal()

    order, first = sample_order_arrays(th, tw, spp)
    # made in slot order (no gather of the rays), unit directions
    o0, d0 = camera.generate_rays(cam, st.spp, st.seed, window=window, order=order)
    pad = B - n
    o0 = jnp.pad(o0, ((0, pad), (0, 0)))
    d0 = jnp.concatenate([d0, jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], d0.dtype), (pad, 3))])
    act0 = jnp.arange(B) < n
    if window is not None:
        act0 = act0 & (jnp.pad(order % spp, (0, pad)) < window.count)
    pix0 = jnp.pad(order // spp, (0, pad))

    buf = None
    if record:
        buf = GBuffer(
            active=jnp.zeros((D, B), bool), prim=jnp.full((D, B), -1, jnp.int32),
            u=jnp.zeros((D, B)), v=jnp.zeros((D, B)), t=jnp.zeros((D, B)),
            direction=jnp.zeros((D, B, 3)), parent=jnp.full((D, B), -1, jnp.int32),
            branch=jnp.zeros((D, B), jnp.int32), pixel=jnp.zeros((D, B), jnp.int32),
            visible=jnp.zeros((D, B, L), wdtype if glass_shadows else bool), weight=jnp.zeros((D, B)), dropped=jnp.zeros((), jnp.int32),
        )
    img = jnp.zeros((npix, 3), wdtype) if image else None
    rec = None
    if aovs:
        rec = dict(prim=jnp.full((npix,), -1, jnp.int32), u=jnp.zeros(npix), v=jnp.zeros(npix), t=jnp.zeros(npix),
                   d=jnp.zeros((npix, 3)))
    ray0 = (o0, d0, act0, pix0, jnp.full((B,), -1, jnp.int32), jnp.zeros((B,), jnp.int32), act0.astype(wdtype))

    def cond(carry):
        k, ray = carry[:2]
        return (k < D) & jnp.any(ray[2])

    def body(carry):
        k, (o, d, act, pix, parent, branch, weight), buf, img, rec = carry
        # the surface from the traversal's hit points and normals (the pass is under stop_gradient;
        # on the CPU Embree returns them, and the corners are not gathered again)
        if native_shadows:
            hit, s, occ = geo.intersect_surface_shadowed(o, d, 0.0, jnp.where(act, jnp.inf, -1.0),
                                                         scene.lights.position)
        else:
            hit, s = intersect_surface_active(geo, o, d, act)
        prim = jnp.where(act, hit.prim, -1)
        found = prim >= 0
        u, v, t = (jnp.where(found, x, 0.0) for x in (hit.u, hit.v, hit.t))
        ng, ns, _ = oriented(s, d)
        eps = offset_scale(s.p)
        # shadow rays, one per (slot, light)
        wi, dist, so, smax = shadow_segments(scene.lights, s.p, ng, eps)
        lit = found[:, None] & (dot(wi, ng[:, None, :]) > 0) & ~is_glass(mats, s.material)[:, None]
        smax = jnp.where(lit, smax, -1.0)
        if native_shadows:
            # traced with the hits (inactive slots and misses are not lit)
            visible = lit & ~occ
        elif glass_shadows:
            # glass lets light through: V is the Fresnel transmittance (jaxrt.shading.shadows)
            visible = lit * _shadows.transmittance(scene, so.reshape(-1, 3), wi.reshape(-1, 3),
                                                   smax.reshape(-1)).reshape(B, L)
        else:
            # from the light: coherent origins (single-level BVH; the two-level one traces forwards)
            occ = geo.occluded(so.reshape(-1, 3), wi.reshape(-1, 3), smax.reshape(-1),
                            from_end=True).reshape(B, L)
            visible = lit & ~occ
        if record:
            buf = GBuffer(
                active=buf.active.at[k].set(act), prim=buf.prim.at[k].set(prim),
                u=buf.u.at[k].set(u), v=buf.v.at[k].set(v), t=buf.t.at[k].set(t), direction=buf.direction.at[k].set(d),
                parent=buf.parent.at[k].set(parent), branch=buf.branch.at[k].set(branch),
                pixel=buf.pixel.at[k].set(pix), visible=buf.visible.at[k].set(visible),
                weight=buf.weight.at[k].set(jnp.where(act, weight, 0.0)), dropped=buf.dropped,
            )
        delta, glass = delta_and_glass(mats, s, found)
        if image:
            # `weight` is the product of δ, R, 1 − R along the path for the current values: the
            # throughput `shade` rebuilds from the parents, so the sum is the same image
            local = local_radiance(scene, s, d, visible, found, delta, glass)
            contrib = jnp.where(act[:, None], weight[:, None] * local, 0.0)
            if D == 1 and spp == 1:
                # one ray per pixel and no children: the image is the level's contributions in pixel
                # order, a gather of a static permutation instead of a scatter-add into zeros (the same
                # sums, 0 + x; on the CPU the scatter was ~6 % of a 512² direct frame)
                img = img + contrib[first]
            else:
                # (indices_are_sorted, though true, made this scatter-add 2.4x slower on an H200)
                img = img.at[jnp.where(act, pix, npix)].add(contrib, mode="drop")
        if aovs:
            new = dict(prim=prim[first], u=u[first], v=v[first], t=t[first], d=d[first])
            rec = jax.tree_util.tree_map(lambda a, b: jnp.where(k == 0, b, a), rec, new)
        if D == 1:
            # one level (direct lighting): no ray has children and the loop ends here, so the
            # children's directions, ranking and compaction below would all be discarded
            return k + 1, (o, d, jnp.zeros_like(act), pix, parent, branch, weight), buf, img, rec
        # children: (primary, secondary) per parent
        w_mirror = weight * delta
        r = jnp.zeros(B, wdtype)
        dr = mirror_dir(d, ng, ns)
        dt = d
        t_ok = jnp.zeros(B, bool)
        for kk, name in enumerate(mats.models):
            if brdfs.get(name).delta:
                rk, drk, dtk, okk = glass_split(mats, s, d, kk)
                sel = glass & (mats.model_id[s.material] == kk)
                r = jnp.where(sel, rk, r)
                dr = jnp.where(sel[:, None], drk, dr)
                dt = jnp.where(sel[:, None], dtk, dt)
                t_ok = jnp.where(sel, okk, t_ok)
        w_r = jnp.where(glass, weight * r, w_mirror)
        w_t = jnp.where(glass & t_ok, weight * (1.0 - r), 0.0)
        b_r = jnp.where(glass, GLASS_R, MIRROR)
        refl_first = w_r >= w_t
        cand_w = jnp.stack([jnp.where(refl_first, w_r, w_t), jnp.where(refl_first, w_t, w_r)], 1)  # (B, 2)
        cand_d = jnp.stack([jnp.where(refl_first[:, None], dr, dt), jnp.where(refl_first[:, None], dt, dr)], 1)
        refl_o = s.p + ng * eps
        tran_o = s.p - ng * eps
        cand_o = jnp.stack(
            [jnp.where(refl_first[:, None], refl_o, tran_o), jnp.where(refl_first[:, None], tran_o, refl_o)], 1)
        cand_b = jnp.stack([jnp.where(refl_first, b_r, GLASS_T), jnp.where(refl_first, GLASS_T, b_r)], 1)
        alive = (cand_w > 0) & (k + 1 < D)
        cw, cd, co, cb, ca = (x.reshape((2 * B,) + x.shape[2:]) for x in (cand_w, cand_d, cand_o, cand_b, alive))
        cparent = jnp.repeat(jnp.arange(B, dtype=jnp.int32), 2)
        cpix = jnp.repeat(pix, 2)
        total = jnp.sum(ca)

        def keep_best(ca):
            # rank alive candidates by weight; keep the B heaviest
            order = jnp.argsort(jnp.where(ca, -cw, jnp.inf))
            rank = jnp.zeros(2 * B, jnp.int32).at[order].set(jnp.arange(2 * B, dtype=jnp.int32),
                                                             unique_indices=True)  # a permutation
            return ca & (rank < B)

        if any(brdfs.get(m).delta for m in mats.models):
            keep = jax.lax.cond(total > B, keep_best, lambda ca: ca, ca)
        else:
            # without glass a ray has at most one child, so a level never overflows; skipping the
            # cond saves a device-to-host read of its predicate per level on GPUs
            keep = ca
        # Compaction: one scatter of candidate indices (dropped candidates go to distinct slots past
        # the end, so every index is unique: plain stores, not a serialised scatter), then gathers,
        # which XLA fuses into one kernel for all seven arrays rather than seven scatters
        # (measured: BENCHMARKS.md).
        slot = jnp.where(keep, jnp.cumsum(keep) - 1, B + jnp.arange(2 * B))
        src = jnp.full(B, 2 * B, jnp.int32).at[slot].set(jnp.arange(2 * B, dtype=jnp.int32), mode="drop",
                                                         unique_indices=True)
        filled = src < 2 * B
        src = jnp.minimum(src, 2 * B - 1)
        new = lambda x, fill: jnp.where(filled.reshape((B,) + (1,) * (x.ndim - 1)), x[src], fill)  # noqa: E731
        ray = (
            new(co, 0.0), normalize(new(cd, 1.0)), new(keep, False), new(cpix, 0), new(cparent, -1),
            new(cb, 0), new(cw, 0.0),
        )
        if record:
            buf = eqx.tree_at(lambda g: g.dropped, buf, buf.dropped + total - jnp.sum(keep))
        return k + 1, ray, buf, img, rec

    carry = (jnp.asarray(0), ray0, buf, img, rec)
    if D == 1:
        # one level: the loop would run its body once (an inactive slot adds nothing), and as a
        # while loop every carried array is stored between the loop's pieces, which XLA may fuse
        # across when the body stands alone
        _, _, buf, img, rec = body(carry)
    else:
        _, _, buf, img, rec = jax.lax.while_loop(cond, body, carry)
    if image:
        img = (img / st.spp).reshape(th, tw, 3)
    if aovs:
        rec = build_aovs(scene, **rec, shape=(th, tw))
    return buf, img, rec


def shadow_segments(lights, p: Float[Array, "B 3"], ng: Float[Array, "B 3"], eps: Float[Array, "B 1"]):
    """The shadow rays of hits at p with geometric normals ng turned towards the arriving ray and
    offsets eps (`surface.offset_scale`), one per (hit, light): (wi, dist, so, smax), wi the unit
    direction to the light and dist its distance (`lights.incident`), so = p + ng·eps the origin and
    smax = dist − 2·eps the segment's end (before masking the hits that are not lit). Embree's
    direct-light call (`accel.intersect_points_shadowed`) makes the same segments in float32 with the
    same operations; change both together."""
    wi, dist, _ = _lights.incident(lights, p)  # (B, L, 3), (B, L)
    so = jnp.broadcast_to(p[:, None, :] + ng[:, None, :] * eps[:, None, :], wi.shape)
    return wi, dist, so, dist - 2.0 * eps


def trace(scene) -> GBuffer:
    """Trace the Whitted ray tree of `scene` (non-differentiable; see module docstring)."""
    return _trace_loop(scene, record=True, image=False)[0]


def _glass_r(scene, s, d):
    mats = scene.materials
    r = jnp.zeros(d.shape[0])
    for k, name in enumerate(mats.models):
        if brdfs.get(name).delta:
            rk, *_ = glass_split(mats, s, d, k)
            r = jnp.where(mats.model_id[s.material] == k, rk, r)
    return r


def shade(gbuffer: GBuffer, scene, aovs: bool = False):
    """Sum the traced ray tree into an image (differentiable in materials and lights).

    Returns:
        image (H, W, 3) linear radiance, or with `aovs=True` a pair (image, dict) where the dict has
        the AOVs of `jaxrt.shading.aovs` (depth, normal, albedo, object_id), each from the pixel's
        first sample.
    """
    mats, st, cam = scene.materials, scene.settings, scene.camera
    npix = cam.num_pixels
    B = gbuffer.active.shape[1]

    def level(carry, g):
        tput_prev, delta_prev, r_prev = carry
        act, prim = g["active"], g["prim"]
        par = jnp.maximum(g["parent"], 0)
        factor = jnp.select(
            [g["branch"] == MIRROR, g["branch"] == GLASS_R],
            [delta_prev[par], r_prev[par]], 1.0 - r_prev[par],
        )
        tput = jnp.where(g["parent"] >= 0, tput_prev[par] * factor, 1.0)
        tput = jnp.where(act, tput, 0.0)

        def hit_terms(_):
            s = scene.geometry.surface(prim, g["u"], g["v"])
            found = prim >= 0
            delta, glass = delta_and_glass(mats, s, found)
            r = jnp.where(glass, _glass_r(scene, s, g["direction"]), 0.0)
            return local_radiance(scene, s, g["direction"], g["visible"], found, delta, glass), delta, r

        def empty(_):
            return jnp.zeros((B, 3)), jnp.zeros(B), jnp.zeros(B)

        local, delta, r = jax.lax.cond(jnp.any(act), hit_terms, empty, None)
        contrib = tput[:, None] * local
        img = jax.ops.segment_sum(jnp.where(act[:, None], contrib, 0.0), jnp.where(act, g["pixel"], npix),
                                  num_segments=npix + 1)[:npix]
        return (tput, delta, r), img

    xs = {k: getattr(gbuffer, k) for k in ("active", "prim", "u", "v", "direction", "parent", "branch", "pixel",
                                           "visible")}
    zeros = jnp.zeros(B)
    _, imgs = jax.lax.scan(level, (zeros, zeros, zeros), xs)
    image = (jnp.sum(imgs, axis=0) / st.spp).reshape(cam.height, cam.width, 3)
    if not aovs:
        return image
    first = sample_order_arrays(cam.height, cam.width, st.spp)[1]  # level-0 slot of each pixel's first sample
    return image, build_aovs(scene, *(x[0, first] for x in (gbuffer.prim, gbuffer.u, gbuffer.v, gbuffer.t,
                                                           gbuffer.direction)))


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _whitted(scene, aovs):
    _, img, aov = _trace_loop(scene, record=False, image=True, aovs=aovs)
    return (img, aov) if aovs else img


def _whitted_fwd(scene, aovs):
    # differentiated: exactly the two-pass composition (trace, then shade with its VJP), so a
    # gradient costs what it did before the fusion; the pullback (a pytree of residuals) is the residual
    gb = trace(scene)
    return jax.vjp(lambda sc: shade(gb, sc, aovs=aovs), scene)


def _whitted_bwd(aovs, pullback, cotangent):
    return pullback(cotangent)


_whitted.defvjp(_whitted_fwd, _whitted_bwd)


def whitted(scene, aovs: bool = False, window: camera.Window | None = None):
    """The Whitted image (H, W, 3), or (image, aovs) with `aovs=True`; equal to
    `shade(trace(scene), scene, aovs)`, computed in one pass.

    With a `window` (`camera.Window`, one tile of tiled rendering) only its pixels and samples are
    rendered: the window's share of the image, Σ over its samples / spp, (window height, width, 3).
    Tiles are forward-only (no custom VJP): differentiate whole-image renders.

    The forward pass shades each level of the ray tree as it is traced (`_trace_loop`), so hit
    surfaces are evaluated once and no GBuffer is written. Under reverse-mode differentiation (a
    custom VJP) the forward pass is the two-pass `shade(trace(scene), scene)` and the backward pass
    `shade`'s pullback: the same gradients, at the same cost, as before the fusion. Forward-mode
    (jax.jvp) is not defined through it; use `shade(trace(scene), scene)` for that.
    """
    if window is not None:
        _, img, aov = _trace_loop(scene, record=False, image=True, aovs=aovs, window=window)
        return (img, aov) if aovs else img
    return _whitted(scene, aovs)
