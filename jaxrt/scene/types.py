"""The `Scene` pytree and its parts, with validated value updates (`with_*`).

In a `Scene` every value (vertices, material parameters, lights, camera, background) is a traced
array; only shapes and the set of models are static, so changing a parameter, a light or the camera
never recompiles the renderer.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import brdfs
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrt import glare as _glare
from jaxrt.camera import Camera
from jaxrt.errors import InputError
from jaxrt.geometry.base import AbstractGeometry
from jaxrt.lights import AreaLights, PointLights
from jaxrt.scene.spec import DELTA
from jaxrt.scene.tables import MAX_APERTURE_RATIO, MIN_FOCUS_DISTANCE, check_range, check_rgb, check_vec3


class Materials(eqx.Module):
    """Materials grouped by model so per-pixel model selection is a gather plus a select.

    Attributes:
        params: one stacked parameter table per model in `models`; table k maps each parameter
            name to an array with one row per material of that model ((rows, 3) RGB, (rows,) scalar).
        model_id: (M,) index into `models` for each material.
        row: (M,) row of each material in its model's table.
        delta: (M,) the mirror reflection coefficient δ in [0, 1] (`jaxrt.scene.DELTA`; 0 for glass).
        models: static tuple of `brdfs` model names used by the scene.
        names: static tuple of material names (scene-file keys), index = material id.
        fresnel: static tuple, per material, of its Fresnel choice (`jaxrt.scene.FRESNEL`;
            "" for opaque materials); () means Schlick everywhere.
            Static because it selects code (`brdfs.glass.fresnel`'s `exact`), not values.
    """

    params: tuple[dict, ...]
    model_id: Int[Array, "M"]
    row: Int[Array, "M"]
    delta: Float[Array, "M"]
    models: tuple[str, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    # Textured parameters (jaxrt.shading.textures): the texel values are traced, which parameter of which
    # material row uses which texture is static: bindings[j] = (model index, row, param, texture index).
    textures: tuple = ()
    bindings: tuple[tuple[int, int, str, int], ...] = eqx.field(static=True, default=())
    fresnel: tuple[str, ...] = eqx.field(static=True, default=())

    def index(self, name: str) -> int:
        if name not in self.names:
            raise InputError(f"unknown material {name!r}; the scene defines: {', '.join(self.names)}")
        return self.names.index(name)



class Settings(eqx.Module):
    """Render settings. background: (3,) linear RGB radiance of rays that escape; seed: () int."""

    background: Float[Array, "3"]
    seed: Int[Array, ""]
    integrator: str = eqx.field(static=True)
    max_depth: int = eqx.field(static=True)
    spp: int = eqx.field(static=True)
    ray_budget: int = eqx.field(static=True)
    # Whitted shadow rays through glass (`jaxrt.shading.shadows`): "transmit" or "opaque"
    glass_shadows: str = eqx.field(static=True, default="transmit")
    # stochastic progressive photon mapping (`jaxrt.integrators.sppm`): photons per pass and the
    # initial gather radius, 0 for the integrator's defaults (derived from the resolution and scene size)
    photons: int = eqx.field(static=True, default=0)
    radius: float = eqx.field(static=True, default=0.0)
    # visible points per pixel per pass (0: the integrator's default)
    camera_samples: int = eqx.field(static=True, default=0)
    # levels of the photon hash grid (0: the integrator's default for the JAX backend)
    grid_levels: int = eqx.field(static=True, default=0)
    # the fraction of photons aimed at the glass and mirror objects (`jaxrt.integrators.sppm`), in
    # [0, 1); 0 turns aiming off (the photon pass is then the unaimed one, bit for bit)
    photon_aim: float = eqx.field(static=True, default=0.0)
    # SPPM's radius reduction α in (0, 1) (0: the integrator's default, `jaxrt.integrators.sppm.ALPHA`)
    alpha: float = eqx.field(static=True, default=0.0)



class Scene(eqx.Module):
    geometry: AbstractGeometry
    materials: Materials
    lights: PointLights
    camera: Camera
    settings: Settings
    source: str = eqx.field(static=True, default="<scene>")
    # emissive materials/triangles and the environment (None: no environment); used by the path
    # tracer, and Whitted's escaping rays see the environment instead of `background`
    area_lights: AreaLights | None = None
    environment: Any = None
    # glare (`jaxrt.glare.Glare`, None: off): a post-process of the finished image that
    # `jaxrt.render` and `jaxrt.render_tiles.render` apply; the compiled render programs see the scene
    # without it (`without_glare`), so glare settings never recompile the renderer
    glare: Any = eqx.field(static=True, default=None)

    # ---- value updates (validated, never recompile) ----
    def with_glare(self, glare: "_glare.Glare | None") -> "Scene":
        """A copy with glare settings (a `jaxrt.glare.Glare`, or None: off). Static: the renderer's
        programs do not depend on it (see `without_glare`); the glare program compiles per setting."""
        if glare is not None and not isinstance(glare, _glare.Glare):
            raise InputError(f"glare: expected a jaxrt.glare.Glare or None, got {type(glare).__name__}")
        return dataclasses.replace(self, glare=glare)

    def without_glare(self) -> "Scene":
        """The scene the renderer's compiled programs take: the same, with glare off."""
        return self if self.glare is None else dataclasses.replace(self, glare=None)

    def with_material(self, name: str, **values) -> "Scene":
        """A copy with material `name`'s parameters (or `delta`) changed; bounds-checked."""
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
                delta = delta.at[i].set(check_range(v, DELTA.lo, DELTA.hi, f"material {name!r}: delta"))
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
        """A copy with point light `index` (0 .. count − 1) moved and/or re-scaled."""
        lights = self.lights
        count = lights.count
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < count:
            allowed = f"0..{count - 1}" if count else "none: the scene has no point lights"
            raise InputError(f"light {index!r}: no such point light; allowed indices: {allowed}")
        pos, inten = lights.position, lights.intensity
        if position is not None:
            pos = pos.at[index].set(check_vec3(position, f"light {index}: position"))
        if intensity is not None:
            inten = inten.at[index].set(check_rgb(intensity, f"light {index}: intensity", lo=0.0))
        return eqx.tree_at(lambda s: (s.lights.position, s.lights.intensity), self, (pos, inten))

    def with_camera(self, **values) -> "Scene":
        """A copy with camera values (position, look_at, up, vfov, aperture, focus_distance) changed."""
        cam = self.camera
        names = ("position", "look_at", "up", "vfov", "aperture", "focus_distance")
        for k in values:
            if k not in names:
                raise InputError(f"camera: unknown key {k!r}; allowed: {', '.join(names)}")
        # the ranges of the scene file's [camera] table (jaxrt.scene.parse); traced values (inside
        # jax.grad) are not checked
        checked = {}
        for k, v in values.items():
            if isinstance(v, jax.core.Tracer):
                checked[k] = v
            elif k in ("position", "look_at", "up"):
                checked[k] = check_vec3(v, f"camera: {k}")
            elif k == "vfov":
                checked[k] = check_range(v, 1e-6, 180.0 - 1e-6, "camera: vfov (degrees, open interval (0, 180))")
            elif k == "focus_distance":
                checked[k] = check_range(v, MIN_FOCUS_DISTANCE, math.inf, "camera: focus_distance")
        pos, look, up = (np.asarray(checked.get(k, getattr(cam, k))) for k in ("position", "look_at", "up"))
        if "aperture" in values and not isinstance(values["aperture"], jax.core.Tracer):
            focus = float(np.asarray(checked.get("focus_distance", cam.focus_distance)))
            checked["aperture"] = check_range(values["aperture"], 0.0, MAX_APERTURE_RATIO * focus,
                                              f"camera: aperture (at most {MAX_APERTURE_RATIO:g} x focus_distance)")
        if not any(isinstance(x, jax.core.Tracer) for x in checked.values()):
            view = (look - pos).astype(np.float32)
            if not np.any(view):
                raise InputError(f"camera: look_at {look.tolist()} must differ from position {pos.tolist()}")
            if np.linalg.norm(np.cross(view / np.linalg.norm(view), up)) <= 1e-6 * np.linalg.norm(up):
                raise InputError(f"camera: up {up.tolist()} must not be zero or parallel to the view direction")
        new = [jnp.asarray(checked.get(k, getattr(cam, k)), jnp.float32) for k in names]
        return eqx.tree_at(lambda s: tuple(getattr(s.camera, k) for k in names), self, tuple(new))


def device_bytes(tree_like) -> int:
    """Total bytes of the array leaves of a pytree (e.g. a Scene)."""
    return int(sum(x.nbytes for x in jax.tree.leaves(tree_like) if hasattr(x, "nbytes")))
