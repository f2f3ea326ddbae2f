"""The one place that edits which material an object wears, and what a material row holds.

Sweeps, the viewer and fitting all give one object of a scene a material of their own:
`wear` does it on a validated spec (before building), `material_spec` makes that material from a
model and parameter values (validated against the model's `Param` declarations), and
`set_material_row` replaces the parameters of one material row of a built `Scene` (a value
change: never recompiles; used inside fits, where the values are traced).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import brdfs
from brdfs.base import Model
from jaxrt.errors import InputError
from jaxrt.scene.spec import DELTA, MaterialSpec, ObjectSpec, SceneSpec
from jaxrt.scene.types import Scene


def find_object(spec: SceneSpec, name: str | None, *, skip_planes: bool = False) -> ObjectSpec:
    """The [[objects]] entry called `name`; None picks the first object (the first that is not a
    plane with skip_planes). Objects placed by [[instances]] are not addressable here."""
    names = [o.name for o in spec.objects]
    if not names:
        raise InputError(f"{spec.source}: sweeps and fits address [[objects]] only; this scene has none")
    if name is None:
        return next((o for o in spec.objects if o.primitive != "plane"), spec.objects[0]) if skip_planes \
            else spec.objects[0]
    if name not in names:
        raise InputError(f"{spec.source}: no object named {name!r}; objects: {', '.join(names)}")
    return spec.objects[names.index(name)]


def material_spec(name: str, model: str | Model, values: Mapping[str, Any] | None = None, *,
                  where: str = "") -> MaterialSpec:
    """A validated material `name` of `model`: `values` (parameter name -> value, and "delta") over
    the model's defaults. Raises InputError naming the parameter and what is allowed."""
    m = brdfs.get(model) if isinstance(model, str) else model
    values = dict(values or {})
    delta = values.pop("delta", DELTA.default)
    prefix = f"{where}: " if where else ""
    for k in values:
        if k not in m.param_names:
            allowed = m.param_names + (() if m.delta else ("delta",))
            raise InputError(f"{prefix}{m.name}: unknown parameter {k!r}; allowed: {', '.join(allowed)}")
    if m.delta and delta:
        raise InputError(f"{prefix}delta is not a parameter of the delta BSDF {m.name}")
    params = {p.name: np.asarray(p.check(values.get(p.name, p.default), m.name)) for p in m.spec}
    return MaterialSpec(name, m.name, params, 0.0 if m.delta else float(DELTA.check(delta, m.name)))


def wear(spec: SceneSpec, obj: str, material: MaterialSpec, *,
         extra: Mapping[str, MaterialSpec] | None = None) -> SceneSpec:
    """A copy of `spec` in which object `obj` wears `material` (added to the materials, replacing a
    material of the same name); `extra` materials are added too (e.g. one per model, so that the
    built scene can switch models by a value change: `Scene.geometry.with_object_material`)."""
    find_object(spec, obj)
    materials = dict(spec.materials)
    materials.update(extra or {})
    materials[material.name] = material
    objects = tuple(dataclasses.replace(o, material=material.name) if o.name == obj else o for o in spec.objects)
    return dataclasses.replace(spec, materials=materials, objects=objects)


def set_material_row(scene: Scene, model_index: int, row: int, params: Mapping[str, Array]) -> Scene:
    """A copy of `scene` whose material table `model_index`, row `row`, holds `params` (not
    range-checked: values may be traced, e.g. a solver's iterates)."""
    tables = scene.materials.params
    table = {k: v.at[row].set(jnp.asarray(params[k], v.dtype)) for k, v in tables[model_index].items()}
    new = tuple(table if j == model_index else t for j, t in enumerate(tables))
    return eqx.tree_at(lambda s: s.materials.params, scene, new)


def wear_material(scene: Scene, obj: str, material: str) -> Scene:
    """A copy of a built `scene` in which object `obj` wears the material called `material` (a value
    change of the geometry's per-object material ids: never recompiles)."""
    g = scene.geometry
    geometry = g.with_object_material(g.object_index(obj), scene.materials.index(material))
    return eqx.tree_at(lambda s: s.geometry, scene, geometry)
