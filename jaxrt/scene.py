"""Scene files: TOML -> validated specification -> `Scene` pytree of arrays.

Loading happens in two stages so that bad input is caught before any JAX work:

1. `parse(...)` reads the TOML (tomllib: no eval, no pickle) and validates every table and key
   into plain Python records (`SceneSpec`). Any problem raises one `InputError` naming the file,
   the table and the key, and saying what is allowed. BRDF parameter bounds come from each
   model's `Param` declarations (the single source of truth).
2. `build(spec)` loads meshes, places primitives, concatenates everything into one triangle set
   with one BVH, and groups materials by model into stacked parameter tables.

In the resulting `Scene` every value (vertices, material parameters, lights, camera, background)
is a traced array; only shapes and the set of models are static, so changing a parameter, a light
or the camera never recompiles the renderer. See README "Scene files" for an annotated example.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrt.camera import Camera
from jaxrt.errors import InputError
from jaxrt.lights import AreaLights, PointLights

SCENES_DIR = Path(__file__).resolve().parents[1] / "scenes"
INTEGRATORS = ("whitted", "path")
MAX_RESOLUTION = 16384

# --------------------------------------------------------------------------- arrays (pytrees)


class Materials(eqx.Module):
    """Materials grouped by model so per-pixel model selection is a gather plus a select.

    Attributes:
        params: one stacked parameter table per model in `models`; table k maps each parameter
            name to an array with one row per material of that model ((rows, 3) RGB, (rows,) scalar).
        model_id: (M,) index into `models` for each material.
        row: (M,) row of each material in its model's table.
        delta: (M,) the seed's mirror reflection coefficient δ in [0, 1] (0 for glass).
        models: static tuple of `brdfs` model names used by the scene.
        names: static tuple of material names (scene-file keys), index = material id.
    """

    params: tuple[dict, ...]
    model_id: Int[Array, "M"]
    row: Int[Array, "M"]
    delta: Float[Array, "M"]
    models: tuple[str, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    # Textured parameters (jaxrt.textures): the texel values are traced, which parameter of which
    # material row uses which texture is static: bindings[j] = (model index, row, param, texture index).
    textures: tuple = ()
    bindings: tuple[tuple[int, int, str, int], ...] = eqx.field(static=True, default=())

    def index(self, name: str) -> int:
        if name not in self.names:
            raise InputError(f"unknown material {name!r}; the scene defines: {', '.join(self.names)}")
        return self.names.index(name)


class Geometry(eqx.Module):
    """All triangles of the scene in one set (original face order) plus its BVH.

    vertices/normals/tangents: (V, 3) world space; faces: (F, 3) int32; material: (F,) material id
    per face; object_id: (F,) scene-object id per face; tree: the `jaxrt.bvh` pytree.
    """

    vertices: Float[Array, "V 3"]
    normals: Float[Array, "V 3"]
    tangents: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    material: Int[Array, "F"]
    object_id: Int[Array, "F"]
    tree: Any
    object_names: tuple[str, ...] = eqx.field(static=True)
    uvs: Float[Array, "V 2"] | None = None  # texture coordinates per vertex (zeros where a mesh has none)


class Settings(eqx.Module):
    """Render settings. background: (3,) linear RGB radiance of rays that escape; seed: () int."""

    background: Float[Array, "3"]
    seed: Int[Array, ""]
    integrator: str = eqx.field(static=True)
    max_depth: int = eqx.field(static=True)
    spp: int = eqx.field(static=True)
    ray_budget: int = eqx.field(static=True)


class Scene(eqx.Module):
    geometry: Geometry
    materials: Materials
    lights: PointLights
    camera: Camera
    settings: Settings
    source: str = eqx.field(static=True, default="<scene>")
    # emissive materials/triangles and the environment (None: no environment); used by the path
    # tracer, and Whitted's escaping rays see the environment instead of `background`
    area_lights: AreaLights | None = None
    environment: Any = None

    # ---- value updates (validated, never recompile) ----
    def with_material(self, name: str, **values) -> "Scene":
        """A copy with material `name`'s parameters (or `delta`) changed; bounds-checked."""
        import brdfs

        mats = self.materials
        i = mats.index(name)
        m = int(mats.model_id[i])
        model = brdfs.get(mats.models[m])
        r = int(mats.row[i])
        table = dict(mats.params[m])
        delta = mats.delta
        for k, v in values.items():
            if k == "delta":
                if model.delta:
                    raise InputError(f"material {name!r}: delta is not a parameter of {model.name}")
                delta = delta.at[i].set(_check_range(v, 0.0, 1.0, f"material {name!r}: delta"))
                continue
            if any(b[:3] == (m, r, k) for b in mats.bindings):
                raise InputError(f"material {name!r}: {k} is textured; change it with with_texture")
            try:
                val = model.param(k).check(v, model.name)
            except ValueError as e:
                raise InputError(f"material {name!r}: {e}") from None
            table[k] = table[k].at[r].set(val)
        params = tuple(table if j == m else t for j, t in enumerate(mats.params))
        return eqx.tree_at(lambda s: (s.materials.params, s.materials.delta), self, (params, delta))

    def with_texture(self, name: str, param: str, texels) -> "Scene":
        """A copy with the texels of material `name`'s textured parameter `param` replaced (same shape;
        never recompiles). Concrete values must be finite; they are not range-checked here (an
        optimiser's steps may pass through), and traced values (inside jax.grad) are not checked."""
        mats = self.materials
        i = mats.index(name)
        key = (int(mats.model_id[i]), int(mats.row[i]), param)
        hit = [b[3] for b in mats.bindings if b[:3] == key]
        if not hit:
            raise InputError(f"material {name!r}: {param} is not textured")
        old = mats.textures[hit[0]].texels
        new = jnp.asarray(texels, jnp.float32)
        if new.shape != old.shape:
            raise InputError(f"material {name!r}: {param} texels must keep the shape {old.shape}, got {new.shape}")
        if not isinstance(new, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(new))):
            raise InputError(f"material {name!r}: {param} texels must be finite")
        return eqx.tree_at(lambda s: s.materials.textures[hit[0]].texels, self, new)

    def with_light(self, index: int = 0, position=None, intensity=None) -> "Scene":
        """A copy with light `index` moved and/or re-scaled."""
        lights = self.lights
        pos, inten = lights.position, lights.intensity
        if position is not None:
            pos = pos.at[index].set(_vec3(position, f"light {index}: position"))
        if intensity is not None:
            inten = inten.at[index].set(_rgb(intensity, f"light {index}: intensity", lo=0.0))
        return eqx.tree_at(lambda s: (s.lights.position, s.lights.intensity), self, (pos, inten))

    def with_camera(self, **values) -> "Scene":
        """A copy with camera values (position, look_at, up, vfov, aperture, focus_distance) changed."""
        cam = self.camera
        names = ("position", "look_at", "up", "vfov", "aperture", "focus_distance")
        for k in values:
            if k not in names:
                raise InputError(f"camera: unknown key {k!r}; allowed: {', '.join(names)}")
        new = [jnp.asarray(values.get(k, getattr(cam, k)), jnp.float32) for k in names]
        return eqx.tree_at(lambda s: tuple(getattr(s.camera, k) for k in names), self, tuple(new))


def _check_range(v, lo, hi, where):
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected a number in [{lo:g}, {hi:g}], got {v!r}") from None
    if not (lo <= x <= hi):
        raise InputError(f"{where}: {x:g} is outside the allowed range [{lo:g}, {hi:g}]")
    return x


def _vec3(v, where):
    a = np.asarray(v, np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{where}: expected 3 finite numbers, got {v!r}")
    return a.astype(np.float32)


def _rgb(v, where, lo=0.0):
    a = np.asarray(v, np.float64)
    if a.shape == ():
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a < lo):
        raise InputError(f"{where}: expected a finite number or RGB triple >= {lo:g}, got {v!r}")
    return a.astype(np.float32)


# --------------------------------------------------------------------------- validated spec


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    position: tuple
    look_at: tuple
    up: tuple
    vfov: float
    aperture: float
    focus_distance: float
    width: int
    height: int


@dataclasses.dataclass(frozen=True)
class MaterialSpec:
    name: str
    model: str
    params: dict  # name -> float32 numpy array (validated); a textured parameter holds its texture's mean
    delta: float
    textures: dict = dataclasses.field(default_factory=dict)  # name -> TextureSpec
    emission: tuple = (0.0, 0.0, 0.0)  # RGB radiance [W/(m²·sr)]


@dataclasses.dataclass(frozen=True)
class TextureSpec:
    kind: str  # "image" | "checker"
    texels: np.ndarray  # (H, W, C) float32 linear; checker: (1, 2, C)
    wrap: str
    uv_scale: tuple
    uv_offset: tuple
    source: str  # file path or "checker"


@dataclasses.dataclass(frozen=True)
class ObjectSpec:
    name: str
    material: str
    mesh: Path | None  # resolved mesh file
    primitive: str | None
    primitive_args: dict
    scale: Any
    rotate: tuple | None
    translate: tuple | None
    flat: bool
    parts: tuple[str, ...] | None
    part_materials: dict


@dataclasses.dataclass(frozen=True)
class RenderSpec:
    integrator: str
    max_depth: int
    spp: int
    seed: int
    background: tuple
    ray_budget: int | None


@dataclasses.dataclass(frozen=True)
class EnvironmentSpec:
    file: Path | None  # a lat-long OpenEXR map, or None for a constant environment
    radiance: tuple  # constant RGB radiance (file is None)
    scale: float
    rotate: float  # degrees about +y


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    source: str
    camera: CameraSpec
    lights: tuple[tuple[tuple, tuple], ...]
    materials: dict[str, MaterialSpec]
    objects: tuple[ObjectSpec, ...]
    render: RenderSpec
    groups: tuple = ()  # jaxrt.instancing.GroupSpec
    instances: tuple = ()  # jaxrt.instancing.InstanceSpec
    environment: EnvironmentSpec | None = None


_REQ = object()


class _Checker:
    """Typed access to one TOML table with error messages naming file, table and key."""

    def __init__(self, file: str, table: str, data: Any):
        self.file, self.table = file, table
        if not isinstance(data, dict):
            self.fail(None, f"expected a table, got {type(data).__name__}")
        self.data = data
        self.used: set[str] = set()

    def fail(self, key, msg):
        where = f"{self.file}: [{self.table}]" + (f" {key}" if key else "")
        raise InputError(f"{where}: {msg}")

    def raw(self, key, default=_REQ):
        self.used.add(key)
        if key not in self.data:
            if default is _REQ:
                self.fail(key, "is required but missing")
            return default
        return self.data[key]

    def number(self, key, default=_REQ, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
        v = self.raw(key, default)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"expected a finite number, got {v!r}")
        if v < lo or v > hi or (lo_open and v == lo) or (hi_open and v == hi):
            rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            self.fail(key, f"{v!r} is outside the allowed range {rng}")
        return float(v)

    def integer(self, key, default=_REQ, lo=-(2**31), hi=2**31 - 1):
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"expected an integer, got {v!r}")
        if not lo <= v <= hi:
            self.fail(key, f"{v} is outside the allowed range [{lo}, {hi}]")
        return int(v)

    def string(self, key, default=_REQ, choices: Sequence[str] | None = None):
        v = self.raw(key, default)
        if v is None:
            return None
        if not isinstance(v, str):
            self.fail(key, f"expected a string, got {v!r}")
        if choices is not None and v not in choices:
            self.fail(key, f"{v!r} is not allowed; allowed: {', '.join(choices)}")
        return v

    def boolean(self, key, default=_REQ):
        v = self.raw(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"expected true or false, got {v!r}")
        return v

    def vector(self, key, n, default=_REQ, lo=-math.inf, scalar_ok=False):
        v = self.raw(key, default)
        if v is None:
            return None
        if scalar_ok and isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * n
        ok = (
            isinstance(v, list)
            and len(v) == n
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        )
        if not ok:
            alt = " or a single number" if scalar_ok else ""
            self.fail(key, f"expected a list of {n} finite numbers{alt}, got {v!r}")
        if any(x < lo for x in v):
            self.fail(key, f"{v!r}: every component must be >= {lo:g}")
        return tuple(float(x) for x in v)

    def done(self, extra_allowed: Sequence[str] = ()):
        unknown = [k for k in self.data if k not in self.used and k not in extra_allowed]
        if unknown:
            allowed = sorted(self.used | set(extra_allowed))
            self.fail(unknown[0], f"unknown key; allowed: {', '.join(allowed)}")


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


def _apply_overrides(doc: dict, overrides: Mapping[str, Any] | None) -> dict:
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


def parse(
    source: str | os.PathLike | Mapping, base_dir: str | os.PathLike | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> SceneSpec:
    """Read and validate a scene (a TOML path or an already-parsed dict) without touching JAX."""
    if isinstance(source, Mapping):
        file, doc = "<scene>", dict(source)
        base = Path(base_dir or ".")
    else:
        path = Path(source)
        file = str(path)
        if not path.is_file():
            raise InputError(f"{file}: no such scene file")
        try:
            with open(path, "rb") as f:
                doc = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{file}: not valid TOML: {e}") from None
        except OSError as e:
            raise InputError(f"{file}: cannot read: {e.strerror}") from None
        base = Path(base_dir) if base_dir is not None else path.parent
    doc = _apply_overrides(doc, overrides)
    import brdfs  # cheap: no JAX tracing, only the parameter declarations

    top = _Checker(file, "top level", doc)
    for k in ("camera", "lights", "materials", "objects", "render", "description", "groups", "instances", "environment"):
        top.used.add(k)
    top.done()
    if "description" in doc and not isinstance(doc["description"], str):
        top.fail("description", "expected a string")

    # ---- camera
    c = _Checker(file, "camera", top.raw("camera"))
    position = c.vector("position", 3)
    look_at = c.vector("look_at", 3)
    up = c.vector("up", 3, default=[0.0, 1.0, 0.0])
    view = np.subtract(look_at, position)
    if np.linalg.norm(view) == 0:
        c.fail("look_at", "must differ from position")
    if np.linalg.norm(np.cross(view, up)) <= 1e-9 * np.linalg.norm(view) * max(np.linalg.norm(up), 1e-30):
        c.fail("up", f"{list(up)} must not be zero or parallel to the view direction")
    camera = CameraSpec(
        position=position, look_at=look_at, up=up,
        vfov=c.number("vfov", 40.0, lo=0.0, hi=180.0, lo_open=True, hi_open=True),
        aperture=c.number("aperture", 0.0, lo=0.0),
        focus_distance=c.number("focus_distance", float(np.linalg.norm(view)), lo=0.0, lo_open=True),
        width=c.integer("width", 512, lo=1, hi=MAX_RESOLUTION),
        height=c.integer("height", 512, lo=1, hi=MAX_RESOLUTION),
    )
    c.done()

    # ---- environment (optional)
    environment = None
    if "environment" in doc:
        ec = _Checker(file, "environment", doc["environment"])
        env_file = ec.string("file", None)
        env_rad = ec.vector("radiance", 3, default=None, lo=0.0, scalar_ok=True)
        if (env_file is None) == (env_rad is None):
            ec.fail(None, "give exactly one of file = \"map.exr\" (lat-long OpenEXR or .hdr) or radiance = [r, g, b]")
        env_path = None
        if env_file is not None:
            env_path = Path(env_file) if Path(env_file).is_absolute() else base / env_file
            from jaxrt.envmap import SUFFIXES

            if env_path.suffix.lower() not in SUFFIXES:
                ec.fail("file", f"{env_file!r}: lat-long maps must be OpenEXR (.exr) or Radiance RGBE "
                                "(.hdr, .pic)")
            if not env_path.is_file():
                ec.fail("file", f"{env_file!r}: no such file (looked for {env_path})")
        environment = EnvironmentSpec(
            file=env_path, radiance=env_rad or (0.0, 0.0, 0.0),
            scale=ec.number("scale", 1.0, lo=0.0), rotate=ec.number("rotate", 0.0),
        )
        ec.done()

    # ---- lights (point lights; optional when the scene has an environment or an emissive material)
    raw_lights = top.raw("lights", [])
    emissive = isinstance(doc.get("materials"), dict) and any(
        isinstance(m, dict) and "emission" in m for m in doc["materials"].values())
    if not isinstance(raw_lights, list) or (not raw_lights and environment is None and not emissive):
        top.fail("lights", "expected one or more [[lights]] tables (point lights), unless the scene has an "
                           "[environment] or a material with emission")
    lights = []
    for i, l in enumerate(raw_lights):
        lc = _Checker(file, f"[lights] #{i + 1}", l)
        lc.string("type", "point", choices=("point",))
        lights.append((lc.vector("position", 3), lc.vector("intensity", 3, lo=0.0, scalar_ok=True)))
        lc.done()

    # ---- materials
    raw_mats = top.raw("materials")
    if not isinstance(raw_mats, dict) or not raw_mats:
        top.fail("materials", "expected one or more [materials.NAME] tables")
    materials: dict[str, MaterialSpec] = {}
    for name, m in raw_mats.items():
        mc = _Checker(file, f"materials.{name}", m)
        model_name = mc.string("model", choices=tuple(brdfs.names()))
        model = brdfs.get(model_name)
        if model.delta:
            delta = 0.0
            emission = (0.0, 0.0, 0.0)
        else:
            delta = mc.number("delta", 0.0, lo=0.0, hi=1.0)
            emission = mc.vector("emission", 3, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True)
        params, textures = {}, {}
        for p in model.spec:
            value = mc.raw(p.name, p.default)
            if isinstance(value, Mapping) and not model.delta:
                textures[p.name] = _parse_texture(value, p, model.name, base, f"{file}: materials.{name}.{p.name}")
                params[p.name] = np.asarray(textures[p.name].texels.reshape(-1, textures[p.name].texels.shape[-1])
                                            .mean(0) if p.rgb else textures[p.name].texels.mean(), np.float32)
                continue
            try:
                params[p.name] = p.check(value, model.name)
            except ValueError as e:
                mc.fail(p.name, str(e).split(": ", 1)[-1])
        mc.done()
        materials[name] = MaterialSpec(name, model_name, params, delta, textures, emission=emission)

    # ---- objects (optional when [[instances]] place groups)
    raw_objs = top.raw("objects", None)
    has_instances = doc.get("instances") is not None
    if raw_objs is None and has_instances:
        raw_objs = []
    elif not isinstance(raw_objs, list) or (not raw_objs and not has_instances):
        top.fail("objects", "expected one or more [[objects]] tables (or [[groups]] placed by [[instances]])")
    names_seen: set[str] = set()
    objects = [_parse_object(_Checker(file, f"[objects] #{i + 1}", o), materials, base, names_seen)
               for i, o in enumerate(raw_objs)]

    # ---- groups and instances (jaxrt.instancing)
    from jaxrt import instancing

    groups, instances = instancing.parse(doc, file, materials, base,
                                         lambda oc, seen: _parse_object(oc, materials, base, seen), names_seen)

    # ---- render
    rc = _Checker(file, "render", top.raw("render", {}))
    render = RenderSpec(
        integrator=rc.string("integrator", "whitted", choices=INTEGRATORS),
        max_depth=rc.integer("max_depth", 5, lo=1, hi=16),
        spp=rc.integer("spp", 1, lo=1, hi=4096),
        seed=rc.integer("seed", 0, lo=0, hi=2**31 - 1),
        background=rc.vector("background", 3, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True),
        ray_budget=rc.integer("ray_budget", None, lo=1, hi=8) if "ray_budget" in rc.data else None,
    )
    rc.raw("ray_budget", None)
    rc.done()
    return SceneSpec(file, camera, tuple(lights), materials, tuple(objects), render, groups, instances, environment)


def _unique_name(name: str, names_seen: set[str]) -> str:
    """`name`, or name.2, name.3, ... if taken; the result is added to `names_seen`."""
    base_name, k = name, 2
    while name in names_seen:
        name, k = f"{base_name}.{k}", k + 1
    names_seen.add(name)
    return name


def _parse_transform(c: "_Checker") -> tuple:
    """(scale, rotate, translate) of an object or instance table, each None when absent."""
    scale = c.raw("scale", None)
    if scale is not None:
        scale = c.vector("scale", 3, lo=1e-30, scalar_ok=True)
        if any(s <= 0 for s in scale):
            c.fail("scale", "every component must be > 0")
    return scale, c.vector("rotate", 3, default=None), c.vector("translate", 3, default=None)


def _parse_object(oc: "_Checker", materials: dict, base: Path, names_seen: set[str]) -> ObjectSpec:
    """One [[objects]] (or [[groups.objects]]) table; `names_seen` makes names unique (adds .2, .3)."""
    mesh_ref = oc.string("mesh", None)
    prim = oc.string("primitive", None, choices=("sphere", "plane", "box"))
    if (mesh_ref is None) == (prim is None):
        oc.fail(None, "give exactly one of mesh = NAME|PATH or primitive = sphere|plane|box")
    name = oc.string("name", mesh_ref if prim is None else prim)
    if isinstance(name, str) and mesh_ref is not None and name == mesh_ref:
        name = Path(mesh_ref).stem
    name = _unique_name(name, names_seen)
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
        mesh_path = _resolve_mesh(mesh_ref, base, oc)
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
    scale, rotate, translate = _parse_transform(oc)
    oc.done()
    return ObjectSpec(name, material, mesh_path, prim, prim_args, scale, rotate, translate, flat, parts,
                      part_materials)


def _parse_texture(t: Mapping, p, model: str, base: Path, where: str) -> TextureSpec:
    """Validate a texture table `{ texture = "file.png" | checker = [a, b], wrap, scale, offset }` for
    parameter declaration `p` (see jaxrt/textures.py for the conventions)."""
    from jaxrt import textures as _tx

    allowed = ("texture", "checker", "wrap", "scale", "offset")
    unknown = [k for k in t if k not in allowed]
    if unknown:
        raise InputError(f"{where}: unknown texture key {unknown[0]!r}; allowed: {', '.join(allowed)}")
    if ("texture" in t) == ("checker" in t):
        raise InputError(f"{where}: a texture table needs exactly one of texture = \"FILE.png|.exr\" "
                         "or checker = [VALUE_A, VALUE_B]")
    wrap = t.get("wrap", "repeat")
    if wrap not in _tx.WRAPS:
        raise InputError(f"{where}: wrap = {wrap!r}; allowed: {', '.join(_tx.WRAPS)}")

    def pair(key, default, positive):
        v = t.get(key, default)
        try:
            a = np.broadcast_to(np.asarray(v, np.float64), (2,))
        except (TypeError, ValueError):
            raise InputError(f"{where}: {key} must be a number or [u, v], got {v!r}") from None
        if not np.all(np.isfinite(a)) or (positive and np.any(a == 0)):
            raise InputError(f"{where}: {key} = {v!r} must be finite{' and non-zero' if positive else ''}")
        return tuple(float(x) for x in a)

    scale, offset = pair("scale", 1.0, True), pair("offset", 0.0, False)
    chans = 3 if p.rgb else 1
    if "checker" in t:
        vals = t["checker"]
        if not isinstance(vals, list) or len(vals) != 2:
            raise InputError(f"{where}: checker must be a list of two values, got {vals!r}")
        texels = []
        for k, v in enumerate(vals):
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
    path = Path(ref) if Path(ref).is_absolute() else base / ref
    texels = _tx.read_image(path, p.rgb, where)
    if not np.all(np.isfinite(texels)):
        raise InputError(f"{where}: {path} contains non-finite values")
    lo, hi = float(texels.min()), float(texels.max())
    if lo < p.lo or hi > p.hi:
        raise InputError(f"{where}: {path} has values in [{lo:g}, {hi:g}], outside the allowed range "
                         f"[{p.lo:g}, {p.hi:g}] of {model}.{p.name}")
    return TextureSpec("image", texels, wrap, scale, offset, str(path))


def _resolve_mesh(ref: str, base: Path, oc: _Checker) -> Path:
    """A registry name (bunny, dragon, ...: found through jaxrt.data) or a path relative to the scene."""
    p = Path(ref)
    if p.suffix == "" and len(p.parts) == 1:
        from jaxrt import data

        try:
            return Path(data.find(ref))
        except (ValueError, FileNotFoundError, KeyError) as e:
            msg = str(e)
        oc.fail("mesh", f"{ref!r}: {msg}")
    full = p if p.is_absolute() else base / p
    if not full.is_file():
        oc.fail("mesh", f"{ref!r}: no such file (looked for {full})")
    return full


# --------------------------------------------------------------------------- build


def _object_meshes(o: ObjectSpec, cache: dict):
    """[(scene-object name, mesh, material name)] for one [[objects]] entry, transformed to world."""
    from jaxrt import mesh as _mesh
    from jaxrt import shapes

    if o.primitive is not None:
        m = shapes.PRIMITIVES[o.primitive](**o.primitive_args, name=o.name)
        pieces = [(o.name, m, o.material)]
    else:
        key = (str(o.mesh), o.flat)
        if key not in cache:
            try:
                cache[key] = _mesh.load(o.mesh, flat=o.flat)
            except InputError:
                raise
            except (ValueError, OSError) as e:
                raise InputError(f"object {o.name!r}: cannot load mesh {o.mesh}: {e}") from None
        m = cache[key]
        names = tuple(m.names)
        unknown = [p for p in (o.parts or ()) if p not in names]
        unknown += [p for p in o.part_materials if p not in names]
        if unknown:
            raise InputError(
                f"object {o.name!r}: {o.mesh.name} has no part {unknown[0]!r}; parts: {', '.join(names)}"
            )
        if o.parts is None and not o.part_materials:
            pieces = [(o.name, m, o.material)]
        else:
            pieces = []
            oid = np.asarray(m.object_id)
            for k, part in enumerate(names):
                if o.parts is not None and part not in o.parts:
                    continue
                f = np.asarray(m.faces)[oid == k]
                sub = _mesh.Mesh.from_arrays(
                    np.asarray(m.vertices), f, normals=np.asarray(m.normals),
                    uvs=None if m.uvs is None else np.asarray(m.uvs), name=part,
                )
                pieces.append((f"{o.name}/{part}", sub, o.part_materials.get(part, o.material)))
    out = []
    for name, m, mat in pieces:
        if o.scale is not None or o.rotate is not None or o.translate is not None:
            m = m.transformed(
                scale=1.0 if o.scale is None else np.asarray(o.scale),
                rotation=(0.0, 0.0, 0.0) if o.rotate is None else o.rotate,
                translation=(0.0, 0.0, 0.0) if o.translate is None else o.translate,
            )
        out.append((name, m, mat))
    return out


def build(spec: SceneSpec) -> Scene:
    """Turn a validated spec into the `Scene` pytree (loads meshes, builds the BVH)."""
    import brdfs
    from jaxrt import bvh
    from jaxrt import mesh as _mesh

    # materials grouped by model, in order of first appearance
    mat_names = tuple(spec.materials)
    models: list[str] = []
    rows: dict[str, list] = {}
    model_id, row, delta = [], [], []
    for n in mat_names:
        ms = spec.materials[n]
        if ms.model not in models:
            models.append(ms.model)
            rows[ms.model] = []
        model_id.append(models.index(ms.model))
        row.append(len(rows[ms.model]))
        rows[ms.model].append(ms.params)
        delta.append(ms.delta)
    tables = tuple(
        {p: jnp.asarray(np.stack([r[p] for r in rows[mname]])) for p in brdfs.get(mname).param_names}
        for mname in models
    )
    from jaxrt import textures as _tx

    texs, bindings = [], []
    for n, mid, r in zip(mat_names, model_id, row):
        for pname, ts in spec.materials[n].textures.items():
            bindings.append((mid, r, pname, len(texs)))
            texs.append(_tx.make(ts.texels, ts.kind, ts.wrap, ts.uv_scale, ts.uv_offset))
    materials = Materials(
        params=tables,
        model_id=jnp.asarray(model_id, jnp.int32),
        row=jnp.asarray(row, jnp.int32),
        delta=jnp.asarray(delta, jnp.float32),
        models=tuple(models),
        names=mat_names,
        textures=tuple(texs),
        bindings=tuple(bindings),
    )

    cache: dict = {}
    if spec.instances:
        from jaxrt import instancing

        geometry = instancing.build_geometry(spec, mat_names, cache)
    else:
        meshes, obj_names, face_mat, face_obj = [], [], [], []
        for o in spec.objects:
            for name, m, mat in _object_meshes(o, cache):
                nf = int(np.asarray(m.faces).shape[0])
                face_mat.append(np.full(nf, mat_names.index(mat), np.int32))
                face_obj.append(np.full(nf, len(obj_names), np.int32))
                obj_names.append(name)
                meshes.append(m)
        whole = _mesh.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        verts = np.asarray(whole.vertices, np.float32)
        faces = np.asarray(whole.faces, np.int32)
        if not np.all(np.isfinite(verts)):
            raise InputError(f"{spec.source}: scene geometry contains non-finite vertices")
        tree = bvh.build(verts, faces, **bvh.RENDER_TREE)
        geometry = Geometry(
            vertices=jnp.asarray(verts),
            normals=jnp.asarray(np.asarray(whole.normals, np.float32)),
            tangents=jnp.asarray(np.asarray(whole.tangents, np.float32)),
            faces=jnp.asarray(faces),
            material=jnp.asarray(np.concatenate(face_mat)),
            object_id=jnp.asarray(np.concatenate(face_obj)),
            tree=tree,
            object_names=tuple(obj_names),
            # mesh.concatenate drops UVs unless every mesh has them: keep them, zeros where a mesh has none
            uvs=jnp.asarray(np.concatenate([np.zeros((m.num_vertices, 2), np.float32) if m.uvs is None
                                            else np.asarray(m.uvs, np.float32) for m in meshes])),
        )

    lights = PointLights(
        position=jnp.asarray(np.reshape([l[0] for l in spec.lights], (-1, 3)), jnp.float32),
        intensity=jnp.asarray(np.reshape([l[1] for l in spec.lights], (-1, 3)), jnp.float32),
    )
    emission = np.asarray([spec.materials[n].emission for n in mat_names], np.float32).reshape(-1, 3)
    if spec.instances:
        emitting = [n for n in mat_names if max(spec.materials[n].emission) > 0]
        if emitting:
            raise InputError(f"{spec.source}: materials.{emitting[0]}.emission: emissive materials are not "
                             "supported in scenes with [[instances]] yet; use plain [[objects]] for lights")
        fmat = np.zeros(0, np.int32)
    else:
        fmat = np.concatenate(face_mat)
    area_lights = AreaLights(
        emission=jnp.asarray(emission),
        prims=jnp.asarray(np.nonzero(emission.max(axis=1)[fmat] > 0)[0].astype(np.int32)),
    )
    environment = None
    if spec.environment is not None:
        from jaxrt import envmap

        e = spec.environment
        if e.file is None:
            environment = envmap.constant(np.asarray(e.radiance) * e.scale)
        else:
            environment = envmap.load(e.file, scale=e.scale, rotate=e.rotate)
    c = spec.camera
    camera = Camera(
        position=jnp.asarray(c.position, jnp.float32), look_at=jnp.asarray(c.look_at, jnp.float32),
        up=jnp.asarray(c.up, jnp.float32), vfov=jnp.asarray(c.vfov, jnp.float32),
        aperture=jnp.asarray(c.aperture, jnp.float32), focus_distance=jnp.asarray(c.focus_distance, jnp.float32),
        width=c.width, height=c.height,
    )
    r = spec.render
    has_glass = any(brdfs.get(m).delta for m in models)
    settings = Settings(
        background=jnp.asarray(r.background, jnp.float32),
        seed=jnp.asarray(r.seed, jnp.int32),
        integrator=r.integrator,
        max_depth=r.max_depth,
        spp=r.spp,
        ray_budget=r.ray_budget if r.ray_budget is not None else (2 if has_glass else 1),
    )
    return Scene(geometry, materials, lights, camera, settings, source=spec.source, area_lights=area_lights,
                 environment=environment)


def load(
    source: str | os.PathLike | Mapping, base_dir: str | os.PathLike | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> Scene:
    """Validate then build a scene.

    Args:
        source: a TOML path, a shipped scene name (`spheres`), or an already-parsed dict.
        base_dir: directory that relative mesh paths are resolved against (default: the file's).
        overrides: {"camera.width": 64, "render.spp": 4, ...} applied before validation.
    Raises:
        InputError: one line naming file, table and key, and what is allowed.
    """
    if not isinstance(source, Mapping):
        source = find_scene(source)
    return build(parse(source, base_dir=base_dir, overrides=overrides))
