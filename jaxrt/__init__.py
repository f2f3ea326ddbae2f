"""jaxrt: a JAX array ray tracer for analysing and fitting BRDFs.

    import jaxrt
    img = jaxrt.render("spheres")                       # (H, W, 3) linear radiance
    sc = jaxrt.load_scene("bunny", overrides={"camera.width": 128})
    img, aovs = jaxrt.frame(sc, aovs=True)              # the compiled frame of a built Scene
    jaxrt.join_hosts()                                  # several hosts: JAXRT_COORDINATOR & co., first

Packages (docs/ARCHITECTURE.md has the layout and data flow):
  scene        scene files -> validated spec -> `Scene` pytree; the one place that edits materials
  geometry     the abstract geometry interface; triangle and instanced geometry; meshes, primitives
  accel        BVH builders and traversal back ends (XLA loop, Pallas GPU kernel, native CPU kernel)
  shading      surfaces and frames, material gathering (textures), direct lighting, AOVs
  integrators  Whitted and path tracing behind one registry; the compiled `frame`
  cli          the `jaxrt` command, one module per subcommand
Modules: camera, lights, envmap, image (EXR/PNG), render_tiles (rendering within a memory budget),
glare (the aperture's diffraction glare, a post-process of the image),
sweep (parameter sweeps), viewer, fsutil, errors.
"""

from jaxrt import accel, cache, geometry, glare, integrators, render_tiles, scene, shading
from jaxrt._devices import initialize as join_hosts
from jaxrt.api import gbuffer, render, reshade
from jaxrt.errors import InputError
from jaxrt.integrators import frame, shade, trace
from jaxrt.scene import Scene
from jaxrt.scene import load as load_scene

__version__ = "0.1.0"

# Compiled programs are kept across processes (JAX's persistent compilation cache) unless
# JAXRT_CACHE=off; `jaxrt.cache` says where and how to clear it.
cache.enable_compilation_cache()

__all__ = [
    "InputError", "Scene", "accel", "cache", "frame", "gbuffer", "geometry", "glare", "integrators", "join_hosts",
    "load_scene", "render", "render_tiles", "reshade", "scene", "shade", "shading", "trace",
]
