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
sweep (parameter sweeps), viewer, fsutil, errors, serve (the resident worker behind `jaxrt serve`).

Names are imported on first use: `import jaxrt` loads no JAX; the first JAX-using module turns
JAX's persistent compilation cache on (`jaxrt.cache`) before it loads.
"""

from __future__ import annotations

import importlib
import sys
import threading

from brdfs import lazy as _lazy
from jaxrt.errors import InputError

__version__ = "0.1.0"

__all__ = [
    "InputError", "Scene", "accel", "cache", "frame", "gbuffer", "geometry", "glare", "integrators", "join_hosts",
    "load_scene", "render", "render_tiles", "reshade", "scene", "shade", "shading", "trace",
]

# `import jaxrt` loads neither JAX nor the renderer (JAX alone takes 1.5-2 s of CPU on a small
# machine, and the `jaxrt` command parses its arguments, or hands them to a resident worker, without
# it): each public name is imported on first use (PEP 562), as scipy and numpy do for their
# subpackages. public name -> (module, attribute; None for the module itself)
_LAZY: dict[str, tuple[str, str | None]] = {
    "accel": ("jaxrt.accel", None), "cache": ("jaxrt.cache", None), "geometry": ("jaxrt.geometry", None),
    "glare": ("jaxrt.glare", None), "integrators": ("jaxrt.integrators", None),
    "render_tiles": ("jaxrt.render_tiles", None), "scene": ("jaxrt.scene", None),
    "shading": ("jaxrt.shading", None),
    "join_hosts": ("jaxrt._devices", "initialize"),
    "gbuffer": ("jaxrt.api", "gbuffer"), "render": ("jaxrt.api", "render"), "reshade": ("jaxrt.api", "reshade"),
    "frame": ("jaxrt.integrators", "frame"), "shade": ("jaxrt.integrators", "shade"),
    "trace": ("jaxrt.integrators", "trace"),
    "Scene": ("jaxrt.scene", "Scene"), "load_scene": ("jaxrt.scene", "load"),
}


def __getattr__(name: str):
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = importlib.import_module(module)
        if attr is not None:
            value = getattr(value, attr)
        globals()[name] = value  # later look-ups skip this function
        return value
    # any other name: a submodule (`jaxrt.image`, `jaxrt.sweep`, ..., as `import jaxrt` used to leave them bound)
    return _lazy.submodule(__name__, __file__, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


# Modules of this package that import neither JAX nor a module that does: the command line's
# argument parsing and its client of the resident worker (`jaxrt.serve`), the configuration, errors
# and the cache's housekeeping (`jaxrt cache info|clear`).
_WITHOUT_JAX = frozenset({"jaxrt._config", "jaxrt.errors", "jaxrt.cache", "jaxrt.fsutil", "jaxrt.serve",
                          "jaxrt.cli", "jaxrt.cli.__main__", "jaxrt.cli.cache", "jaxrt.cli.serve"})


class _CompilationCacheFirst:
    """Turns on the persistent compilation cache (`jaxrt.cache.enable_compilation_cache`) just before
    the first JAX-using module of this package is imported, whoever imports it (the CLI, a script,
    a notebook, `fitting`), so that no compilation of jaxrt's runs before the cache is on.

    It sits at the front of `sys.meta_path` and finds nothing itself (every import continues to the
    usual finders); after its one call it only compares a name. It stays in the list because a
    finder that removed itself while the import system iterates the list would make it skip the next one.
    """

    def __init__(self):
        self.done = False
        self._lock = threading.Lock()

    def find_spec(self, name, path=None, target=None):
        if self.done or not name.startswith("jaxrt.") or name in _WITHOUT_JAX:
            return None
        with self._lock:
            if self.done:
                return None
            self.done = True
        from jaxrt import _config, cache

        _config.apply_runtime_defaults()

        try:
            cache.enable_compilation_cache()
        except InputError:
            pass  # a bad JAXRT_CACHE* value: the command's first configuration read reports it in one line
        return None

    def invalidate_caches(self):
        pass


# Compiled programs are kept across processes (JAX's persistent compilation cache) unless
# JAXRT_CACHE=off; `jaxrt.cache` says where and how to clear it. A module that JAX-using code
# imported before this package (jax itself, brdfs) compiles nothing on import.
if not any(type(f).__name__ == _CompilationCacheFirst.__name__ for f in sys.meta_path):
    sys.meta_path.insert(0, _CompilationCacheFirst())
