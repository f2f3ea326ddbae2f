"""Pack Mitsuba 3 and Dr.Jit for a machine that cannot install them, small enough to travel with a
checkout (a GPU benchmark machine without a package index): one `.tar.xz` of the two wheels' files
that the benchmarks' scenes need, to be unpacked onto the Python path there.

Mitsuba's wheel (62 MB compressed) holds every variant's extension module and ~100 plugins, each
plugin built for every variant; the benchmarks (`benchmarks/peers.py`, `benchmarks/path.py`,
`benchmarks/_mitsuba.py`) use one or two variants and the plugins listed in `PLUGINS`. The archive
keeps the shared libraries, the Python package, the chosen variants' modules and those plugins.

    python benchmarks/mitsuba_carry.py --wheels DIR --out .mitsuba/mitsuba.tar.xz --variants cuda_ad_rgb
    # on the other machine:
    mkdir -p /tmp/site && tar xJf .mitsuba/mitsuba.tar.xz -C /tmp/site && export PYTHONPATH=/tmp/site:$PYTHONPATH

DIR holds `mitsuba-*.whl` and `drjit-*.whl` for that machine's Python (`pip download --no-deps
--only-binary=:all: --python-version 3.12 ... mitsuba==3.9.1 drjit==1.5.0`). `--check` imports the
unpacked copy in a child process and renders a small scene with each variant that can run here.
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path

# The plugins the benchmarks' scenes load (listed from /proc/self/maps after `benchmarks/peers.py
# --rows direct rays path` with the whole wheel: the named types and those Mitsuba adds itself, such
# as the shape merger, the sampler, the film's colour space, the D65 and uniform spectra), with a few
# a small variation of those scenes needs (other shapes, glass, a constant environment, a bitmap, the
# Gaussian filter). One list: add a name here when a benchmark scene uses a new type.
PLUGINS = ("area", "bitmap", "box", "constant", "cube", "d65", "dielectric", "diffuse", "direct", "envmap",
           "gaussian", "hdrfilm", "independent", "merge", "obj", "path", "perspective", "ply", "point",
           "rectangle", "regular", "roughconductor", "roughplastic", "sphere", "srgb", "twosided", "uniform")

# What the rgb variants do not read at run time: headers, build files, typing stubs, the spectral
# upsampling table and the sky model's data (spectral variants and the sunsky emitter only).
_SKIP_PREFIXES = ("mitsuba/include/", "mitsuba/cmake/", "mitsuba/pkgconfig/", "mitsuba/mitsuba_stubs/",
                  "mitsuba/data/srgb.coeff", "mitsuba/data/sunsky/",
                  "drjit/include/", "drjit/cmake/", "drjit/stubs/")
_SKIP_SUFFIXES = (".pyi",)
_VARIANT_PREFIXES = ("scalar_", "llvm_", "cuda_")


def _keep(name: str, variants: tuple[str, ...]) -> bool:
    if name.startswith(_SKIP_PREFIXES) or name.endswith(_SKIP_SUFFIXES) or ".dist-info/" in name:
        return False
    base = name.rsplit("/", 1)[-1]
    if name.startswith("mitsuba/plugins/"):
        return base.split(".")[0] in PLUGINS
    if name.startswith("mitsuba/") and name.count("/") == 1 and base.startswith(_VARIANT_PREFIXES):
        return base.split(".")[0] in variants  # a variant's extension module
    return True


def pack(wheels: Path, out: Path, variants: tuple[str, ...]) -> tuple[int, int]:
    """Write the archive; returns (files, bytes unpacked)."""
    found = {n: sorted(wheels.glob(f"{n}-*.whl")) for n in ("mitsuba", "drjit")}
    for n, ws in found.items():
        if len(ws) != 1:
            raise SystemExit(f"{wheels}: expected one {n}-*.whl, found {len(ws)}")
    out.parent.mkdir(parents=True, exist_ok=True)
    files = size = 0
    with tempfile.NamedTemporaryFile(dir=out.parent, prefix=out.name + ".", delete=False) as tmp:
        with tarfile.open(fileobj=tmp, mode="w:xz", preset=6) as tar:
            for w in (found["mitsuba"][0], found["drjit"][0]):
                with zipfile.ZipFile(w) as z:
                    for info in z.infolist():
                        if info.is_dir() or not _keep(info.filename, variants):
                            continue
                        data = z.read(info)
                        ti = tarfile.TarInfo(info.filename)
                        ti.size = len(data)
                        ti.mode = 0o755 if info.filename.endswith(".so") else 0o644
                        tar.addfile(ti, io.BytesIO(data))
                        files, size = files + 1, size + len(data)
    os.chmod(tmp.name, 0o644)
    Path(tmp.name).replace(out)  # all or nothing
    return files, size


_CHECK = r"""
import sys
import mitsuba as mi
assert mi.__file__.startswith(sys.argv[1]), mi.__file__
mi.set_variant(sys.argv[2])
scene = mi.load_dict({
    "type": "scene", "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 16, "height": 16,
               "rfilter": {"type": "box"}}, "sampler": {"type": "independent", "sample_count": 4}},
    "light": {"type": "point", "position": [0, 0, 2], "intensity": {"type": "rgb", "value": [4, 4, 4]}},
    "env": {"type": "constant"},
    "floor": {"type": "rectangle", "bsdf": {"type": "roughplastic"}},
    "box": {"type": "cube", "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
    "ball": {"type": "sphere", "bsdf": {"type": "dielectric"}},
})
img = mi.render(scene)
print(sys.argv[2], "ok", float(mi.TensorXf(img).numpy().mean()))
"""


def check(archive: Path, variants: tuple[str, ...]) -> int:
    """Unpack into a temporary folder and render a small scene with each variant in a child process."""
    with tempfile.TemporaryDirectory() as d:
        with tarfile.open(archive) as tar:
            tar.extractall(d, filter="data")
        bad = 0
        for v in variants:
            env = {"PYTHONPATH": d, "PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": d}
            if os.environ.get("DRJIT_LIBLLVM_PATH"):
                env["DRJIT_LIBLLVM_PATH"] = os.environ["DRJIT_LIBLLVM_PATH"]
            r = subprocess.run([sys.executable, "-c", _CHECK, d, v], env=env,
                               capture_output=True, text=True, check=False)
            print(r.stdout.strip() or f"{v}: failed\n{r.stderr[-2000:]}")
            bad += r.returncode != 0
        return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--wheels", type=Path, required=True, help="folder with one mitsuba-*.whl and one drjit-*.whl")
    ap.add_argument("--out", type=Path, required=True, help="the .tar.xz to write")
    ap.add_argument("--variants", nargs="+", default=["cuda_ad_rgb"], help="variants to keep (default cuda_ad_rgb)")
    ap.add_argument("--check", nargs="*", metavar="VARIANT",
                    help="after packing, render a small scene with these variants (they must run here)")
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import _mitsuba

    _mitsuba.use_libllvm()  # Debian's default libLLVM aborts on the path integrator (see _mitsuba)
    files, size = pack(args.wheels, args.out, tuple(args.variants))
    print(f"{args.out}: {files} files, {size / 2**20:.1f} MiB unpacked, {args.out.stat().st_size / 2**20:.1f} MiB packed")
    return check(args.out, tuple(args.check)) if args.check else 0


if __name__ == "__main__":
    raise SystemExit(main())
