"""The BRDF-space study of Ngan, Durand & Matusik 2005 over the measured materials (`jaxrt study`).

Every analytic "diffuse + one specular lobe" model (`study_models`) is fitted to every measured
material of a collection in BRDF space (`fitting.brdf_space`: the MERL half/difference sampling with
its solid-angle weights and the 80° cutoff, Levenberg–Marquardt from deterministic starts, batched
over materials), and `write` produces

    study.csv, study.json   one row per (material, model): fitted parameters, standard errors, the error
                            of every metric at the fit, convergence, the parameters that end at a bound
    summary.md              per model: median and quartile error, how often it is the best model
    errors.png              Ngan et al.'s figure: materials sorted by error, one curve per model, log scale
    spheres.png             for a few materials: the measured sphere beside each model's fit

The reported error (`error`, in the study's units, `brdf_space.UNITS`) is evaluated on a finer grid
than the fit's (`brdf_space.EVAL_RESOLUTION` against `brdf_space.FIT_RESOLUTION`): on the fit's
grid the sharpest highlights are sampled by a few cells only, so E there reads low (by 24 % for
blue-acrylic, one of the sharpest MERL materials), while the fitted parameters change little with the
fit grid (measured for eight MERL materials with Cook–Torrance: E on the fine grid differs by at most
5 % between fits on the (24, 16, 16) and (48, 32, 32) grids, by less than 2 % for six of them). The fit
grid's E is kept as `fit_error`.

Models. Ngan et al. fitted Ward, Ward–Dür, Blinn–Phong, Cook–Torrance, Lafortune, Ashikhmin–Shirley and
He et al., each as a Lambertian term plus one lobe. Here: every registered model with an `eval` and a
`rho_d` parameter except Lambert (no lobe) and Disney (three lobes: not a "one lobe" form); models
added to `brdfs` later (e.g. other Ward normalisations) join automatically. Their parameter ranges
are read from each model's `Param`s; fits that end at a bound say so (`at_bound`).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import brdfs
from brdfs.errors import InputError
from fitting import brdf_space as bs

__all__ = [
    "COLLECTIONS", "EVAL_RESOLUTION", "EXCLUDED", "FIT_RESOLUTION", "GRID_ROWS", "IMAGE_OUTPUTS", "OUTPUTS", "SPACES",
    "Study",
    "check_output_dir", "csv_text", "default_batch", "grid_materials", "json_obj", "parse_materials",
    "parse_models", "parse_resolution", "rows", "run", "study_models", "summary", "summary_markdown", "write",
]

EXCLUDED = {"lambert": "no specular lobe", "disney": "three lobes, not a diffuse + one lobe form"}
COLLECTIONS = ("merl", "rgl", "nielsen")
EVAL_RESOLUTION = bs.EVAL_RESOLUTION
FIT_RESOLUTION = bs.FIT_RESOLUTION
OUTPUTS = ("study.csv", "study.json", "summary.md", "errors.png", "spheres.png")
#: the image-space study's outputs (`fitting.study_image`): renders.png in place of spheres.png
IMAGE_OUTPUTS = ("study.csv", "study.json", "summary.md", "errors.png", "renders.png")
SPACES = ("brdf", "image")
GRID_ROWS = 6


def study_models() -> tuple[str, ...]:
    """The registered models in the study (see the module docstring), in registry order."""
    out = []
    for name in brdfs.names():
        m = brdfs.get(name)
        if name in EXCLUDED or m.delta or m.eval is None or "rho_d" not in m.param_names:
            continue
        out.append(name)
    return tuple(out)


def parse_models(text: str | None) -> list[str]:
    """Comma-separated model names (default: all of `study_models`), each checked."""
    allowed = study_models()
    if not text:
        return list(allowed)
    names = [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        if n not in allowed:
            why = f" ({EXCLUDED[n]})" if n in EXCLUDED else ""
            raise InputError(f"--models: {n!r} is not a study model{why}; allowed: {', '.join(allowed)}")
    if len(set(names)) != len(names):
        raise InputError(f"--models: {text!r} names a model twice")
    return names


def parse_materials(text: str) -> list[str]:
    """merl | rgl | nielsen | all, or comma-separated material names ("merl/alum-bronze,...") or files
    (NAME.h5 neural-BRDF weights, NAME.binary MERL tables; read when the study loads them)."""
    from brdfs import measured, measured_data

    if text == "all":
        return list(measured.names())
    if text in COLLECTIONS:
        return list(measured.names(text))
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise InputError("--materials: give merl, rgl, nielsen, all or comma-separated material names")
    for n in names:
        if Path(n).suffix:
            if Path(n).suffix.lower() not in measured.SUFFIXES or not Path(n).is_file():
                raise InputError(f"--materials: {n!r} is not a measured-material file (an existing .h5 or .binary)")
        else:
            measured_data.find_material(n)  # InputError with close matches for an unknown name
    if len(set(names)) != len(names):
        raise InputError(f"--materials: {text!r} names a material twice")
    return names


def parse_resolution(text: str | None, default, flag: str) -> tuple[int, int, int]:
    """"NH,ND,NP" -> (n_theta_h, n_theta_d, n_phi_d) of a `brdf_space.sampling` grid."""
    if not text:
        return tuple(default)
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"{flag} {text!r}: expected three integers NH,ND,NP (e.g. 24,16,16)") from None
    if len(vals) != 3 or min(vals) < 1 or max(vals) > 512:
        raise InputError(f"{flag} {text!r}: expected three integers NH,ND,NP between 1 and 512")
    return vals


def check_output_dir(path: str | os.PathLike, flag: str = "-o") -> Path:
    """The study's output folder: an existing writable folder, or a new one in an existing writable folder."""
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise InputError(f"{flag} {p}: exists and is not a folder")
        if not os.access(p, os.W_OK | os.X_OK):
            raise InputError(f"{flag} {p}: folder is not writable")
        return p
    parent = p.resolve().parent
    if not parent.is_dir():
        raise InputError(f"{flag} {p}: parent folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {p}: parent folder {parent} is not writable")
    return p


@dataclasses.dataclass
class Study:
    """The fits of one study run; `fits[(material, model)]` (`brdf_space.BrdfFit` in BRDF space,
    `study_image.ImageFit` in image space). `images` (image space only): the first view of each target
    (`(material, "target")`) and of each fit (`(material, model)`), (H, W, 3) linear RGB, and the
    compared pixels of that view (`(material, "mask")`, (H, W))."""

    materials: list[str]
    models: list[str]
    metric: str
    fits: dict
    settings: dict
    wall_time_s: float
    space: str = "brdf"
    images: dict | None = None

    @property
    def outputs(self) -> tuple[str, ...]:
        return IMAGE_OUTPUTS if self.space == "image" else OUTPUTS

    @property
    def unit(self) -> str:
        return self.settings.get("unit") or bs.UNITS[self.metric]

    def error(self, material: str, model: str) -> float:
        return self.fits[(material, model)].error

    def table(self) -> np.ndarray:
        """(materials, models) errors of the study's metric on the evaluation grid."""
        return np.array([[self.error(a, m) for m in self.models] for a in self.materials])


def default_batch(n: int) -> int:
    """Materials per compiled solve: all of them on a GPU (one program for every lane), one on a CPU.

    A vmapped while loop computes every lane at every step until its slowest lane stops, and on a CPU
    the lanes run one after another anyway, so large batches only add waiting and memory traffic:
    20 MERL materials with 6 starts took 10 s in batches of 1 against 39 s in one batch of 20
    (Cook–Torrance), and 11 s against 13 s (2) and 16 s (5) (Ward), with identical fits, on the shared
    2-core CPU of BENCHMARKS.md.
    """
    import jax

    return n if jax.default_backend() == "gpu" else 1


def run(materials: Sequence[str], models: Sequence[str], *, metric: str = "ngan",
        fit_resolution=FIT_RESOLUTION, eval_resolution=EVAL_RESOLUTION, starts: int = 6, max_steps: int = 100,
        batch: int | None = None, progress: bool = True, devices=None) -> Study:
    """Fit every model to every material (see the module docstring); `batch` materials per compiled
    solve (default `default_batch`). A tqdm bar counts (material, model) fits.

    `devices` (None: the default device; an int N, "all" or a list of `jax.devices()`) splits each
    compiled solve's materials over several devices (`fitting.solve.solve_batch`); `batch` then counts
    materials per device (default `default_batch` of each device's share), so a call solves
    batch × N materials."""
    import jax
    from tqdm.auto import tqdm

    from fitting.solve import fit_devices

    bs.check_metric(metric)
    n_dev = max(1, len(fit_devices(devices)))
    t0 = time.perf_counter()
    samp = bs.sampling(*fit_resolution)
    ev = bs.sampling(*eval_resolution)
    if batch is None:
        batch = default_batch(-(-len(materials) // n_dev))
    batch = max(1, min(batch * n_dev, len(materials)))
    bar = tqdm(total=len(materials) * len(models), desc="study", unit="fit", disable=not progress)
    bar.set_postfix_str("sampling the measured materials")
    f_fit = bs.measured_samples(materials, samp)
    f_eval = bs.measured_samples(materials, ev)
    fits, per_model = {}, {}
    t_sample = time.perf_counter() - t0
    for name in models:
        t_model = time.perf_counter()
        model = bs.fit_model(name)
        for lo in range(0, len(materials), batch):
            names = list(materials[lo: lo + batch])
            bar.set_postfix_str(f"{name}: {names[0]}…")
            chunk = bs.fit_samples(f_fit[lo: lo + batch], model, names=names, metric=metric, samp=samp,
                                   f_eval=f_eval[lo: lo + batch], eval_samp=ev, starts=starts,
                                   max_steps=max_steps, batch=batch, devices=devices if n_dev > 1 else None)
            fits.update({(f.material, name): f for f in chunk})
            bar.update(len(names))
        per_model[name] = time.perf_counter() - t_model
    bar.close()
    settings = {
        "metric": metric, "unit": bs.UNITS[metric], "metric_definition": bs.METRIC_DOC[metric],
        "fit_sampling": samp.describe(), "eval_sampling": ev.describe(), "starts": starts, "max_steps": max_steps,
        "solver": f"Levenberg-Marquardt (optimistix), {bs.SOLVER}", "batch": batch, "devices": n_dev,
        "backend": jax.default_backend(), "device": jax.devices()[0].device_kind,
        "wall_s_sampling": t_sample, "wall_s_per_model": per_model,
        "models": {m: [dataclasses.asdict(p) for p in brdfs.get(m).spec] for m in models},
    }
    return Study(list(materials), list(models), metric, fits, settings, time.perf_counter() - t0)


# --- tables -----------------------------------------------------------------------------------------------


def _flat(values: dict) -> dict[str, float]:
    out = {}
    for k, v in values.items():
        if isinstance(v, list):
            out.update({f"{k}[{c}]": float(x) for c, x in zip("rgb", v)})
        else:
            out[k] = float(v)
    return out


def rows(study: Study) -> list[dict]:
    """One flat record per (material, model) for the CSV file."""
    out = []
    for a in study.materials:
        for m in study.models:
            f = study.fits[(a, m)]
            row = {"material": a, "model": m, "space": study.space, "metric": f.metric, "error": f.error, "unit": f.unit,
                   "fit_error": f.fit_error,
                   **{f"error_{k}": v for k, v in f.errors.items()},
                   "converged": f.converged, "iterations": f.iterations, "starts_at_best": f.starts_at_best,
                   "condition_number": f.condition_number,
                   "at_bound": ";".join(f"{k}:{v}" for k, v in f.at_bound.items()),
                   "tied": ";".join(f"{k}={v}" for k, v in f.tied.items())}
            row.update(_flat(f.params))
            row.update({f"stderr:{k}": v for k, v in _flat(f.stderr).items()})
            out.append(row)
    return out


def summary(study: Study) -> dict[str, dict]:
    """Per model: median, quartiles and mean of the error, how often it is the best model (ties go to
    the first in study order), how many fits end at a bound and how many converged."""
    e = study.table()
    best = np.argmin(e, axis=1)
    out = {}
    for j, m in enumerate(study.models):
        col = e[:, j]
        fits = [study.fits[(a, m)] for a in study.materials]
        out[m] = {"median": float(np.median(col)), "q1": float(np.percentile(col, 25)),
                  "q3": float(np.percentile(col, 75)), "mean": float(col.mean()),
                  "best": int(np.sum(best == j)), "at_bound": sum(1 for f in fits if f.at_bound),
                  "converged": sum(1 for f in fits if f.converged), "materials": len(fits)}
    return out


def summary_markdown(study: Study) -> str:
    s = summary(study)
    unit = study.unit
    st = study.settings
    if study.space == "image":
        head = [f"# Image-space study: {len(study.materials)} materials × {len(study.models)} models",
                "",
                f"Metric: {study.metric} — {st['metric_definition']}; E in {unit}. Scene: {st['scene']} "
                f"({st['size'][0]}×{st['size'][1]}, {st['pixels']} compared pixels over {len(st['lights'])} views)."]
    else:
        head = [f"# BRDF-space study: {len(study.materials)} materials × {len(study.models)} models",
                "",
                f"Metric: {study.metric} — {bs.METRIC_DOC[study.metric]}; E in {unit}, evaluated on the "
                f"{st['eval_sampling']['samples']}-pair grid (fits on "
                f"{st['fit_sampling']['samples']} pairs, θ ≤ {st['fit_sampling']['cutoff_deg']:g}°)."]
    lines = head + ["",
             "| model | median E | quartiles (25 %, 75 %) | mean E | best for | ends at a bound | converged |",
             "|---|---|---|---|---|---|---|"]
    order = sorted(study.models, key=lambda m: s[m]["median"])
    for m in order:
        r = s[m]
        lines.append(f"| {m} | {r['median']:.4g} | {r['q1']:.4g}, {r['q3']:.4g} | {r['mean']:.4g} | "
                     f"{r['best']} / {r['materials']} | {r['at_bound']} | {r['converged']} |")
    lines += ["", f"Wall time {study.wall_time_s:.1f} s ({study.settings['backend']}, "
              f"{study.settings['starts']} starts, batch {study.settings['batch']})."]
    return "\n".join(lines) + "\n"


def csv_text(study: Study) -> str:
    rs = rows(study)
    cols: list[str] = []
    for r in rs:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rs:
        w.writerow({k: ("" if r.get(k) is None else r.get(k, "")) for k in cols})
    return buf.getvalue()


def json_obj(study: Study) -> dict:
    return {"space": study.space, "materials": study.materials, "models": study.models, "metric": study.metric,
            "settings": study.settings, "wall_time_s": study.wall_time_s, "summary": summary(study),
            "fits": [study.fits[(a, m)].to_json() for a in study.materials for m in study.models]}


def grid_materials(study: Study, n: int = GRID_ROWS) -> list[str]:
    """n materials spread over the study's error range (by the best model's error), lowest first."""
    best = study.table().min(axis=1)
    order = np.argsort(best, kind="stable")
    if len(order) <= n:
        return [study.materials[i] for i in order]
    pick = np.unique(np.round(np.linspace(0, len(order) - 1, n)).astype(int))
    return [study.materials[order[i]] for i in pick]


def write(study: Study, out_dir: str | os.PathLike, grid: Sequence[str] | None = None) -> list[Path]:
    """Write every output (`study.outputs`: `OUTPUTS`, or `IMAGE_OUTPUTS` for an image-space study) into
    `out_dir`: all of them or, on any failure, none (each goes to a temporary file first; the renames
    happen only after all were written)."""
    from fitting import report
    from jaxrt.fsutil import atomic_path

    out_dir = Path(out_dir)
    grid = list(grid) if grid else grid_materials(study)
    for g in grid:
        if g not in study.materials:
            raise InputError(f"--grid: {g!r} is not one of the study's materials")
    created = not out_dir.exists()
    out_dir.mkdir(exist_ok=True)
    paths = [out_dir / n for n in study.outputs]
    try:
        with contextlib.ExitStack() as stack:
            tmp = {p.name: stack.enter_context(atomic_path(p)) for p in paths}
            tmp["study.csv"].write_text(csv_text(study))
            tmp["study.json"].write_text(json.dumps(json_obj(study), indent=1))
            tmp["summary.md"].write_text(summary_markdown(study))
            report.study_errors_png(tmp["errors.png"], study.materials, study.models, study.table(),
                                    study.metric, study.unit, space=study.space)
            if study.space == "image":
                report.study_renders_png(tmp["renders.png"], grid, study.models, study.images,
                                         {(a, m): study.fits[(a, m)] for a in grid for m in study.models})
            else:
                report.study_spheres_png(tmp["spheres.png"], grid, study.models,
                                         {(a, m): study.fits[(a, m)] for a in grid for m in study.models})
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                out_dir.rmdir()
        raise
    return paths
