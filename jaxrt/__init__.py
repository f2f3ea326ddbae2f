"""jaxrt: a JAX array ray tracer for analysing and fitting BRDFs.

Submodules (imported on demand so `import jaxrt` stays cheap and does not import JAX):
  mesh, data, bvh        geometry: mesh loading, the data registry, BVH build and traversal
  instancing, bvh_instanced  object groups placed as instances; the two-level BVH
  scene, camera, lights  scene description
  integrators, image     rendering and image I/O
  render                 `jaxrt.render(scene)` -> (H, W, 3) linear image

`jaxrt.render(scene, aovs=False)` and `jaxrt.load_scene(path)` are available at the top level.
"""

import importlib

__version__ = "0.1.0"

_SUBMODULES = frozenset(
    {"mesh", "data", "bvh", "scene", "camera", "lights", "integrators", "image", "shapes", "cli", "errors", "fsutil",
     "instancing", "bvh_instanced"}
)


def __getattr__(name: str):
    # `render` is the function, not the module, at the top level
    if name == "render":
        return importlib.import_module("jaxrt.render").render
    if name == "load_scene":
        return importlib.import_module("jaxrt.scene").load
    if name in _SUBMODULES:
        return importlib.import_module(f"jaxrt.{name}")
    raise AttributeError(f"module 'jaxrt' has no attribute {name!r}")
