"""The package structure: no import cycles and no module reaching into another module's private names.

The walk reads every first-party module's source (jaxrt, brdfs, fitting, benchmarks) with `ast`, so it
sees imports inside functions too (a lazy import that closes a cycle is still coupling), and it
never imports the code it checks.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jaxrt", "brdfs", "fitting")


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules(dirs=PACKAGES) -> dict[str, Path]:
    out = {}
    for d in dirs:
        for p in sorted((ROOT / d).rglob("*.py")):
            out[_module_name(p)] = p
    return out


MODULES = _modules()


def _is_package(name: str) -> bool:
    return MODULES.get(name, Path()).name == "__init__.py"


def _resolve(importer: str, node: ast.ImportFrom | ast.Import) -> list[tuple[str, str | None]]:
    """(first-party module imported, name taken from it or None) for one import statement."""
    out = []
    if isinstance(node, ast.Import):
        for a in node.names:
            if a.name.split(".")[0] in PACKAGES:
                out.append((a.name, None))
        return out
    base = node.module or ""
    if node.level:
        pkg = importer if _is_package(importer) else importer.rpartition(".")[0]
        for _ in range(node.level - 1):
            pkg = pkg.rpartition(".")[0]
        base = f"{pkg}.{base}" if base else pkg
    if base.split(".")[0] not in PACKAGES:
        return out
    for a in node.names:
        sub = f"{base}.{a.name}"
        out.append((sub, None) if sub in MODULES else (base, a.name))
    return out


def _edges() -> dict[str, list[tuple[str, str | None, int]]]:
    graph = {}
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        edges = []
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for mod, taken in _resolve(name, node):
                    edges.append((mod, taken, node.lineno))
        graph[name] = edges
    return graph


GRAPH = _edges()


def _cycles(graph: dict[str, list[tuple[str, str | None, int]]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    adj = {m: sorted({t for t, _, _ in e if t in graph and t != m}) for m, e in graph.items()}
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in adj[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10_000)
    for v in adj:
        if v not in index:
            visit(v)
    return out


def test_the_walk_sees_the_packages():
    # guards the checks below against passing vacuously (a wrong root or a parser that finds nothing)
    assert {"jaxrt.scene.parse", "jaxrt.geometry.base", "jaxrt.integrators.whitted", "brdfs", "fitting.setup"} <= set(MODULES)
    assert ("jaxrt.shading.surface", "Surface") in {(m, t) for m, t, _ in GRAPH["jaxrt.geometry.base"]}


def test_no_import_cycles():
    assert _cycles(GRAPH) == []


def test_cycle_finder_finds_a_cycle():
    fake = {"a": [("b", None, 1)], "b": [("c", None, 1)], "c": [("a", "_x", 1)], "d": [("a", None, 1)]}
    assert _cycles(fake) == [["a", "b", "c"]]


def _private_imports(graph) -> list[str]:
    bad = []
    for importer, edges in graph.items():
        for mod, taken, line in edges:
            if taken is not None and taken.startswith("_") and not taken.startswith("__") and mod != importer:
                bad.append(f"{importer}:{line} takes {taken} from {mod}")
    return bad


def test_no_module_imports_another_modules_private_names():
    assert _private_imports(GRAPH) == []


def test_no_private_attribute_of_another_first_party_module():
    """`from jaxrt.accel import bvh; bvh._impl(...)` reaches in as surely as importing `_impl`."""
    bad = []
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text())
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for a, (mod, taken) in zip(node.names, _resolve(name, node)):
                    if taken is None and mod != name:
                        aliases[a.asname or a.name.split(".")[0]] = mod
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                bad.append(f"{name}:{node.lineno} uses {node.value.id}.{node.attr}")
    assert bad == []


def test_private_import_check_catches_one():
    fake = {"x": [("y", "_helper", 3), ("y", "public", 4), ("x", "_own", 5), ("y", "__version__", 6)]}
    assert _private_imports(fake) == ["x:3 takes _helper from y"]


def test_packages_declare_their_public_names():
    """Every package's `__init__` lists its public API in `__all__`, and each listed name exists."""
    for name, path in MODULES.items():
        if path.name != "__init__.py" or name.count(".") > 1:
            continue
        tree = ast.parse(path.read_text())
        decl = [n for n in tree.body if isinstance(n, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets)]
        assert decl, f"{name} has no __all__"
    code = ("import importlib, sys\n"
            "for m in sys.argv[1:]:\n"
            "    mod = importlib.import_module(m)\n"
            "    missing = [n for n in mod.__all__ if not hasattr(mod, n)]\n"
            "    assert not missing, (m, missing)\n")
    pkgs = [n for n, p in MODULES.items() if p.name == "__init__.py" and n.count(".") <= 1]
    r = subprocess.run([sys.executable, "-c", code, *pkgs], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.parametrize("module", ["jaxrt.integrators.path", "jaxrt.integrators.whitted"])
def test_integrators_never_import_each_other(module):
    others = {"jaxrt.integrators.path", "jaxrt.integrators.whitted"} - {module}
    assert not [m for m, _, _ in GRAPH[module] if m in others]


def test_no_geometry_kind_dispatch_above_the_geometry_layer():
    """Integrators, shading, sweeps, the viewer, the CLI and fitting program against
    `AbstractGeometry`: they never test which kind of geometry they hold."""
    kinds = ("InstancedGeometry", "TriangleGeometry", "InstancedBVH", "is_instanced")
    bad = []
    for name, path in MODULES.items():
        if not name.startswith(("jaxrt.integrators", "jaxrt.shading", "jaxrt.sweep", "jaxrt.viewer", "jaxrt.cli",
                                "fitting")):
            continue
        src = path.read_text()
        bad += [f"{name}: {k}" for k in kinds if k in src]
    assert bad == []


# Packages that cost a second or more to import on a small machine (colour-science alone loads scipy
# and matplotlib) or that only some commands need: each is imported where it is first used, so
# `import jaxrt`, `import brdfs` and `import fitting` pay for JAX and the project's own modules only.
HEAVY = ("matplotlib", "colour", "scipy", "trimesh", "OpenEXR", "h5py", "optimistix", "lineax", "ipywidgets",
         "tqdm", "jax.experimental.pallas.triton")


def test_package_imports_and_png_writing_leave_heavy_modules_unloaded(tmp_path):
    code = ("import json, sys\n"
            "import numpy as np\n"
            "heavy = lambda: sorted(m for m in sys.argv[2:] if m in sys.modules)\n"
            "out = {}\n"
            "import brdfs\n"
            "out['brdfs'] = heavy()\n"
            "import fitting\n"
            "out['fitting'] = heavy()\n"
            "import jaxrt\n"
            "out['jaxrt'] = heavy()\n"
            "from jaxrt import image\n"
            "image.write_png(sys.argv[1], np.linspace(0, 2, 24, dtype=np.float32).reshape(2, 4, 3))\n"
            "out['png'] = heavy()\n"
            "out['probe'] = [m for m in ('PIL', 'jax') if m not in sys.modules]\n"
            "print(json.dumps(out))\n")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "a.png"), *HEAVY], cwd=ROOT, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"brdfs": [], "fitting": [], "jaxrt": [], "png": [], "probe": []}


def test_package_imports_and_cli_help_leave_jax_unloaded_and_first_use_turns_the_cache_on(tmp_path):
    """`import jaxrt, brdfs, fitting`, the `jaxrt` parser (no command, `--help`) and the resident
    worker's client import no JAX; the first JAX-using module of jaxrt loads it with JAX's persistent
    compilation cache already pointing at the cache folder (checked before any jaxrt code compiles)."""
    code = ("import json, sys, contextlib, io\n"
            "out = {}\n"
            "import jaxrt, brdfs, fitting\n"
            "import jaxrt.cli, jaxrt.serve\n"
            "out['names'] = [set(jaxrt.__all__) <= set(dir(jaxrt)), set(brdfs.__all__) <= set(dir(brdfs))]\n"
            "with contextlib.redirect_stdout(io.StringIO()) as help_text:\n"
            "    try:\n"
            "        jaxrt.cli.main(['--help'])\n"
            "    except SystemExit as e:\n"
            "        out['help_exit'] = e.code\n"
            "out['help'] = 'render' in help_text.getvalue()\n"
            "out['jax_before'] = 'jax' in sys.modules\n"
            "render = jaxrt.render\n"
            "import jax\n"
            "out['cache_dir'] = jax.config.jax_compilation_cache_dir\n"
            "out['models'] = list(brdfs.names())[:2]\n"
            "out['fit'] = fitting.fit_images.__module__\n"
            "print(json.dumps(out))\n")
    env = {**os.environ, "JAXRT_CACHE_DIR": str(tmp_path / "c"), "JAXRT_WORKER": "off"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"names": [True, True], "help_exit": 0, "help": True, "jax_before": False,
                   "cache_dir": str(tmp_path / "c" / "xla"), "models": ["lambert", "phong"], "fit": "fitting.solve"}
    # the console command itself, as a separate process: `python -m jaxrt.cli --help` then the modules it loaded
    probe = ("import runpy, sys\n"
             "sys.argv = ['jaxrt', '--help']\n"
             "try:\n"
             "    runpy.run_module('jaxrt.cli', run_name='__main__')\n"
             "except SystemExit:\n"
             "    pass\n"
             "print('JAX' if 'jax' in sys.modules else 'NOJAX')\n")
    r = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, env=env)
    assert r.returncode == 0 and r.stdout.strip().splitlines()[-1] == "NOJAX", r.stdout[-500:] + r.stderr[-2000:]


def test_lazy_package_names_are_the_modules_objects():
    code = ("import jaxrt, brdfs, fitting\n"
            "from jaxrt.api import render\n"
            "from jaxrt.scene import load, Scene\n"
            "from brdfs.base import Model\n"
            "from brdfs.lambert import MODEL\n"
            "from fitting.solve import solve_batch\n"
            "assert jaxrt.render is render and jaxrt.load_scene is load and jaxrt.Scene is Scene\n"
            "assert brdfs.Model is Model and brdfs.MODELS['lambert'] is MODEL and brdfs.get('lambert') is MODEL\n"
            "assert fitting.solve_batch is solve_batch and jaxrt.image.__name__ == 'jaxrt.image'\n"
            "for pkg in (jaxrt, brdfs, fitting):\n"
            "    try:\n"
            "        pkg.no_such_name\n"
            "    except AttributeError:\n"
            "        pass\n"
            "    else:\n"
            "        raise SystemExit(pkg.__name__)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       env={**os.environ, "JAXRT_WORKER": "off"})
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.parametrize("given", [None, "true"])
def test_first_jax_module_sets_gpu_preallocation_off_unless_the_environment_says(tmp_path, given):
    """JAX's GPU client reserves most of the GPU at its first allocation unless
    XLA_PYTHON_CLIENT_PREALLOCATE=false; jaxrt sets that default before its first JAX-using module
    loads (the backend starts later), and leaves a value the user gave alone."""
    code = ("import os, jaxrt\n"
            "before = os.environ.get('XLA_PYTHON_CLIENT_PREALLOCATE')\n"
            "import jaxrt.scene\n"
            "print(before, os.environ.get('XLA_PYTHON_CLIENT_PREALLOCATE'))\n")
    env = {**os.environ, "JAXRT_CACHE_DIR": str(tmp_path / "c"), "JAXRT_WORKER": "off"}
    env.pop("XLA_PYTHON_CLIENT_PREALLOCATE", None)
    if given is not None:
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = given
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ([str(given), given] if given else ["None", "false"])
