"""Parameter sweeps: one compiled scene re-rendered for each value of one BRDF parameter.

    from jaxrt import sweep
    values = sweep.default_values("phong", "s", 5)          # log grid over the declared range
    images = sweep.sweep("phong", "s", values, width=32, height=32)
    sweep.strip_png("phong_s.png", images, sweep.labels("phong", "s", values))

`sweep` gives the chosen object of a scene (by default the first sphere of the shipped `spheres`
scene, shown alone on the floor) its own material of MODEL, frames the camera on
that object and renders each value with `Scene.with_material` through `jaxrt.frame`. The
prepared scene holds one material per registered model (`substitute`), so its structure does not
depend on MODEL: every model, parameter and value of a sweep at one size shares ONE compiled frame
(about 15-20 s of compilation on a 2-core CPU), and the viewer switches models the same way. Besides every
declared parameter of the model (`Param` in `brdfs/<model>.py`), the material's mirror reflection
coefficient `delta` (δ ∈ [0, 1], not for glass) can be swept; glass's `n_t` is an ordinary parameter.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from jaxtyping import Float

import brdfs
from brdfs.base import Model, Param, log_or_linear_grid
from jaxrt.errors import InputError
from jaxrt import scene as _scene
from jaxrt.scene import DELTA, edit

SWEEP_MATERIAL = "sweep"  # materials "sweep:<model>", one per registered model


def _model(model: str | Model) -> Model:
    return brdfs.get(model) if isinstance(model, str) else model


def param_spec(model: str | Model, name: str) -> Param:
    """The declaration of `name` for `model`: one of its `Param`s, or `DELTA` (δ, non-delta models only).

    Raises InputError naming the model and the parameters allowed.
    """
    m = _model(model)
    if name == "delta" and not m.delta:
        return DELTA
    if name not in m.param_names:
        allowed = m.param_names + (() if m.delta else ("delta",))
        raise InputError(f"{m.name}: unknown parameter {name!r}; allowed: {', '.join(allowed)}")
    return m.param(name)


def default_values(model: str | Model, name: str, steps: int = 7) -> np.ndarray:
    """`steps` values spanning the parameter's typical range (`Param.typical_range`: ordinary
    materials; the whole declared range where none is given) on its natural (log/linear) scale."""
    if steps < 1:
        raise InputError(f"steps: expected a positive integer, got {steps}")
    p = param_spec(model, name)
    lo, hi = p.typical_range
    grid = np.exp(np.linspace(math.log(lo), math.log(hi), steps)) if p.scale == "log" else np.linspace(lo, hi, steps)
    return np.clip(grid, lo, hi)  # exp(log(hi)) may round past hi


def span(model: str | Model, name: str, start: float | None = None, stop: float | None = None,
         steps: int = 7) -> np.ndarray:
    """`steps` values from `start` to `stop` (defaults: the ends of the typical range) on the parameter's
    natural scale (geometric for log-scale parameters); InputError naming --from/--to for ends outside
    the declared bounds."""
    m = _model(model)
    p = param_spec(m, name)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise InputError(f"steps: expected a positive integer, got {steps!r}")
    a = p.typical_range[0] if start is None else float(start)
    b = p.typical_range[1] if stop is None else float(stop)
    for flag, v in (("--from", a), ("--to", b)):
        if not math.isfinite(v) or v < p.lo or v > p.hi:
            raise InputError(f"{flag} {v:g}: {m.name}.{name} must lie in [{p.lo:g}, {p.hi:g}]")
    if steps == 1:
        return np.array([a])
    if p.scale == "log":
        return np.clip(np.geomspace(a, b, steps), p.lo, p.hi)
    return np.linspace(a, b, steps)


def check_values(model: str | Model, name: str, values: Sequence[float]) -> np.ndarray:
    """Validate sweep values against the parameter's declared bounds; (N,) float64."""
    p = param_spec(model, name)
    v = np.asarray(values, np.float64).reshape(-1)
    if v.size == 0:
        raise InputError(f"{_model(model).name}.{name}: no values to sweep")
    bad = v[~np.isfinite(v) | (v < p.lo) | (v > p.hi)]
    if bad.size:
        raise InputError(f"{_model(model).name}.{name}: value {bad[0]:g} is outside the allowed range "
                         f"[{p.lo:g}, {p.hi:g}]")
    return v


def labels(model: str | Model, name: str, values: Sequence[float]) -> list[str]:
    """One caption per frame: 'model\\nparam = value'."""
    m = _model(model)
    return [f"{m.name}\n{name} = {float(x):.3g}" for x in values]


def material_name(model: str | Model) -> str:
    """The name of the material that holds `model`'s parameters in a prepared scene."""
    return f"{SWEEP_MATERIAL}:{_model(model).name}"


def substitute(spec, model: str | Model | None, obj: str | None, base_params: Mapping[str, Any] | None = None,
               isolate: bool = False, inherit: bool = False):
    """A scene spec in which object `obj` can wear any registered model without recompiling.

    One material `material_name(m)` is added per registered model m (their stacked tables make every
    model part of the compiled frame's structure), and the object's own material where it is a
    measured one (`model = "measured"`: its data, no parameters); the object wears `model`'s
    (default: its own material's model). Which material a face wears is a traced value, so `use_model` switches
    models without recompiling.

    Args:
        spec: a validated `jaxrt.scene.SceneSpec`.
        obj: object name (default: the first object that is not a plane).
        base_params: parameter values (and "delta") for `model`'s material; the rest are defaults.
        isolate: keep only `obj` and the ground planes (the sweep's one-sphere view).
        inherit: start every model from the object's current material where parameter names agree
            (rho_d, rho_s, ... and δ), so switching models keeps its colour.
    Returns:
        (new spec, object name, model name).
    """
    # the same default object for every model keeps one compiled structure for all
    target = edit.find_object(spec, obj, skip_planes=True)
    obj = target.name
    own = spec.materials[target.material]
    m = _model(model) if model is not None else brdfs.get(own.model)
    materials = {}
    for name in brdfs.names():
        mm = brdfs.get(name)
        start: dict = {}
        if inherit:
            for k, v in {**own.params, "delta": own.delta}.items():
                if k in mm.param_names or (k == "delta" and not mm.delta):
                    try:
                        param_spec(mm, k).check(v, mm.name)
                        start[k] = v
                    except InputError:
                        pass
        if mm.name == m.name:
            start.update(base_params or {})
        materials[material_name(mm)] = edit.material_spec(material_name(mm), mm, start,
                                                          where=f"{spec.source}: object {obj!r}")
    if brdfs.is_measured(own.model):
        # a measured material has no parameters to start another one from: it stays one of the
        # object's choices as it is (the viewer shows it without parameter sliders)
        materials[material_name(own.model)] = dataclasses.replace(own, name=material_name(own.model))
    if material_name(m) not in materials:
        raise InputError(f"{spec.source}: object {obj!r}: the measured model {m.name} comes with a material's "
                         f"data; give the object a material with model = \"measured\" in the scene instead")
    spec = edit.wear(spec, obj, materials[material_name(m)], extra=materials)
    if isolate:
        objects = tuple(o for o in spec.objects if o.name == obj or o.primitive == "plane")
        keep = {o.material for o in objects} | {v for o in objects for v in o.part_materials.values()}
        kept = {k: v for k, v in spec.materials.items() if k in keep or k.startswith(f"{SWEEP_MATERIAL}:")}
        spec = dataclasses.replace(spec, materials=kept, objects=objects)
    return spec, obj, m.name


def use_model(scene, obj: str, model: str | Model):
    """A copy of a `substitute`d scene in which object `obj` wears `model`'s material (a value change)."""
    return edit.wear_material(scene, obj, material_name(model))


def frame_object(scene, obj: str, margin: float = 1.15):
    """A copy of `scene` whose camera looks at object `obj`'s bounding sphere from the same position,
    with the vertical field of view just wide enough to hold it (times `margin`)."""
    g = scene.geometry
    v = g.object_triangles(g.object_index(obj)).reshape(-1, 3)
    lo, hi = v.min(0), v.max(0)
    centre = 0.5 * (lo + hi)
    radius = float(np.max(np.linalg.norm(v - centre, axis=-1)))  # bounding sphere about the box centre
    dist = float(np.linalg.norm(np.asarray(scene.camera.position) - centre))
    if dist <= radius:
        return scene.with_camera(look_at=centre)
    w, h = scene.camera.width, scene.camera.height
    half = math.asin(min(radius * margin / dist, 1.0))
    tan_v = math.tan(half) * max(1.0, h / w)  # the object must fit the narrower image side
    vfov = min(2.0 * math.degrees(math.atan(tan_v)), 170.0)
    return scene.with_camera(look_at=centre, vfov=vfov)


def prepare(
    model: str | Model | None = None,
    *,
    scene: str | os.PathLike = "spheres",
    object: str | None = None,
    width: int = 96,
    height: int = 96,
    base_params: Mapping[str, Any] | None = None,
    max_depth: int | None = None,
    frame: bool = True,
    isolate: bool = True,
    inherit: bool = False,
):
    """Build a scene in which `object` wears `model` (switchable by `use_model`), at width x height.

    See `substitute` for object/base_params/isolate/inherit; `frame` points the camera at the object
    (`frame_object`). Every call with the same scene, object, size and flags builds the same
    structure, so all models and parameter values share one compiled `jaxrt.frame`.
    Returns (Scene, object name, model name).
    """
    for k, n in (("width", width), ("height", height)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= _scene.MAX_RESOLUTION:
            raise InputError(f"{k}: expected an integer in [1, {_scene.MAX_RESOLUTION}], got {n!r}")
    overrides = {"camera.width": int(width), "camera.height": int(height), "render.max_depth": max_depth}
    spec = _scene.parse(_scene.find_scene(scene), overrides=overrides)
    spec, obj, name = substitute(spec, model, object, base_params, isolate=isolate, inherit=inherit)
    sc = _scene.build(spec)
    return (frame_object(sc, obj) if frame else sc), obj, name


def sweep(
    model: str | Model,
    param: str,
    values: Sequence[float] | None = None,
    *,
    scene: str | os.PathLike = "spheres",
    object: str | None = None,
    width: int = 96,
    height: int = 96,
    base_params: Mapping[str, Any] | None = None,
    max_depth: int | None = None,
    isolate: bool = True,
) -> list[Float[np.ndarray, "H W 3"]]:
    """Render `object` with `model` for each value of `param`; one compiled frame for all values.

    Args:
        model: a `brdfs` model name or Model.
        param: one of the model's parameters (RGB ones are set grey: all channels to the value), or
            "delta" (mirror reflection coefficient δ, non-delta models).
        values: the values to render (default: `default_values(model, param, 7)`); each must lie in the
            parameter's declared range.
        scene: scene file or shipped scene name; object: the object to re-material (default: the
            first object that is not a plane).
        width, height: image size [pixels]; base_params: the other parameters (defaults otherwise);
        max_depth: override the scene's ray-tree depth; isolate: drop the other objects except
            ground planes (default; fewer models in the scene compile much faster).
    Returns:
        a list of (height, width, 3) float32 linear-RGB images, one per value.
    """
    m = _model(model)
    values = default_values(m, param) if values is None else check_values(m, param, values)
    from jaxrt import integrators

    sc, _, _ = prepare(m, scene=scene, object=object, width=width, height=height, base_params=base_params,
                       max_depth=max_depth, isolate=isolate)
    out = []
    for v in values:
        img = np.asarray(integrators.frame(sc.with_material(material_name(m), **{param: float(v)})))
        if not np.all(np.isfinite(img)):
            raise RuntimeError(f"{m.name}.{param} = {v:g}: the render contains NaN/Inf pixels")
        out.append(img)
    return out


def strip_png(
    path: str | os.PathLike,
    images: Sequence[Float[np.ndarray, "H W 3"]],
    labels: Sequence[str],
    title: str = "",
    exposure: float = 0.0,
) -> None:
    """Write the images side by side (sRGB via `jaxrt.image.to_srgb8`), each captioned, to a PNG, atomically."""
    from matplotlib.figure import Figure  # no pyplot: no backend switch, no global figure state

    from jaxrt.fsutil import atomic_path
    from jaxrt.image import to_srgb8

    if len(images) == 0 or len(images) != len(labels):
        raise InputError(f"strip_png: need one label per image, got {len(images)} images and {len(labels)} labels")
    n = len(images)
    h, w = np.asarray(images[0]).shape[:2]
    panel = 1.6
    fig = Figure(figsize=(panel * n, panel * h / w + 0.9 if title else panel * h / w + 0.6))
    axes = fig.subplots(1, n, squeeze=False)[0]
    for ax, img, lab in zip(axes, images, labels):
        ax.imshow(to_srgb8(np.asarray(img), exposure), interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel(lab, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")


def title(model: str | Model, param: str) -> str:
    """A strip title: 'model: param (doc), linear|log steps'."""
    p = param_spec(model, param)
    return f"{_model(model).name}: {param} — {p.doc} ({p.scale} steps)"
