"""The image-space study: analytic models fitted to renders of measured materials (`jaxrt study --space image`).

The BRDF-space study (`fitting.study`) compares each model with the measurement over a fixed set of
direction pairs. Here the comparison is the one a renderer makes: a scene is rendered with the
measured material (the targets), and every "diffuse + one lobe" model is fitted to those renders
with the image-space fit of `jaxrt fit` (`fitting.setup`, `fitting.solve.fit_images`:
Levenberg–Marquardt from deterministic starts, standard errors, parameters that end at a bound).

The scene (`scene_doc`). The Stanford bunny (`scene="bunny"`, the camera of scenes/bunny.toml) on a
grey Lambertian floor, or, where the bunny mesh is not installed or with `scene="sphere"`, a unit
sphere on that floor; `scene="auto"` (the default) takes the bunny when `jaxrt.geometry.data` finds
it and the sphere otherwise, and the study records which (`settings["scene"]`). Two views, one
point light each (`LIGHTS`): a key light above and to the right of the camera (the bunny scene's
main light) and a rim light behind the object, which separates a lobe's strength from its Fresnel
term (as in BENCHMARKS.md's fitting benchmark); both views are fitted jointly. The Whitted
integrator at one sample per pixel, so targets and fits share one deterministic ray tree; the
compared pixels are those whose camera ray hits the object (the floor and shadows are constant).

Materials. By default a documented subset (`DEFAULT_MATERIALS`: a plastic, a metallic paint, a metal
and a fabric of the MERL database, the neural stand-ins of Sztrajman et al. 2021); any measured
material names or files (`brdfs.measured.load`: "merl/alum-bronze", NAME.h5, NAME.binary) may be
given. The error (`METRIC`) is the RMSE of the fitted renders against the targets over the compared
pixels of both views, in the renders' linear radiance (the study's units here; `errors` adds the
RMSE relative to the targets' RMS and the mean CIEDE2000 ΔE).

Work done once. The scene is traced once per view (`jaxrt.integrators.trace`, one compilation for
every model and material: a trace holds hits and visibility, nothing a BRDF changes); each model's
fit buffer (`fitting.compact`) is built once from those traces; each material's targets are the
renderer's `jaxrt.integrators.shade` of the traces with that material's data in the measured
material's row (one compiled program for every material of a kind, the data being traced values);
each model's solver is compiled once and fits every material: all materials of a kind go through one
solve vmapped over materials and starts (`fitting.solve.solve_batch`, as the BRDF-space study does),
in calls of `batch` materials (one on a CPU, where the lanes of a vmapped solve run one after
another anyway, all on a GPU) split over `devices`. The fitted renders give what `jaxrt fit` reports
(RMSE, its ratio to the targets' RMS, mean ΔE2000, the warnings).

Isotropy. As in the BRDF-space study, the anisotropic models fit one roughness (α_y = α_x,
n_v = n_u: `fitting.brdf_space.ISOTROPIC_TIES`), reported equal to its source with its standard error.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

import brdfs
from brdfs.errors import InputError
from fitting import brdf_space as bs
from fitting import compact
from fitting import setup as fit_setup
from fitting.record import FitRecord
from fitting.solve import fit_images
from fitting.study import Study

__all__ = [
    "DEFAULT_MATERIALS", "DEFAULT_SIZE", "LIGHTS", "METRIC", "METRIC_DOC", "OBJECT", "SCENES", "UNIT", "ImageFit",
    "choose_scene", "run_image", "scene_doc",
]

#: the default subset: a plastic, a metallic paint, a metal and a fabric
DEFAULT_MATERIALS = ("merl/blue-acrylic", "merl/gold-metallic-paint", "merl/alum-bronze", "merl/red-fabric")
DEFAULT_SIZE = (64, 64)
SCENES = ("auto", "bunny", "sphere")
OBJECT = "target"  # the fitted object's name in `scene_doc`
METRIC = "rmse"
UNIT = "linear radiance"
METRIC_DOC = ("RMSE of the fitted renders against the targets over the object's pixels of both views "
              "(two point lights, Whitted, 1 spp)")
#: one point light per view: a key light (the bunny scene's) and a rim light behind the object
LIGHTS = (
    {"position": [2.5, 4.0, 3.0], "intensity": [25.0, 25.0, 25.0]},
    {"position": [0.0, 2.5, -4.0], "intensity": [40.0, 40.0, 40.0]},
)
_FLOOR = {"model": "lambert", "rho_d": [0.5, 0.5, 0.5]}


@dataclasses.dataclass
class ImageFit(FitRecord):
    """One image-space fit of `model` to the renders of `material`: `error` is the RMSE over the
    compared pixels [linear radiance], `errors` also holds relative_rmse (to the targets' RMS) and
    delta_e_mean (CIEDE2000), `fit_error` the same RMSE (what the solver minimised)."""

    pixels: int  # compared pixels over both views
    warnings: list[str]


def choose_scene(scene: str) -> str:
    """"auto" -> "bunny" when the bunny mesh is found (`jaxrt.geometry.data`), else "sphere"."""
    if scene not in SCENES:
        raise InputError(f"--scene {scene!r}: allowed: {', '.join(SCENES)}")
    if scene != "auto":
        return scene
    from jaxrt.geometry import data

    try:
        data.find("bunny")
    except InputError:
        return "sphere"
    return "bunny"


def scene_doc(scene: str, data: str, light: Mapping, size: tuple[int, int] = DEFAULT_SIZE) -> dict:
    """The study's scene as a parsed-TOML dict: `scene` "bunny" or "sphere" (see the module docstring)
    wearing the measured material `data` (a name or an absolute file path), lit by one point light."""
    w, h = size
    if scene == "bunny":
        camera = {"position": [0.0, 1.6, 5.6], "look_at": [-0.1, 0.85, 0.0], "vfov": 30.0}
        obj = {"name": OBJECT, "mesh": "bunny", "scale": 10.0, "translate": [0.15, -0.33, 0.0]}
        floor_y = 0.0
    elif scene == "sphere":
        camera = {"position": [0.0, 0.4, 4.0], "look_at": [0.0, 0.0, 0.0], "vfov": 32.0}
        obj = {"name": OBJECT, "primitive": "sphere", "radius": 1.0}
        floor_y = -1.0
    else:
        raise InputError(f"scene {scene!r}: allowed: bunny, sphere")
    return {
        "description": f"image-space study: {scene} in {data}",
        "camera": {**camera, "width": int(w), "height": int(h)},
        "render": {"integrator": "whitted", "max_depth": 1, "spp": 1, "background": [0.0, 0.0, 0.0]},
        "lights": [dict(light)],
        "materials": {"measured": {"model": "measured", "data": data}, "floor": dict(_FLOOR)},
        "objects": [{**obj, "material": "measured"},
                    {"primitive": "plane", "size": [30.0, 30.0], "translate": [0.0, floor_y, 0.0],
                     "material": "floor"}],
    }


@functools.lru_cache(maxsize=None)
def _shader(model_name: str, tie: tuple[tuple[str, str], ...]):
    """The fit buffer's shade function with the isotropic ties applied; one object per (model, ties)
    so that each model's solver compiles once."""
    base = compact.shader(model_name)

    def shade(params, fb):
        return base({**params, **{t: params[s] for t, s in tie}}, fb)

    shade.program_key = f"fitting.study_image._shader({model_name!r}, {tie!r})"  # stable across processes
    return shade


@functools.lru_cache(maxsize=None)
def _render(shade):
    return jax.jit(shade)


def _ref(name: str) -> str:
    """A material name stays a name; a file becomes absolute (the scene dict has no folder of its own)."""
    from pathlib import Path

    return str(Path(name).resolve()) if Path(name).suffix else name


# the solver's tolerances (fitting.solve.fit_images's defaults), shared by the batched and unbatched fits
RTOL, ATOL = 1e-7, 1e-9


def _as_params(values: Mapping) -> dict:
    return {k: jnp.asarray(v, jnp.float32) for k, v in values.items()}


def _batching(n: int, batch: int | None, devices) -> tuple[int, int]:
    """(devices used, materials per compiled call) for n materials: `batch` per device, default
    `fitting.study.default_batch` of each device's share (as the BRDF-space study)."""
    from fitting import study
    from fitting.solve import fit_devices

    n_dev = max(1, len(fit_devices(devices)))
    if batch is None:
        batch = study.default_batch(-(-n // n_dev))
    if batch < 1:
        raise InputError(f"--batch {batch}: must be at least 1")
    return n_dev, max(1, min(batch * n_dev, n))


@dataclasses.dataclass
class _BatchedFit:
    """What `run_image` reads from a fit, for fits made by `solve_batch` (`FitResult`'s fields)."""

    params: dict
    stderr: dict
    fixed: list
    rmse: float
    relative_rmse: float
    delta_e_mean: float
    at_bound: dict
    converged: bool
    iterations: int
    total_iterations: int
    starts: int
    starts_at_best: int
    condition_number: float
    ill_conditioned: bool
    correlated: list
    warnings: list
    first_view: np.ndarray  # (H, W, 3) the fitted render of the first view


def _fit_batched(shade, setup, targets: list, model, fix, starts: int, max_steps: int, batch: int,
                 devices) -> list[_BatchedFit]:
    """Each material's targets (K, H, W, 3) fitted by `solve_batch` (one compiled solve for them all,
    `batch` materials a call), then rendered at the fit to report what `fit_images` reports (RMSE over
    the compared pixels, its ratio to the targets' RMS, the mean CIEDE2000 ΔE, the warnings)."""
    from fitting import metrics
    from fitting.solve import fit_devices, fit_warnings, solve_batch

    sols = solve_batch(shade, setup.fitbuffer, np.stack(targets), model, mask=setup.mask, fix=fix, rgb=True,
                       solver="lm", starts=starts, max_steps=max_steps, rtol=RTOL, atol=ATOL, batch=batch,
                       progress=False, devices=devices if fit_devices(devices) else None)
    m = np.asarray(setup.mask) > 0
    out = []
    for sol, tgt in zip(sols, targets):
        fitted = np.asarray(_render(shade)(_as_params(sol.params), setup.fitbuffer))
        tgt = np.asarray(tgt)
        rmse = metrics.rmse(fitted, tgt, m)
        rms = float(np.sqrt(np.mean(np.asarray(tgt, np.float64)[m] ** 2))) if np.any(m) else 0.0
        relative = rmse / rms if rms > 0 else (0.0 if rmse == 0 else float("inf"))
        de = metrics.delta_e_2000(fitted, tgt, m)
        out.append(_BatchedFit(
            params=sol.params, stderr=sol.stderr, fixed=list(sol.fixed), rmse=rmse, relative_rmse=relative,
            delta_e_mean=float(de.mean()) if de.size else 0.0, at_bound=sol.at_bound, converged=sol.converged,
            iterations=sol.iterations, total_iterations=sol.total_iterations, starts=sol.starts,
            starts_at_best=sol.starts_at_best, condition_number=sol.condition_number,
            ill_conditioned=sol.ill_conditioned, correlated=sol.correlated,
            warnings=fit_warnings(sol.converged, sol.iterations, max_steps, sol.starts, sol.meaningless, relative),
            first_view=fitted[0]))
    return out


def run_image(materials: Sequence[str] = DEFAULT_MATERIALS, models: Sequence[str] | None = None, *,
              scene: str = "auto", size: tuple[int, int] = DEFAULT_SIZE, starts: int = 6, max_steps: int = 100,
              progress: bool = True, batched: bool = True, batch: int | None = None, devices=None) -> Study:
    """Fit every model to the renders of every material (see the module docstring); a `Study` with
    `space == "image"` whose `images` hold the first view of each target and fit (for the picture).
    A tqdm bar counts (material, model) fits.

    `batched` (default): each model's fits of all materials of a kind run through one compiled solve
    vmapped over materials and starts (`fitting.solve.solve_batch`, as the BRDF-space study), `batch`
    materials per call (default `fitting.study.default_batch`: one on a CPU, all on a GPU) and, with
    `devices` (an int N, "all" or a list of `jax.devices()`), each call's materials split over those
    devices. `batched=False`: one `fitting.solve.fit_images` per (material, model), its starts one after
    another. Both run the same single-start solve from the same starts; the fits agree to the
    rounding of differently compiled programs (tests/fitting/test_study_image.py states the tolerance)."""
    from tqdm.auto import tqdm

    from brdfs import measured
    from jaxrt import integrators
    from jaxrt import scene as _scene
    from jaxrt.scene import edit
    from fitting import study

    models = list(models) if models is not None else list(study.study_models())
    materials = list(materials)
    w, h = (int(v) for v in size)
    if not (8 <= w <= 1024 and 8 <= h <= 1024):
        raise InputError(f"--size {w},{h}: width and height must be between 8 and 1024")
    which = choose_scene(scene)
    n_dev, used_batch = _batching(len(materials), batch, devices) if batched else (1, 1)
    batch = used_batch
    t0 = time.perf_counter()
    bar = tqdm(total=len(materials) * len(models), desc="image study", unit="fit", disable=not progress)
    bar.set_postfix_str(f"tracing the {which}")
    loaded = {a: measured.read(_ref(a)) for a in materials}  # numpy only: bad data fails before any JAX work
    kinds: dict[str, list[str]] = {}
    for a, (m, _) in loaded.items():
        kinds.setdefault(m.name, []).append(a)
    fits: dict = {}
    images: dict = {}
    per_model: dict[str, float] = {}
    pixels = None
    for kind, names in kinds.items():
        # one scene per kind of measured data (a neural BRDF or a MERL table), parsed with its first material
        specs = [_scene.parse(scene_doc(which, _ref(names[0]), light, (w, h))) for light in LIGHTS]
        built = [_scene.build(s) for s in specs]
        traces = [integrators.trace(sc) for sc in built]
        mi = built[0].materials.index("measured")
        slot = int(built[0].materials.model_id[mi]), int(built[0].materials.row[mi])
        targets = {}
        for a in names:
            p = measured.complete(brdfs.get(kind), loaded[a][1])
            targets[a] = np.stack([np.asarray(integrators.shade(gb, edit.set_material_row(sc, *slot, p)))
                                   for gb, sc in zip(traces, built)])
            fit_setup.check_targets(targets[a], f"renders of {a}")
            images[(a, "target")] = targets[a][0]
        for name in models:
            t_model = time.perf_counter()
            model = bs.fit_model(name)
            bar.set_postfix_str(f"{name}: preparing")
            setup = fit_setup.prepare(specs, model, object=OBJECT, traced=traces)
            pixels = int(setup.mask.sum())
            for a in names:
                images[(a, "mask")] = setup.mask[0]
            tie = bs.ties(model)
            fix = {t: model.param(t).default for t, _ in tie}  # not fitted: the shader sets it to its source
            shade = _shader(model.name, tie)
            if batched:
                bar.set_postfix_str(f"{name}: {len(names)} materials")
                results = _fit_batched(shade, setup, [targets[a] for a in names], model, fix, starts, max_steps,
                                       batch, devices)
            for i, a in enumerate(names):
                bar.set_postfix_str(f"{name}: {a}")
                if batched:
                    r = results[i]
                else:
                    r = fit_images(shade, setup.fitbuffer, targets[a], model, mask=setup.mask, fix=fix, rgb=True,
                                   starts=starts, max_steps=max_steps, rtol=RTOL, atol=ATOL, progress=False)
                for t, s in tie:
                    r.params[t] = r.params[s]
                    r.stderr[t] = r.stderr[s]
                    r.fixed.remove(t)
                    if s in r.at_bound:
                        r.at_bound[t] = r.at_bound[s]
                fits[(a, name)] = ImageFit.from_solution(
                    r, material=a, model=name, metric=METRIC, unit=UNIT, error=r.rmse,
                    errors={"rmse": r.rmse, "relative_rmse": r.relative_rmse, "delta_e_mean": r.delta_e_mean},
                    fit_error=r.rmse, tied=dict(tie), pixels=pixels, warnings=r.warnings)
                images[(a, name)] = r.first_view if batched else np.asarray(
                    _render(shade)(_as_params(r.params), setup.fitbuffer)[0])
                bar.update(1)
            per_model[name] = per_model.get(name, 0.0) + time.perf_counter() - t_model
    bar.close()
    settings = {
        "space": "image", "metric": METRIC, "unit": UNIT, "metric_definition": METRIC_DOC, "scene": which,
        "scene_requested": scene, "size": [w, h], "lights": [dict(l) for l in LIGHTS], "pixels": pixels,
        "starts": starts, "max_steps": max_steps, "solver": "Levenberg-Marquardt (optimistix), lm",
        "batched": batched, "batch": used_batch if batched else 1, "devices": n_dev if batched else 1,
        "backend": jax.default_backend(), "device": jax.devices()[0].device_kind, "wall_s_per_model": per_model,
        "models": {m: [dataclasses.asdict(p) for p in brdfs.get(m).spec] for m in models},
    }
    return Study(materials, models, METRIC, fits, settings, time.perf_counter() - t0, space="image", images=images)
