"""Fitting a material of a scene to target renders: trace once, re-shade per solver iteration.

`fit(scene, targets, model, object=...)` replaces the chosen object's material by `model` (with
its defaults), traces every view once into a G-buffer (`jaxrt.integrators.trace`: hits, ray
trees, shadow visibility — nothing that depends on BRDF values), and hands a `shade(params,
gbuffer)` closure to the renderer-independent solver in `fitting.solve`. By default only the pixels
whose camera ray hits that material are compared; `mask` narrows it further.

Several targets fit jointly: pass one scene per target (e.g. the same scene file with different
light positions or cameras through `overrides`), all with the same structure and resolution.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Mapping, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import brdfs
from brdfs.base import Model
from fitting import compact
from fitting.solve import FitResult, fit_images
from jaxrt import integrators
from jaxrt.programs import cached_jit
from jaxrt import scene as _scene
from jaxrt.scene import edit
from jaxrt.errors import InputError

FIT_MATERIAL = "fit"  # name given to the substituted material when the object's own name is shared

#: The largest target value a fit accepts: the solver's sum of squared residuals is float32, and
#: (1e12)² · 3 channels · 16384² pixels (the largest render) stays below float32's 3.4e38.
MAX_TARGET = 1e12
#: How far below 0 a target may dip, as a fraction of its largest |value|: measurement noise
#: around black (a dark-frame-subtracted photograph, a noisy render) is negative here and there;
#: a target mostly or substantially negative cannot be radiance.
NEGATIVE_TOLERANCE = 0.1


def check_targets(targets, where: str = "targets") -> None:
    """Refuse targets no render can be: NaN/Inf, negative beyond noise (below −NEGATIVE_TOLERANCE
    times the largest |value|), or above MAX_TARGET. InputError naming `where` (a file, or "targets")."""
    t = np.asarray(targets)
    if not np.all(np.isfinite(t)):
        raise InputError(f"{where}: contains NaN or Inf pixels")
    if not t.size:
        return
    low, peak = float(t.min()), float(np.abs(t).max())
    if low < 0 and (low < -NEGATIVE_TOLERANCE * peak or float(t.max()) <= 0):
        raise InputError(f"{where}: has negative pixel values down to {low:g} (largest |value| {peak:g}); "
                         f"radiance is >= 0, and only noise down to -{NEGATIVE_TOLERANCE:g} x the largest value "
                         "is accepted")
    if t.size and float(t.max()) > MAX_TARGET:
        raise InputError(f"{where}: pixel values reach {float(t.max()):g}; a target must be at most "
                         f"{MAX_TARGET:g} (scale it down, e.g. by the exposure it was taken with)")


@dataclasses.dataclass(frozen=True)
class Setup:
    """A scene prepared for fitting one material with one model.

    scenes: one built Scene per target (identical structure); gbuffers: their traces;
    material: index of the fitted material; model_index/row: where its parameters live in
    `Scene.materials.params`; mask: (K, H, W) float32 pixels that see the material; fitbuffer:
    the nodes that see the material (`fitting.compact`), which is what the solver re-shades.
    """

    scenes: tuple
    gbuffers: tuple
    material: int
    model_index: int
    row: int
    mask: np.ndarray
    model: Model
    object: str
    fitbuffer: "compact.FitBuffer"


def variant(source, *, lights: Sequence[Mapping[str, Any]] | None = None, **tables) -> dict:
    """A scene file or shipped name as a parsed dict with some tables replaced, for extra views.

    `lights` replaces the [[lights]] array (e.g. a rim light behind the object); keyword tables
    update tables key by key, e.g. `camera={"width": 64, "height": 64}`. The result is accepted
    wherever a scene source is (validated when prepared).
    """
    import copy
    import tomllib

    path = _scene.find_scene(source)
    doc = tomllib.loads(path.read_text())
    doc = copy.deepcopy(doc)
    if lights is not None:
        doc["lights"] = [dict(l) for l in lights]
    for table, values in tables.items():
        doc.setdefault(table, {}).update(values)
    return doc


def _spec(source, overrides=None, confine=None) -> _scene.SceneSpec:
    if isinstance(source, _scene.SceneSpec):
        return source
    if not isinstance(source, Mapping):
        source = _scene.find_scene(source)
    return _scene.parse(source, overrides=overrides, confine=confine)


def _substitute(spec: _scene.SceneSpec, model: Model, obj: str | None) -> tuple[_scene.SceneSpec, str, str]:
    """Give the object `obj` (default: the first object) its own material of `model` (defaults; δ
    kept from its own material unless that was glass)."""
    target = edit.find_object(spec, obj)
    if model.delta:
        raise InputError(f"{model.name} is a delta BSDF; fitting supports the models with an eval: "
                         f"{', '.join(n for n in brdfs.names() if not brdfs.get(n).delta)}")
    old = spec.materials[target.material]
    delta = 0.0 if brdfs.get(old.model).delta else old.delta
    mat = edit.material_spec(FIT_MATERIAL, model, {"delta": delta}, where=f"{spec.source}: object {target.name!r}")
    return edit.wear(spec, target.name, mat), FIT_MATERIAL, target.name


def prepare(
    scenes: Any | Sequence[Any],
    model: str | Model,
    *,
    object: str | None = None,
    overrides: Sequence[Mapping[str, Any] | None] | None = None,
    confine: bool | None = None,
    progress: bool = False,
    traced: Sequence[Any] | None = None,
) -> Setup:
    """Build and trace the scene(s) for fitting `model` on `object`'s material.

    Args:
        scenes: a scene file path / shipped name / parsed SceneSpec, or a sequence of them (one per
            target).
        model: the model to fit (name or `brdfs` Model).
        object: name of the object whose material is fitted (default: the scene's first object).
        overrides: per-scene override dicts ({"camera.position": [...]}), same length as scenes.
        confine: refuse scene paths outside each scene's folder and the data folder (default:
            JAXRT_CONFINE; `jaxrt.scene.parse`).
        progress: a progress bar on stderr over the views (build, trace) and the fit buffer.
        traced: the traces (`jaxrt.integrators.trace`) of the scenes *as given*, one per scene, to
            reuse instead of tracing them again, e.g. when several models are fitted to the same views
            (a trace depends on geometry, δ and which materials are glass, not on the opaque models).
            Ignored for an object that was glass (its substituted scene is traced).
    """
    model = brdfs.get(model) if isinstance(model, str) else model
    if isinstance(scenes, (str, os.PathLike, Mapping, _scene.SceneSpec)):
        scenes = [scenes]
    overrides = list(overrides) if overrides is not None else [None] * len(scenes)
    if len(overrides) != len(scenes):
        raise InputError(f"got {len(scenes)} scenes but {len(overrides)} override sets")
    traced = list(traced) if traced is not None else [None] * len(scenes)
    if len(traced) != len(scenes):
        raise InputError(f"got {len(scenes)} scenes but {len(traced)} traces")
    built, gbs, masks = [], [], []
    obj_name = None
    from tqdm import tqdm

    # one step per view (build and trace) and one for the fit buffer
    bar = tqdm(total=len(scenes) + 1, desc="preparing views", unit="step", leave=False, disable=not progress,
               delay=0.5)
    from jaxrt import cache as _cache

    try:
        # each view's geometry is built twice (as given, and wearing the fitted material): one tree for both
        with _cache.sharing_trees():
            for src, ov, gb in zip(scenes, overrides, traced):
                original = _spec(src, ov, confine)
                spec, mat_name, obj_name = _substitute(original, model, object)
                # The ray tree depends on geometry, δ and which materials are glass, not on the opaque
                # model: trace the scene as given (one compilation per scene, whatever model is fitted)
                # unless the object was glass, whose branches the substituted model no longer has.
                was_glass = brdfs.get(original.materials[edit.find_object(original, obj_name).material].model).delta
                if was_glass or gb is None:
                    # the scene to trace is built first, its trace program compiling from its shapes
                    # while the BVH is built on the host (`_compile_trace_ahead`)
                    ahead: list = []
                    to_trace = _scene.build(spec if was_glass else original,
                                            on_shapes=lambda shapes: ahead.append(_compile_trace_ahead(shapes)))
                    sc = to_trace if was_glass else _scene.build(spec)
                    m = sc.materials.index(mat_name)
                    shading = edit.set_material_row(sc, int(sc.materials.model_id[m]), int(sc.materials.row[m]),
                                                    model.params())
                    # not joined first: `_trace` compiles the shade program while this one finishes;
                    # but lowered first, so that the program is the ahead thread's to compile (a
                    # loaded machine can keep that thread from reaching it before this one does)
                    started = [t for t in ahead if t is not None]
                    for t in started:
                        t.lowered.wait()
                    gb = _trace(to_trace, shading, compiling_ahead=bool(started))
                    for t in started:
                        t.join()
                else:
                    sc = _scene.build(spec)
                built.append(sc)
                gbs.append(gb)
                bar.update(1)
        shapes = {(s.camera.height, s.camera.width, s.settings.spp) for s in built}
        if len(shapes) != 1:
            raise InputError(f"all fitting scenes need the same resolution and spp, got {sorted(shapes)}")
        sc = built[0]
        mi = sc.materials.index(mat_name)
        for s, gb in zip(built, gbs):
            npix = s.camera.num_pixels
            first = integrators.sample_order(s.camera.height, s.camera.width, s.settings.spp)[1]
            prim = np.asarray(gb.prim)[0, first]
            hit_mat = np.where(prim >= 0, np.asarray(compact.face_material(s.geometry, prim)), -1)
            masks.append(np.asarray(hit_mat == mi, np.float32).reshape(s.camera.height, s.camera.width))
        mask = np.stack(masks)
        if not mask.any():
            raise InputError(f"object {obj_name!r} is not visible in any view; nothing to fit")
        model_index, row = int(sc.materials.model_id[mi]), int(sc.materials.row[mi])
        fb = compact.build(gbs, built, model_index, row, mi, model.params())
        bar.update(1)
    finally:
        bar.close()
    return Setup(
        scenes=tuple(built),
        gbuffers=tuple(gbs),
        material=mi,
        model_index=model_index,
        row=row,
        mask=mask,
        model=model,
        object=obj_name,
        fitbuffer=fb,
    )


def _compile_trace_ahead(shapes):
    """Start compiling, in a thread, the trace program of the scene `shapes` (`jaxrt.scene.build`'s
    on_shapes: the tree's arrays are `jax.ShapeDtypeStruct`s), as `jaxrt render` compiles its frame
    (`jaxrt.render_tiles.compile_ahead`): XLA compiles with the GIL released while the host builds the
    BVH. The stored program (`jaxrt.programs`) is kept per shapes, so `_trace` finds it compiled. Only
    with the cache on (with it off, `jax.jit` would compile the call again); errors are left to the
    trace itself to raise. The thread's `lowered` event is set once the program is lowered: the
    caller's own `lower` then finds it claimed and waits for this compilation instead of starting one."""
    import threading

    from jaxrt import _config

    if not _config.config().cache:
        return None

    lowered = threading.Event()  # set once the program is lowered (claimed) or failed to be

    def work():
        try:
            program = integrators.trace.lower(shapes)
        except Exception:  # noqa: BLE001 -- see the docstring
            return
        finally:
            lowered.set()
        try:
            program.compile()
        except Exception:  # noqa: BLE001 -- see the docstring
            pass

    t = threading.Thread(target=work, name="fitting-trace-ahead", daemon=True)
    t.lowered = lowered
    t.start()
    return t


def _trace(scene, shading, compiling_ahead: bool = False):
    """`integrators.trace(scene)`, with the program `compact.build` shades the trace with (for the
    constant image, on the scene `shading`) compiled while the trace program compiles: XLA compiles
    with the GIL released, so on a first run the two compilations overlap. Both are stored programs
    (`jaxrt.programs`): a later process reads them without tracing, and the shade program compiles
    from the trace's output shapes (`out_info`). With the cache off the shade program compiles at
    its call, as before. The trace itself is the same call either way, so its results are the same bits.
    compiling_ahead: `_compile_trace_ahead`'s thread is compiling the trace program; none is started
    here (the call waits for that one's)."""
    import threading

    from jaxrt import _config

    # the call below runs this program, compiled once (where `_compile_trace_ahead` is compiling it,
    # `lower` waits for its load, not its compilation, and the thread below for the compilation)
    lowered = integrators.trace.lower(scene)
    compiling = None
    if not compiling_ahead:
        compiling = threading.Thread(target=lowered.compile, name="fitting-trace-compile", daemon=True)
        compiling.start()
    try:
        if _config.config().cache:
            integrators.shade.lower(lowered.out_info, shading).compile()
    finally:
        if compiling is not None:
            compiling.join()
    return integrators.trace(scene)


@functools.lru_cache(maxsize=None)
def shader(model_index: int, row: int):
    """The `shade(params, (gbuffers, scenes)) -> (K, H, W, 3)` function for one material slot.

    Cached so the same Python object is handed to the solver each time (its compiled code is reused).
    """

    def shade(params, data):
        gbuffers, scenes = data
        return jnp.stack([
            integrators.shade(gb, edit.set_material_row(sc, model_index, row, params)) for gb, sc in zip(gbuffers, scenes)
        ])

    shade.program_key = f"fitting.setup.shader({model_index}, {row})"  # stable across processes
    return shade


def render_with(setup: Setup, params: Mapping[str, Array]) -> Float[Array, "K H W 3"]:
    """Images of every view with the fitted material set to `params` (validated pytree)."""
    return _jitted_shader(setup.model_index, setup.row)(params, (setup.gbuffers, setup.scenes))


@functools.lru_cache(maxsize=None)
def _jitted_shader(model_index: int, row: int):
    # kept across processes (`jaxrt.programs`): a warm `jaxrt fit` renders its targets and fitted
    # images without tracing the shading of every view
    shade = shader(model_index, row)
    return cached_jit(shade, name=f"fitting.setup.render_with[{shade.program_key}]")


def fit(
    scenes: Any | Sequence[Any],
    targets: Float[Array, "K H W 3"] | Sequence[Float[Array, "H W 3"]],
    model: str | Model,
    *,
    object: str | None = None,
    overrides: Sequence[Mapping[str, Any] | None] | None = None,
    mask: Float[Array, "K H W"] | None = None,
    setup: Setup | None = None,
    devices: Any = None,
    split: str = "starts",
    **solver_options,
) -> tuple[FitResult, Setup]:
    """Recover `model`'s parameters for `object`'s material from target images.

    Args:
        scenes, model, object, overrides: as for `prepare` (ignored when `setup` is given).
        targets: (K, H, W, 3) linear RGB, one per scene, at the scene's resolution: finite, not
            negative beyond noise and at most MAX_TARGET (`check_targets`).
        mask: optional (K, H, W) weights multiplied into the default mask (the material's pixels).
        setup: a `prepare` result to reuse (skips building and tracing).
        devices: None (default) or 1: the default device; an int N, "all" or a list of
            `jax.devices()`: the fit is split over those devices as `split` says.
        split: "starts" (default): the starts run at once, split over the devices
            (`fitting.solve.fit_images`); "nodes": the starts run one after another and each
            residual evaluation is split: every device shades its share of the fit buffer's nodes and
            a `psum` adds the partial images (`fitting.compact.split_shader`), so the solver's
            Jacobian products are summed over the devices by that collective and its iterates equal
            the one-device fit's up to the order of the sum.
        **solver_options: fix, init, rgb, solver, starts, max_steps, rtol, atol, progress
            (see `fitting.solve.fit_images`).

    Returns:
        (FitResult, Setup); `render_with(setup, params)` re-renders any parameter set.
    """
    setup = setup or prepare(scenes, model, object=object, overrides=overrides)
    targets = np.asarray(targets, np.float32)
    if targets.ndim == 3:
        targets = targets[None]
    expect = setup.mask.shape + (3,)
    if targets.shape != expect:
        raise InputError(f"targets have shape {targets.shape}; the scene renders {expect} (K, H, W, RGB)")
    check_targets(targets)
    m = setup.mask if mask is None else setup.mask * np.asarray(mask, np.float32)
    if split not in ("starts", "nodes"):
        raise InputError(f"split={split!r}: must be 'starts' or 'nodes'")
    from fitting.solve import fit_devices

    devs = fit_devices(devices)
    if split == "nodes" and devs:
        result = fit_images(compact.split_shader(setup.model.name, devs), compact.split(setup.fitbuffer, devs),
                            targets, setup.model, mask=m, **solver_options)
    else:
        result = fit_images(compact.shader(setup.model.name), setup.fitbuffer, targets, setup.model, mask=m,
                            devices=devs or None, **solver_options)
    return result, setup


def cross_model_matrix(
    setups: Mapping[str, Setup], targets_params: Mapping[str, Mapping[str, Any]], *, devices: Any = None,
    **solver_options
) -> np.ndarray:
    """Fit every model to targets rendered by every model (Ngan, Durand & Matusik 2005 style).

    Args:
        setups: model name -> `prepare` result, all of the same scene and object.
        targets_params: model name -> the parameters its target is rendered with (same keys/order as
            `setups`).
        devices: None (default) or 1: one fit after another on the default device (`fit`); an int
            N, "all" or a list of `jax.devices()`: whole fits split over those devices: for each
            fitted model, its fits to every target run as one batch (`fitting.solve.solve_batch`),
            the targets split over the devices.
        **solver_options: passed to `fit` (starts, max_steps, rgb, solver, progress).

    Returns:
        (n, n) RMSE of the best fit relative to the target's RMS over the object's pixels; row i is the
        target model, column j the fitted model.
    """
    from fitting.solve import fit_devices, solve_batch

    names = list(setups)
    out = np.zeros((len(names), len(names)))
    targets, scales = [], []
    for src in names:
        s = setups[src]
        target = np.asarray(render_with(s, s.model.params(**targets_params[src])))
        targets.append(target)
        scales.append(float(np.sqrt(np.mean(target[s.mask > 0] ** 2))) or 1.0)
    if not fit_devices(devices):
        for i, target in enumerate(targets):
            for j, dst in enumerate(names):
                r, _ = fit(None, target, dst, setup=setups[dst], **solver_options)
                out[i, j] = r.rmse / scales[i]
        return out
    for t in targets:
        check_targets(t)
    for j, dst in enumerate(names):
        s = setups[dst]
        sols = solve_batch(compact.shader(s.model.name), s.fitbuffer, np.stack(targets), s.model, mask=s.mask,
                           devices=devices, **solver_options)
        # the mask is 0/1, so the loss ½Σr² is over the object's pixels and channels: the fit's RMSE
        count = 3 * int(np.count_nonzero(s.mask > 0))
        for i, sol in enumerate(sols):
            out[i, j] = float(np.sqrt(2.0 * sol.loss / count)) / scales[i]
    return out
