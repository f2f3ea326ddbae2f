"""Scene files (TOML) -> validated `SceneSpec`, without touching JAX.

`parse` reads the TOML (tomllib: no eval, no pickle) and validates every table and key into the
plain records of `jaxrt.scene.spec`. Any problem raises one `InputError` naming the file, the table
and the key, and saying what is allowed. BRDF parameter bounds come from each model's `Param`
declarations, integrator names from `jaxrt.integrators.names()`, the bound on every other number
from `jaxrt.scene.tables.MAX_MAGNITUDE`.

Paths in a scene (mesh files, textures, environment maps) are relative to the scene file's folder
or absolute, as in other renderers. With `confine` (`--confine` on the CLI, or JAXRT_CONFINE=1) a
path is refused unless it resolves, symbolic links followed, inside the scene's folder or the data
folder (JAXRT_DATA), so an untrusted scene cannot read other files into its output. Registry names
(`mesh = "bunny"`) are always allowed.
"""

from __future__ import annotations

import numbers
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

import brdfs
from jaxrt import _config, integrators
from jaxrt import glare as _glare
from jaxrt.errors import InputError
from jaxrt.scene.spec import (
    DELTA,
    FRESNEL,
    GLASS_SHADOWS,
    CameraSpec,
    EnvironmentSpec,
    GroupSpec,
    InstanceSpec,
    MaterialSpec,
    ObjectSpec,
    RenderSpec,
    SceneSpec,
    TextureSpec,
)
from jaxrt.scene.tables import MAX_APERTURE_RATIO, MAX_MAGNITUDE, MIN_FOCUS_DISTANCE, Names, Table, parse_transform

SCENES_DIR = Path(__file__).resolve().parents[2] / "scenes"
#: `model = "measured"` in a material table: a measured BRDF (brdfs.measured) named by `data`
MEASURED = "measured"
MAX_RESOLUTION = 16384


def find_scene(name_or_path: str | os.PathLike) -> Path:
    """A scene file path, or a shipped scene's name (`spheres` -> scenes/spheres.toml)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    shipped = SCENES_DIR / f"{p.name if p.suffix == '' else p.stem}.toml"
    if p.suffix == "" and len(p.parts) == 1 and shipped.is_file():
        return shipped
    names = sorted(q.stem for q in SCENES_DIR.glob("*.toml")) if SCENES_DIR.is_dir() else []
    raise InputError(f"{name_or_path}: no such scene file; shipped scenes: {', '.join(names) or '(none)'}")


def apply_overrides(doc: dict, overrides: Mapping[str, Any] | None) -> dict:
    """Overrides are {"camera.width": 64, "render.spp": 4, ...} applied before validation."""
    if not overrides:
        return doc
    doc = {k: (dict(v) if isinstance(v, dict) else v) for k, v in doc.items()}
    for dotted, value in overrides.items():
        if value is None:
            continue
        table, key = dotted.split(".", 1)
        doc.setdefault(table, {})
        if not isinstance(doc[table], dict):
            raise InputError(f"[{table}] is not a table")
        doc[table][key] = value
    return doc


class Paths:
    """Resolves the file paths a scene names: relative to `base` (the scene's folder) or absolute;
    with `confine`, only inside `base` or the data folder (see the module docstring)."""

    def __init__(self, base: Path, confine: bool):
        self.base, self.confine = base, confine
        data = _config.config().data
        self.roots = [Path(os.path.realpath(base))] + ([Path(os.path.realpath(data))] if data else [])

    def resolve(self, ref: str) -> Path:
        p = Path(ref)
        return p if p.is_absolute() else self.base / p

    def refusal(self, ref: str, full: Path) -> str | None:
        """Why `full` (from the scene's `ref`) is refused under confinement, or None."""
        if not self.confine:
            return None
        real = Path(os.path.realpath(full))
        if any(real.is_relative_to(r) for r in self.roots):
            return None
        where = " or the data folder " + str(self.roots[1]) if len(self.roots) > 1 else ""
        return (f"{ref!r} resolves to {real}, outside the scene's folder {self.roots[0]}{where}; "
                "paths must stay inside them with --confine / JAXRT_CONFINE=1")


def _not_a_file(ref: str, full: Path) -> str:
    if full.is_dir():
        return f"{ref!r} is a directory, not a file (looked for {full})"
    return f"{ref!r}: no such file (looked for {full})"


def parse(
    source: str | os.PathLike | Mapping, base_dir: str | os.PathLike | None = None,
    overrides: Mapping[str, Any] | None = None, confine: bool | None = None,
) -> SceneSpec:
    """Read and validate a scene (a TOML path or an already-parsed dict) without touching JAX.

    base_dir: the folder relative paths are resolved against (default: the file's; for a dict,
    the current directory). confine: refuse paths outside that folder and the data folder
    (default: JAXRT_CONFINE).
    """
    confine = _config.config().confine if confine is None else bool(confine)
    if isinstance(source, Mapping):
        file, doc = "<scene>", dict(source)
        base = Path(base_dir or ".")
    else:
        path = Path(source)
        file = str(path)
        if path.is_dir():
            raise InputError(f"{file}: is a directory, not a scene file")
        if not path.is_file():
            raise InputError(f"{file}: no such scene file")
        try:
            with open(path, "rb") as f:
                doc = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{file}: not valid TOML: {' '.join(str(e).split())}") from None
        except UnicodeDecodeError:
            raise InputError(f"{file}: not a text file (TOML must be UTF-8 text)") from None
        except OSError as e:
            raise InputError(f"{file}: cannot read: {e.strerror}") from None
        base = Path(base_dir) if base_dir is not None else path.parent
    paths = Paths(base, confine)
    try:
        doc = apply_overrides(doc, overrides)
    except InputError as e:
        raise InputError(f"{file}: {e}") from None

    top = Table(file, "top level", doc)
    for k in ("camera", "lights", "materials", "objects", "render", "description", "groups", "instances", "environment",
              "glare"):
        top.used.add(k)
    top.done()
    if "description" in doc and not isinstance(doc["description"], str):
        top.fail("description", "expected a string")

    # ---- camera
    c = Table(file, "camera", top.raw("camera"))
    position = c.vector("position", 3)
    look_at = c.vector("look_at", 3)
    up = c.vector("up", 3, default=[0.0, 1.0, 0.0])
    # the camera's basis is computed in float32 (jaxrt.camera.basis): check it there
    view = np.subtract(np.float32(look_at), np.float32(position), dtype=np.float32)
    if not np.any(view):
        c.fail("look_at", f"{list(look_at)} must differ from position {list(position)} (in float32)")
    fwd = view / np.linalg.norm(view)
    up32 = np.asarray(up, np.float32)
    if np.linalg.norm(np.cross(fwd, up32)) <= 1e-6 * np.linalg.norm(up32) or not np.any(up32):
        c.fail("up", f"{list(up)} must not be zero or parallel to the view direction")
    focus = c.number("focus_distance", min(float(np.linalg.norm(np.subtract(look_at, position))), MAX_MAGNITUDE),
                     lo=MIN_FOCUS_DISTANCE)
    aperture = c.number("aperture", 0.0, lo=0.0)
    if aperture > MAX_APERTURE_RATIO * focus:
        c.fail("aperture", f"{aperture:g} is more than {MAX_APERTURE_RATIO:g} × focus_distance ({focus:g}); "
                           "a lens that wide loses the scene in float32")
    camera = CameraSpec(
        position=position, look_at=look_at, up=up,
        vfov=c.number("vfov", 40.0, lo=0.0, hi=180.0, lo_open=True, hi_open=True),
        aperture=aperture, focus_distance=focus,
        width=c.integer("width", 512, lo=1, hi=MAX_RESOLUTION),
        height=c.integer("height", 512, lo=1, hi=MAX_RESOLUTION),
    )
    c.done()

    # ---- environment (optional)
    environment = None
    if "environment" in doc:
        ec = Table(file, "environment", doc["environment"])
        env_file = ec.string("file", None)
        env_rad = ec.vector("radiance", 3, default=None, lo=0.0, scalar_ok=True)
        if (env_file is None) == (env_rad is None):
            ec.fail(None, "give exactly one of file = \"map.exr\" (lat-long OpenEXR or .hdr) or radiance = [r, g, b]")
        env_path = None
        if env_file is not None:
            env_path = paths.resolve(env_file)
            from jaxrt.envmap import SUFFIXES

            if env_path.suffix.lower() not in SUFFIXES:
                ec.fail("file", f"{env_file!r}: lat-long maps must be OpenEXR (.exr) or Radiance RGBE "
                                "(.hdr, .pic)")
            if (why := paths.refusal(env_file, env_path)) is not None:
                ec.fail("file", why)
            if not env_path.is_file():
                ec.fail("file", _not_a_file(env_file, env_path))
        environment = EnvironmentSpec(
            file=env_path, radiance=env_rad or (0.0, 0.0, 0.0),
            scale=ec.number("scale", 1.0, lo=0.0), rotate=ec.number("rotate", 0.0),
        )
        ec.done()

    # ---- lights (point lights; optional when the scene has an environment or an emissive material,
    # checked below once the materials are read)
    raw_lights = top.raw("lights", [])
    if not isinstance(raw_lights, list):
        top.fail("lights", "expected one or more [[lights]] tables (point lights)")
    lights = []
    for i, l in enumerate(raw_lights):
        lc = Table(file, f"[lights] #{i + 1}", l)
        lc.string("type", "point", choices=("point",))
        lights.append((lc.vector("position", 3), lc.vector("intensity", 3, lo=0.0, scalar_ok=True)))
        lc.done()

    # ---- materials
    raw_mats = top.raw("materials")
    if not isinstance(raw_mats, dict) or not raw_mats:
        top.fail("materials", "expected one or more [materials.NAME] tables")
    materials: dict[str, MaterialSpec] = {}
    for name, m in raw_mats.items():
        mc = Table(file, f"materials.{name}", m)
        if not name or not name.isprintable():
            mc.fail(None, f"{name!r}: a material name must be a non-empty name without control characters")
        model_name = mc.string("model", choices=tuple(brdfs.names()) + (MEASURED,))
        if model_name == MEASURED:
            materials[name] = parse_measured(mc, name, paths)
            continue
        model = brdfs.get(model_name)
        fresnel = FRESNEL[0]
        if model.delta:
            delta = 0.0
            emission = (0.0, 0.0, 0.0)
            fresnel = mc.string("fresnel", FRESNEL[0], choices=FRESNEL)
        else:
            delta = mc.number("delta", DELTA.default, lo=DELTA.lo, hi=DELTA.hi)
            emission = mc.vector("emission", 3, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True)
        params, textures = {}, {}
        for p in model.spec:
            value = mc.raw(p.name, p.default)
            if isinstance(value, Mapping) and not model.delta:
                textures[p.name] = parse_texture(value, p, model.name, paths, f"{file}: materials.{name}.{p.name}")
                params[p.name] = np.asarray(textures[p.name].texels.reshape(-1, textures[p.name].texels.shape[-1])
                                            .mean(0) if p.rgb else textures[p.name].texels.mean(), np.float32)
                continue
            if not _numbers(value, p.rgb):
                mc.fail(p.name, f"expected a number{' or an RGB triple [r, g, b]' if p.rgb else ''}"
                                f"{' or a texture table' if not model.delta else ''}, got {value!r}")
            try:
                params[p.name] = p.check(value, model.name)
            except ValueError as e:
                mc.fail(p.name, str(e).split(": ", 1)[-1])
        mc.done()
        materials[name] = MaterialSpec(name, model_name, params, delta, textures, emission=emission, fresnel=fresnel)

    emits = (any(max(i) > 0 for _, i in lights)
             or any(max(m.emission) > 0 for m in materials.values())
             or (environment is not None and environment.scale > 0
                 and (environment.file is not None or max(environment.radiance) > 0)))
    if not emits:
        top.fail("lights", "the scene has no light that emits anything: give one or more [[lights]] tables "
                           "(point lights) with intensity > 0, an [environment], or a material with "
                           "emission > 0")

    # ---- objects (optional when [[instances]] place groups)
    raw_objs = top.raw("objects", None)
    has_instances = doc.get("instances") is not None
    if raw_objs is None and has_instances:
        raw_objs = []
    elif not isinstance(raw_objs, list) or (not raw_objs and not has_instances):
        top.fail("objects", "expected one or more [[objects]] tables (or [[groups]] placed by [[instances]])")
    names = Names.of(doc)
    objects = [parse_object(Table(file, f"[objects] #{i + 1}", o), materials, paths, names)
               for i, o in enumerate(raw_objs)]

    # ---- groups and instances (jaxrt.geometry.instanced)
    groups, instances = parse_instances(doc, file, materials, paths, names)

    # ---- render
    rc = Table(file, "render", top.raw("render", {}))
    render = RenderSpec(
        integrator=rc.string("integrator", "whitted", choices=integrators.names()),
        max_depth=rc.integer("max_depth", 5, lo=1, hi=16),
        spp=rc.integer("spp", 1, lo=1, hi=4096),
        seed=rc.integer("seed", 0, lo=0, hi=2**31 - 1),
        background=rc.vector("background", 3, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True),
        ray_budget=rc.integer("ray_budget", None, lo=1, hi=8) if "ray_budget" in rc.data else None,
        glass_shadows=rc.string("glass_shadows", GLASS_SHADOWS[0], choices=GLASS_SHADOWS),
        # SPPM (`integrator = "sppm"`): photons per pass and initial gather radius [scene units]
        photons=rc.integer("photons", 0, lo=1, hi=integrators.sppm.MAX_PHOTONS) if "photons" in rc.data else 0,
        radius=rc.number("radius", 0.0, lo=0.0, lo_open=True) if "radius" in rc.data else 0.0,
        camera_samples=(rc.integer("camera_samples", 0, lo=1, hi=integrators.sppm.MAX_CAMERA_SAMPLES)
                        if "camera_samples" in rc.data else 0),
        grid_levels=(rc.integer("grid_levels", 0, lo=1, hi=integrators.sppm.MAX_GRID_LEVELS)
                     if "grid_levels" in rc.data else 0),
        # SPPM photon aiming: the fraction of photons sent towards the glass and mirror objects
        # (None: the integrator's default, see `jaxrt.integrators.sppm`)
        photon_aim=rc.number("photon_aim", 0.0, lo=0.0, hi=1.0, hi_open=True) if "photon_aim" in rc.data else None,
        # SPPM radius reduction α of the progressive update, 0 < α < 1 (0: the integrator's default)
        alpha=rc.number("alpha", 0.0, lo=0.0, lo_open=True, hi=1.0, hi_open=True) if "alpha" in rc.data else 0.0,
    )
    rc.raw("ray_budget", None)
    rc.raw("photons", None)
    rc.raw("radius", None)
    rc.raw("camera_samples", None)
    rc.raw("grid_levels", None)
    rc.raw("photon_aim", None)
    rc.raw("alpha", None)
    rc.done()
    glare = parse_glare(Table(file, "glare", doc["glare"])) if "glare" in doc else None
    return SceneSpec(file, camera, tuple(lights), materials, tuple(objects), render, groups, instances, environment,
                     glare)


def parse_glare(gc: Table) -> "_glare.Glare":
    """The [glare] table: every key optional (`jaxrt.glare.FIELDS` holds defaults and ranges); its
    presence turns glare on. Cross-key limits (the Airy radius against `size`) fail naming the table."""
    values = {}
    for name, (default, lo, hi, kind, _doc) in _glare.FIELDS.items():
        if name not in gc.data:
            gc.raw(name, None)
            continue
        if kind == "choice":
            values[name] = gc.string(name, choices=_glare.APERTURES)
        elif kind in ("int", "odd"):
            values[name] = gc.integer(name, lo=lo, hi=hi)
            if kind == "odd" and values[name] % 2 == 0:
                gc.fail(name, f"{values[name]} must be odd (the PSF has a centre pixel)")
        else:
            values[name] = gc.number(name, lo=lo, hi=hi)
    if values.get("aperture") == "circle":
        for key in ("blades", "rotation"):
            if key in values:
                gc.fail(key, 'applies to aperture = "polygon" only')
    gc.done()
    try:
        return _glare.Glare(**values)
    except InputError as e:
        gc.fail(None, str(e).removeprefix("glare: "))


def parse_measured(mc: Table, name: str, paths: Paths) -> MaterialSpec:
    """A `model = "measured"` material table: `data` is a measured material's name
    ("merl/gold-metallic-paint", found through JAXRT_DATA) or a file, relative to the scene's folder
    or absolute: NAME.h5 (neural-BRDF weights) or NAME.binary (a MERL table); `delta` and `emission`
    as for other opaque materials. The data are read and checked here (numpy and h5py, no JAX)."""
    data = mc.string("data")
    delta = mc.number("delta", DELTA.default, lo=DELTA.lo, hi=DELTA.hi)
    emission = mc.vector("emission", 3, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True)
    mc.done()
    ref = data
    if Path(data).suffix:  # a file (a name "COLLECTION/NAME" has no suffix)
        full = paths.resolve(data)
        if Path(data).suffix.lower() not in brdfs.measured.SUFFIXES:
            mc.fail("data", f"{data!r}: measured BRDF files are neural-BRDF weights (.h5) or MERL tables "
                            "(.binary); or give a material name such as 'merl/gold-metallic-paint'")
        if (why := paths.refusal(data, full)) is not None:
            mc.fail("data", why)
        if not full.is_file():
            mc.fail("data", _not_a_file(data, full))
        ref = str(full)
    try:
        model, raw = brdfs.measured.read(ref)
    except InputError as e:
        mc.fail("data", str(e))
    return MaterialSpec(name, model.name, raw, delta, emission=emission, data=ref)


def _numbers(value, rgb: bool) -> bool:
    """value is a number, or (rgb) 3 numbers (a list, tuple or array): what a parameter's value may be."""
    def num(x):
        return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "fiu" and value.shape in (((), (3,)) if rgb else ((),))
    if num(value):
        return True
    return rgb and isinstance(value, (list, tuple)) and len(value) == 3 and all(num(x) for x in value)


def parse_object(oc: "Table", materials: dict, paths: Paths, names: Names) -> ObjectSpec:
    """One [[objects]] (or [[groups.objects]]) table. An explicit name must be unique (`names`);
    a default one (the primitive or the mesh file's stem) gets .2, .3, ... when taken."""
    mesh_ref = oc.string("mesh", None)
    prim = oc.string("primitive", None, choices=("sphere", "plane", "box"))
    if (mesh_ref is None) == (prim is None):
        oc.fail(None, "give exactly one of mesh = NAME|PATH or primitive = sphere|plane|box")
    if "name" in oc.data:
        name = oc.string("name")
        if not name or not name.isprintable():
            oc.fail("name", f"{name!r}: expected a non-empty name without control characters")
        names.claim(name, oc)
    else:
        oc.raw("name", None)
        name = names.generate(Path(mesh_ref).stem if prim is None else prim, oc)
    material = oc.string("material", choices=tuple(materials))
    prim_args: dict = {}
    mesh_path = None
    parts = None
    part_materials: dict = {}
    flat = False
    if prim == "sphere":
        prim_args["radius"] = oc.number("radius", 1.0, lo=0.0, lo_open=True)
        prim_args["subdivisions"] = oc.integer("subdivisions", 4, lo=0, hi=7)
    elif prim == "plane":
        prim_args["size"] = oc.vector("size", 2, default=[1.0, 1.0], lo=1e-30)
    elif prim == "box":
        prim_args["size"] = oc.vector("size", 3, default=[1.0, 1.0, 1.0], lo=1e-30, scalar_ok=True)
    else:
        mesh_path = resolve_mesh(mesh_ref, paths, oc)
        flat = oc.boolean("flat", False)
        p = oc.raw("parts", None)
        if p is not None:
            if not isinstance(p, list) or not p or not all(isinstance(x, str) for x in p):
                oc.fail("parts", f"expected a list of object names in the mesh file, got {p!r}")
            parts = tuple(p)
        pm = oc.raw("part_materials", {})
        if not isinstance(pm, dict) or not all(isinstance(v, str) for v in pm.values()):
            oc.fail("part_materials", "expected a table {part_name = \"material\", ...}")
        for part, mat in pm.items():
            if mat not in materials:
                oc.fail(f"part_materials.{part}", f"{mat!r} is not a material; allowed: {', '.join(materials)}")
        part_materials = dict(pm)
    scale, rotate, translate = parse_transform(oc)
    oc.done()
    return ObjectSpec(name, material, mesh_path, prim, prim_args, scale, rotate, translate, flat, parts,
                      part_materials)


def parse_texture(t: Mapping, p, model: str, paths: Paths, where: str) -> TextureSpec:
    """Validate a texture table `{ texture = "file.png" | checker = [a, b], wrap, scale, offset }` for
    parameter declaration `p` (see jaxrt/textures.py for the conventions)."""
    from jaxrt.shading import textures as _tx

    allowed = ("texture", "checker", "wrap", "scale", "offset")
    unknown = [k for k in t if k not in allowed]
    if unknown:
        raise InputError(f"{where}: unknown texture key {unknown[0]!r}; allowed: {', '.join(allowed)}")
    if ("texture" in t) == ("checker" in t):
        raise InputError(f"{where}: a texture table needs exactly one of texture = \"FILE.png|.exr\" "
                         "or checker = [VALUE_A, VALUE_B]")
    wrap = t.get("wrap", "repeat")
    if not isinstance(wrap, str) or wrap not in _tx.WRAPS:
        raise InputError(f"{where}: wrap = {wrap!r}; allowed: {', '.join(_tx.WRAPS)}")

    def pair(key, default, positive):
        v = t.get(key, default)
        try:
            a = np.broadcast_to(np.asarray(v, np.float64), (2,))
        except (TypeError, ValueError):
            raise InputError(f"{where}: {key} must be a number or [u, v], got {v!r}") from None
        if a.dtype == object or isinstance(v, (bool, str)) or (isinstance(v, list) and any(
                isinstance(x, (bool, str)) for x in v)):
            raise InputError(f"{where}: {key} must be a number or [u, v], got {v!r}")
        if not np.all(np.isfinite(a)) or (positive and np.any(a == 0)) or np.any(np.abs(a) > MAX_MAGNITUDE):
            raise InputError(f"{where}: {key} = {v!r} must be finite{' and non-zero' if positive else ''}, "
                             f"with magnitude <= {MAX_MAGNITUDE:g}")
        return tuple(float(x) for x in a)

    scale, offset = pair("scale", 1.0, True), pair("offset", 0.0, False)
    chans = 3 if p.rgb else 1
    if "checker" in t:
        vals = t["checker"]
        if not isinstance(vals, list) or len(vals) != 2:
            raise InputError(f"{where}: checker must be a list of two values, got {vals!r}")
        texels = []
        for k, v in enumerate(vals):
            if not _numbers(v, p.rgb):
                raise InputError(f"{where}: checker value {k + 1} must be a number"
                                 f"{' or an RGB triple' if p.rgb else ''}, got {v!r}")
            if not p.rgb and np.ndim(v) != 0:
                raise InputError(f"{where}: checker value {k + 1} must be a number ({p.name} is not RGB), got {v!r}")
            try:
                texels.append(np.broadcast_to(p.check(v, model), (chans,)))
            except ValueError as e:
                raise InputError(f"{where}: checker value {k + 1}: {str(e).split(': ', 1)[-1]}") from None
        return TextureSpec("checker", np.stack(texels)[None].astype(np.float32), wrap, scale, offset, "checker")
    ref = t["texture"]
    if not isinstance(ref, str):
        raise InputError(f"{where}: texture must be a file name, got {ref!r}")
    path = paths.resolve(ref)
    if (why := paths.refusal(ref, path)) is not None:
        raise InputError(f"{where}: texture {why}")
    if path.is_dir():
        raise InputError(f"{where}: texture {ref!r} is a directory, not an image file (looked for {path})")
    texels = _tx.read_image(path, p.rgb, where)
    if not np.all(np.isfinite(texels)):
        raise InputError(f"{where}: {path} contains non-finite values")
    lo, hi = float(texels.min()), float(texels.max())
    if lo < p.lo or hi > p.hi:
        raise InputError(f"{where}: {path} has values in [{lo:g}, {hi:g}], outside the allowed range "
                         f"[{p.lo:g}, {p.hi:g}] of {model}.{p.name}")
    return TextureSpec("image", texels, wrap, scale, offset, str(path))


def resolve_mesh(ref: str, paths: Paths, oc: Table) -> Path:
    """A registry name (bunny, dragon, ...: found through jaxrt.geometry.data) or a path relative to the
    scene (refused outside the allowed folders under confinement)."""
    p = Path(ref)
    if p.suffix == "" and len(p.parts) == 1:
        from jaxrt.geometry import data

        try:
            return Path(data.find(ref))
        except (ValueError, FileNotFoundError, KeyError) as e:
            msg = str(e)
        oc.fail("mesh", f"{ref!r}: {msg}")
    full = paths.resolve(ref)
    if (why := paths.refusal(ref, full)) is not None:
        oc.fail("mesh", why)
    if not full.is_file():
        oc.fail("mesh", _not_a_file(ref, full))
    return full


def parse_instances(doc: dict, file: str, materials: dict, paths: Paths, names: Names):
    """Validate [[groups]] and [[instances]] of a parsed TOML document.

    A group's objects take the keys of [[objects]] (`parse_object`). Returns
    (groups, instances) as tuples of GroupSpec / InstanceSpec; ((), ()) when the scene has none.
    Raises InputError naming the file, table and key.
    """
    raw_groups, raw_inst = doc.get("groups"), doc.get("instances")
    if raw_groups is None and raw_inst is None:
        return (), ()
    top = Table(file, "top level", {k: doc[k] for k in ("groups", "instances") if k in doc})
    if raw_groups is not None and (not isinstance(raw_groups, list) or not raw_groups):
        top.fail("groups", "expected one or more [[groups]] tables")
    groups: dict[str, GroupSpec] = {}
    for i, g in enumerate(raw_groups or []):
        gc = Table(file, f"[groups] #{i + 1}", g)
        name = gc.string("name")
        if not name or "/" in name or not name.isprintable():
            gc.fail("name", f"{name!r}: expected a non-empty name without '/' or control characters")
        if name in groups:
            gc.fail("name", f"{name!r}: a group of this name is already defined")
        objs = gc.raw("objects", None)
        if not isinstance(objs, list) or not objs:
            gc.fail("objects", "expected one or more [[groups.objects]] tables")
        gc.done()
        seen = Names.of({"objects": objs})
        specs = []
        for j, o in enumerate(objs):
            oc = Table(file, f"[groups] {name}: [objects] #{j + 1}", o)
            if "group" in o:
                oc.fail("group", "groups cannot contain groups (nested instancing is not supported); "
                                 "place each group with [[instances]]")
            specs.append(parse_object(oc, materials, paths, seen))
        groups[name] = GroupSpec(name, tuple(specs))
    if raw_inst is None:
        return tuple(groups.values()), ()
    if not isinstance(raw_inst, list) or not raw_inst:
        top.fail("instances", "expected one or more [[instances]] tables")
    instances = []
    counts: dict[str, int] = {}
    for i, t in enumerate(raw_inst):
        ic = Table(file, f"[instances] #{i + 1}", t)
        group = ic.raw("group")
        if not isinstance(group, str) or group not in groups:
            ic.fail("group", f"{group!r} is not a defined group; groups: {', '.join(groups) or '(none)'}")
        name = ic.string("name", None)
        if name is None:
            counts[group] = counts.get(group, 0) + 1
            name = names.generate(f"{group}.{counts[group]}", ic)
        else:
            if not name or "/" in name or not name.isprintable():
                ic.fail("name", f"{name!r}: expected a non-empty name without '/' or control characters")
            names.claim(name, ic)
        scale, rotate, translate = parse_transform(ic)
        material = ic.string("material", None, choices=tuple(materials))
        ic.done()
        instances.append(InstanceSpec(name, group, scale, rotate, translate, material))
    return tuple(groups.values()), tuple(instances)
