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

from jaxrt.scene import edit
from jaxrt.scene.build import build, load, object_meshes
from jaxrt.scene.parse import MAX_RESOLUTION, SCENES_DIR, find_scene, parse
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
from jaxrt.scene.tables import Table
from jaxrt.scene.types import Materials, Scene, Settings, device_bytes

__all__ = [
    "DELTA", "FRESNEL", "GLASS_SHADOWS", "MAX_RESOLUTION", "SCENES_DIR", "CameraSpec", "EnvironmentSpec", "GroupSpec", "InstanceSpec",
    "MaterialSpec", "Materials", "ObjectSpec", "RenderSpec", "Scene", "SceneSpec", "Settings", "Table",
    "TextureSpec", "build", "device_bytes", "edit", "find_scene", "load", "object_meshes", "parse",
]
