"""Validated scene specification: plain, frozen Python records between parsing and building.

`jaxrt.scene.parse` produces a `SceneSpec`; `jaxrt.scene.build` turns it into the `Scene` pytree.
Nothing here touches JAX, so a spec can be checked, edited (`jaxrt.scene.edit`) and compared cheaply.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from brdfs.base import Param

# The mirror reflection coefficient δ of an opaque material (Größler & Zettwitz, "An interactive ray
# tracing system based on Nvidia OptiX", 2015): L = δ·L(x, ω_r) + (1 − δ)·direct. Not a BRDF
# parameter, but declared like one so that scene files, sweeps, sliders and fits read one range.
DELTA = Param("delta", 0.0, 0.0, 1.0, doc="mirror reflection coefficient δ: L = δ·L(ω_r) + (1 − δ)·direct")


# Fresnel reflectance choices of a glass material (`fresnel = ...` in its scene-file table), default
# first: Schlick's approximation keeps the images of scenes written before the key existed unchanged.
FRESNEL = ("schlick", "exact")
# Whitted shadow rays through glass (`[render] glass_shadows`), default first: "transmit" carries the
# Fresnel transmittance of the glass crossed (it cannot change scenes without glass), "opaque" blocks.
GLASS_SHADOWS = ("transmit", "opaque")


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
    # a measured material (model "nbrdf" or "merl"): the scene's `data` reference (a material name
    # or the resolved file), and `params` holds its raw data (brdfs.measured.read)
    data: str | None = None
    # a glass material's Fresnel reflectance (`FRESNEL`): "schlick" (Schlick 1994, the default and
    # the only choice before scene files could choose) or "exact" (the dielectric Fresnel equations)
    fresnel: str = "schlick"



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
    glass_shadows: str = "transmit"  # GLASS_SHADOWS
    photons: int = 0  # SPPM photons per pass (0: the integrator's default)
    radius: float = 0.0  # SPPM initial gather radius (0: the integrator's default)
    camera_samples: int = 0  # SPPM visible points per pixel per pass (0: the integrator's default)
    grid_levels: int = 0  # SPPM hash-grid levels (0: the integrator's default for the backend)
    photon_aim: float | None = None  # SPPM fraction of photons aimed at delta objects (None: default)
    alpha: float = 0.0  # SPPM radius reduction α (0: the integrator's default)



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
    groups: tuple = ()  # jaxrt.geometry.instanced.GroupSpec
    instances: tuple = ()  # jaxrt.geometry.instanced.InstanceSpec
    environment: EnvironmentSpec | None = None
    # the [glare] table (`jaxrt.glare.Glare`: diffraction by the aperture, a post-process of the
    # image); None when the scene has none (off, the default)
    glare: Any = None


@dataclasses.dataclass(frozen=True)
class GroupSpec:
    name: str
    objects: tuple  # scene.ObjectSpec, in group space



@dataclasses.dataclass(frozen=True)
class InstanceSpec:
    name: str
    group: str
    scale: Any  # (3,) or None
    rotate: tuple | None  # XYZ degrees
    translate: tuple | None
    material: str | None  # override of every object's material in the group
