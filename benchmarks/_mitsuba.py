"""What the benchmarks that time Mitsuba 3 beside jaxrt share: finding a libLLVM that Mitsuba's
`llvm_ad_rgb` variant can use, and the direct-lighting scene of a jaxrt scene.

libLLVM: Dr.Jit's LLVM back end loads a system libLLVM at run time (`DRJIT_LIBLLVM_PATH`, else its
own search). Debian 12's default libLLVM 15 aborts on Mitsuba's path integrator ("Cannot select:
f32 = fminimum"); LLVM 19 (`apt-get install libllvm19`) runs it. `use_libllvm()` keeps a
`DRJIT_LIBLLVM_PATH` that is already set, else points it at the newest libLLVM found in the usual
library folders; it must run before `import mitsuba` (child processes inherit the variable).
"""

from __future__ import annotations

import glob
import os
import re

LIBLLVM_ENV = "DRJIT_LIBLLVM_PATH"
_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib", "/usr/local/lib",
             "/usr/lib/llvm-*/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib")


def _llvm_version(path: str) -> tuple[int, ...]:
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+(?:\.\d+)*)", os.path.basename(path))
    if m is None:  # /usr/lib/llvm-19/lib/libLLVM.so: the version is in the folder
        m = re.search(r"llvm-(\d+)", path)
    return tuple(int(x) for x in m.group(1).split(".")) if m else ()


def use_libllvm() -> str | None:
    """The libLLVM Dr.Jit will load: `$DRJIT_LIBLLVM_PATH` if set, else the newest one found (then
    exported for this process and its children); None if none is found (Dr.Jit then searches itself)."""
    if os.environ.get(LIBLLVM_ENV):
        return os.environ[LIBLLVM_ENV]
    found = [p for d in _LIB_DIRS for p in glob.glob(os.path.join(d, "libLLVM*.so*")) + glob.glob(
        os.path.join(d, "libLLVM*.dylib")) if os.path.isfile(p) and _llvm_version(p)]
    if not found:
        return None
    best = max(found, key=_llvm_version)
    os.environ[LIBLLVM_ENV] = best
    return best


def direct_scene(mi, vertices, faces, cam, light_position, light_intensity, size: int):
    """Mitsuba's direct integrator on the given world-space triangles (one diffuse BSDF of default
    reflectance 0.5), a point light, the jaxrt camera, 1 spp with a box filter: one camera ray and
    one shadow ray per pixel (`bsdf_samples` 0), the workload of a jaxrt Whitted frame of Lambert
    surfaces at max_depth 1."""
    import tempfile

    import numpy as np
    import trimesh

    T = mi.ScalarTransform4f
    with tempfile.TemporaryDirectory() as d:
        ply = os.path.join(d, "mesh.ply")
        trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False).export(ply)
        return mi.load_dict({
            "type": "scene",
            "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
            "sensor": {
                "type": "perspective", "fov": float(cam.vfov), "fov_axis": "y",
                "to_world": T().look_at(origin=np.asarray(cam.position).tolist(),
                                        target=np.asarray(cam.look_at).tolist(), up=np.asarray(cam.up).tolist()),
                "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": 1},
            },
            "light": {"type": "point", "position": np.asarray(light_position).tolist(),
                      "intensity": {"type": "rgb", "value": np.asarray(light_intensity).tolist()}},
            "mesh": {"type": "ply", "filename": ply, "face_normals": True, "bsdf": {"type": "diffuse"}},
        })
