"""Fuzzing the input paths with hypothesis: generated scene documents and command lines.

The contract (README "Commands"): an input either works — the scene parses and builds, the render is
finite, the command exits 0 and writes its outputs — or it is refused with ONE line naming the file
or field (an `InputError`; exit code 2 on the command line) and nothing is written. Never a
traceback, never a half-written output (nor a temporary file left behind).

Documents are mutations of small valid scenes: a key set to an extreme or wrongly typed value
(1e39, 3.5e38, 1e18, NaN, ±inf, 400-digit integers, strings, booleans, lists of the wrong length,
tables), a key deleted, an unknown key added. Most run through the parser and builder in-process (no
JAX compilation, milliseconds each); value-only mutations of one fixed scene are rendered (one
compiled frame); a few documents and argument lists run through `jaxrt.cli.main` at 8x6 pixels.

The default run is bounded and reproducible (derandomized, no deadline; ~30 s on a 2-core CPU);
`-m slow` runs many more examples of each.
"""

from __future__ import annotations

import copy
import json
import math
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxrt import cli
from jaxrt import scene as S
from jaxrt.errors import InputError

FAST = settings(derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck))


def bounded(n_default: int, n_slow: int):
    """(default-suite settings, slow settings) with n examples each."""
    return settings(FAST, max_examples=n_default), settings(FAST, max_examples=n_slow)


# ---------------------------------------------------------------------------------------------
# scene documents


def base_scenes() -> list[dict]:
    """Small valid scenes covering every table kind: primitives, point lights, an environment, an
    emitter, textures, glass and mirrors, groups and instances."""
    plain = {
        "camera": {"position": [0.0, 1.0, 4.0], "look_at": [0.0, 0.5, 0.0], "width": 8, "height": 6},
        "lights": [{"position": [2.0, 4.0, 3.0], "intensity": 20.0}],
        "materials": {"red": {"model": "phong", "rho_d": [0.6, 0.1, 0.1], "rho_s": 0.3, "s": 40.0},
                      "floor": {"model": "lambert", "rho_d": 0.5, "delta": 0.2}},
        "objects": [
            {"name": "ball", "primitive": "sphere", "radius": 0.5, "subdivisions": 1,
             "translate": [0.0, 0.5, 0.0], "material": "red"},
            {"name": "floor", "primitive": "plane", "size": [4.0, 4.0], "material": "floor"},
        ],
        "render": {"max_depth": 2, "background": [0.1, 0.1, 0.2]},
    }
    lit = copy.deepcopy(plain)
    del lit["lights"]
    lit["environment"] = {"radiance": [0.5, 0.6, 0.7], "scale": 1.0, "rotate": 10.0}
    lit["materials"]["lamp"] = {"model": "lambert", "rho_d": 0.1, "emission": [3.0, 3.0, 3.0]}
    lit["materials"]["glass"] = {"model": "glass", "n_t": 1.5}
    lit["objects"].append({"name": "lamp", "primitive": "box", "size": 0.3, "translate": [1.0, 1.5, 0.0],
                           "rotate": [10.0, 20.0, 30.0], "material": "lamp"})
    lit["objects"].append({"primitive": "sphere", "radius": 0.3, "subdivisions": 0, "translate": [-1.0, 0.3, 0.0],
                           "material": "glass"})
    lit["render"]["integrator"] = "path"
    tex = copy.deepcopy(plain)
    tex["materials"]["floor"]["rho_d"] = {"checker": [[0.8, 0.8, 0.8], [0.1, 0.1, 0.1]], "scale": 4,
                                          "wrap": "repeat", "offset": [0.0, 0.5]}
    tex["camera"].update(aperture=0.1, focus_distance=4.0, vfov=35.0, up=[0.0, 1.0, 0.0])
    inst = copy.deepcopy(plain)
    inst["groups"] = [{"name": "pair", "objects": [
        {"name": "a", "primitive": "sphere", "radius": 0.2, "subdivisions": 0, "material": "red"},
        {"name": "b", "primitive": "box", "size": [0.2, 0.4, 0.2], "translate": [0.5, 0.0, 0.0], "material": "red"}]}]
    inst["instances"] = [{"group": "pair", "translate": [0.0, 1.0, 0.0]},
                         {"group": "pair", "name": "second", "scale": 0.5, "rotate": [0.0, 45.0, 0.0],
                          "material": "floor"}]
    return [plain, lit, tex, inst]


BASES = base_scenes()

# keys a mutation may add where the base lacks them (so optional keys are fuzzed too)
OPTIONAL = [
    ("camera", "aperture"), ("camera", "focus_distance"), ("camera", "up"), ("camera", "vfov"),
    ("render", "spp"), ("render", "seed"), ("render", "ray_budget"), ("render", "integrator"),
    ("environment", "radiance"), ("environment", "scale"), ("environment", "file"),
    ("materials", "red", "emission"), ("materials", "red", "delta"), ("materials", "red", "model"),
    ("objects", 0, "scale"), ("objects", 0, "rotate"), ("objects", 1, "mesh"), ("objects", 0, "name"),
    ("lights", 0, "type"), ("description",),
]

EXTREMES = [0, -0.0, 1e-45, 1e-30, 1e18, 1.0000001e18, 3.4e38, 3.5e38, 1e39, -1e39, 1e300,
            math.nan, math.inf, -math.inf, 2**63, -(2**31) - 1, 10**400, 16384, 16385]

leaf = st.one_of(
    st.sampled_from(EXTREMES),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**40), max_value=2**40),
    st.booleans(),
    st.sampled_from(["", "sphere", "bunny", "../../etc/passwd", "x.exr", "lambert", "path", "a\nb", "ball"]),
)
value = st.one_of(
    leaf,
    st.lists(leaf, max_size=4),
    st.lists(st.sampled_from(EXTREMES + [0.5, 1.0, -1.0]), min_size=2, max_size=3),
    st.dictionaries(st.sampled_from(["texture", "checker", "scale", "x", "name"]), leaf, max_size=2),
)


def leaf_paths(doc, prefix=()):
    out = []
    if isinstance(doc, dict):
        items = doc.items()
    elif isinstance(doc, list):
        items = enumerate(doc)
    else:
        return [prefix]
    for k, v in items:
        out += leaf_paths(v, prefix + (k,))
    return out + ([prefix] if prefix else [])


def mutate(doc, path, op, new):
    """A copy of doc with `path` set to `new` (op "set"), deleted ("del") or given an unknown sibling ("add")."""
    doc = copy.deepcopy(doc)
    cur = doc
    for k in path[:-1]:
        if isinstance(cur, dict):
            cur = cur.setdefault(k, {})
        elif isinstance(cur, list) and isinstance(k, int) and k < len(cur):
            cur = cur[k]
        else:
            return doc
        if not isinstance(cur, (dict, list)):
            return doc
    k = path[-1]
    if isinstance(cur, list) and not (isinstance(k, int) and k < len(cur)):
        return doc
    if op == "del":
        if isinstance(cur, dict):
            cur.pop(k, None)
        else:
            del cur[k]
    elif op == "add" and isinstance(cur, dict):
        cur["no_such_key"] = new
    else:
        cur[k] = new
    return doc


@st.composite
def documents(draw, max_mutations=3):
    doc = draw(st.sampled_from(BASES))
    for _ in range(draw(st.integers(1, max_mutations))):
        paths = leaf_paths(doc) + OPTIONAL
        path = draw(st.sampled_from(paths))
        doc = mutate(doc, path, draw(st.sampled_from(["set", "set", "set", "del", "add"])), draw(value))
    return doc


def assert_one_line(e: Exception, *anyof: str) -> str:
    msg = str(e)
    assert msg and "\n" not in msg and "\r" not in msg, repr(msg)
    if anyof:
        assert any(a in msg for a in anyof), msg
    return msg


def parse_and_build(doc):
    """The Scene, or None after checking the InputError's form. Any other exception fails the test."""
    try:
        spec = S.parse(doc)
    except InputError as e:
        assert_one_line(e, "<scene>")
        return None
    try:
        return S.build(spec)
    except InputError as e:
        assert_one_line(e, "<scene>", "object ", "instance ")
        return None


def _documents_parse_or_fail_in_one_line(doc):
    sc = parse_and_build(doc)
    if sc is not None:  # what was accepted is representable
        for leaf_ in (sc.camera.position, sc.camera.look_at, sc.lights.intensity, sc.settings.background):
            assert np.all(np.isfinite(np.asarray(leaf_)))


_fast, _slow = bounded(250, 3000)
test_documents_parse_or_fail_in_one_line = _fast(given(documents())(_documents_parse_or_fail_in_one_line))
test_documents_parse_or_fail_in_one_line_many = pytest.mark.slow(
    _slow(given(documents(max_mutations=6))(_documents_parse_or_fail_in_one_line)))


# ---- renders of accepted values: one fixed structure (one compiled frame), values fuzzed

VALUE_KEYS = [
    (("camera", "position"), 3), (("camera", "look_at"), 3), (("lights", 0, "position"), 3),
    (("lights", 0, "intensity"), 3), (("objects", 0, "translate"), 3), (("objects", 0, "radius"), 1),
    (("render", "background"), 3), (("materials", "floor", "delta"), 1), (("materials", "red", "s"), 1),
]
magnitude = st.one_of(st.sampled_from([0.0, 1e-30, 1e-6, 0.5, 1.0, 7.0, 1e6, 1e17, 1e18, 1.1e18, 1e39]),
                      st.floats(-1e19, 1e19, allow_nan=False))


@st.composite
def value_documents(draw):
    doc = copy.deepcopy(BASES[0])
    for _ in range(draw(st.integers(1, 3))):
        path, n = draw(st.sampled_from(VALUE_KEYS))
        v = [draw(magnitude) for _ in range(n)]
        doc = mutate(doc, path, "set", v if n > 1 else v[0])
    return doc


def _accepted_values_render_finite(doc):
    from jaxrt import integrators

    sc = parse_and_build(doc)
    if sc is None:
        return
    img = np.asarray(integrators.frame(sc))
    assert img.shape == (6, 8, 3) and np.all(np.isfinite(img)), doc


_fast, _slow = bounded(12, 200)
test_accepted_values_render_finite = _fast(given(value_documents())(_accepted_values_render_finite))
test_accepted_values_render_finite_many = pytest.mark.slow(
    _slow(given(value_documents())(_accepted_values_render_finite)))


# ---------------------------------------------------------------------------------------------
# the command line


def toml(doc: dict) -> str:
    """A TOML text for a document of tables, arrays, numbers, strings and booleans (inline tables)."""
    def key(k):
        return k if re.fullmatch(r"[A-Za-z0-9_-]+", str(k)) else json.dumps(str(k))

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int):
            return str(v)
        if isinstance(v, float):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{key(k)} = {val(x)}" for k, x in v.items()) + "}"
        raise TypeError(type(v))

    return "".join(f"{key(k)} = {val(v)}\n" for k, v in doc.items())


def test_toml_writer_round_trips():
    import tomllib

    for doc in BASES:
        assert tomllib.loads(toml(doc)) == doc


def run_cli(argv, capsys):
    try:
        rc = cli.main([str(a) for a in argv])
    except SystemExit as e:
        rc = e.code
    return rc, capsys.readouterr().err


def check_run(argv, rc, err, folder: Path, before: set[str], outputs: list[Path]):
    """exit 0: every output exists, the EXR is finite, nothing else appeared; exit 2: one line that
    names the scene file or an option of argv, and nothing was written."""
    from jaxrt import image

    now = {p.name for p in folder.iterdir()}
    if rc == 0:
        for p in outputs:
            assert p.is_file(), (argv, sorted(now))
            if p.suffix == ".exr":
                assert np.all(np.isfinite(np.asarray(image.read_exr(p)))), argv
        assert now == before | {p.name for p in outputs}, (argv, sorted(now - before))
        return
    assert rc == 2, (argv, rc, err)
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1, (argv, err)
    named = [str(a) for a in argv if str(a).startswith("-")] + [str(a) for a in argv[1:2]] + ["argument"]
    assert any(n in lines[0] for n in named), (argv, lines[0])
    assert now == before, (argv, sorted(now ^ before))


def _documents_through_the_cli(doc, capsys):
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        scene = folder / "s.toml"
        scene.write_text(toml(doc))
        outs = [folder / "out.exr", folder / "out.png"]
        argv = ["render", scene, "-o", outs[0], "--png", outs[1], "--width", 8, "--height", 6, "-q"]
        before = {p.name for p in folder.iterdir()}
        rc, err = run_cli(argv, capsys)
        check_run(argv, rc, err, folder, before, outs)


_fast, _slow = bounded(4, 60)
test_documents_through_the_cli = _fast(given(doc=documents(max_mutations=2))(_documents_through_the_cli))
test_documents_through_the_cli_many = pytest.mark.slow(
    _slow(given(doc=documents(max_mutations=4))(_documents_through_the_cli)))


# ---- argument lists

def option_values(flag):
    ints = st.sampled_from(["-1", "0", "abc", "", "1e3", "99999999999999999999", "nan"])
    good = {"--width": ["8", "4"], "--height": ["6", "3"], "--spp": ["1", "2"], "--max-depth": ["1", "2"],
            "--seed": ["0", "7"], "--exposure": ["0", "2.5", "-3"], "--integrator": ["whitted", "path"]}
    bad = {"--exposure": ["1024", "-65", "nan", "inf", "1e400", "x"], "--integrator": ["bdpt", ""],
           "--spp": ["4097"], "--max-depth": ["17"], "--width": ["16385"], "--seed": ["-1", "2147483648"]}
    return st.one_of(st.sampled_from(good[flag]), st.sampled_from(bad.get(flag, [])) if flag in bad else ints, ints)


OUTPUT_CHOICES = ["ok.exr", "ok.png", "adir.png", "missing/x.exr", "/sys/x.exr", "/proc/x.png", "x.txt", "",
                  "ok2.exr", "ok2.png"]


@st.composite
def render_arguments(draw):
    flags = draw(st.lists(st.sampled_from(["--width", "--height", "--spp", "--max-depth", "--seed", "--exposure",
                                           "--integrator"]), unique=True, max_size=4))
    argv = ["render", "SCENE"]
    for f in flags:
        argv += [f, draw(option_values(f))]
    outs = {}
    for flag in draw(st.lists(st.sampled_from(["-o", "--png"]), unique=True, max_size=2)):
        outs[flag] = draw(st.sampled_from(OUTPUT_CHOICES))
        argv += [flag, "OUT:" + outs[flag]]
    if draw(st.booleans()):
        argv.append(draw(st.sampled_from(["--aovs", "--confine", "--no-such-flag", "-q"])))
    return argv


def _render_arguments(argv, capsys):
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        (folder / "adir.png").mkdir()
        scene = folder / "s.toml"
        scene.write_text(toml(BASES[0]))
        real, outputs = [], []
        for a in argv:
            if a == "SCENE":
                a = scene
            elif a.startswith("OUT:"):
                name = a[4:]
                a = name if name.startswith("/") or not name else folder / name
                outputs.append(Path(a))
            real.append(a)
        if "--width" not in real:  # keep accepted renders tiny: the scene is 8x6
            real += ["--width", "8", "--height", "6"] if "--height" not in real else ["--width", "8"]
        if not outputs:
            real += ["-o", folder / "default.exr"]
            outputs = [folder / "default.exr"]
        before = {p.name for p in folder.iterdir()}
        rc, err = run_cli(real, capsys)
        check_run(real, rc, err, folder, before, outputs)


_fast, _slow = bounded(16, 200)
test_render_arguments = _fast(given(argv=render_arguments())(_render_arguments))
test_render_arguments_many = pytest.mark.slow(_slow(given(argv=render_arguments())(_render_arguments)))


@st.composite
def other_arguments(draw):
    """fit / fit-matrix / sweep / brdf-report argument lists that must be refused before any work."""
    cmd = draw(st.sampled_from(["fit", "fit-matrix", "sweep", "brdf-report"]))
    if cmd == "fit":
        argv = ["fit", "--demo"] + draw(st.sampled_from([
            ["--max-steps", "-1"], ["--starts", "0"], ["--plot", "OUT:adir.png"], ["--out", "OUT:x.png"],
            ["--solver", "newton"], ["--plot", "OUT:/sys/p.png"], ["--max-steps", "x"]]))
    elif cmd == "fit-matrix":
        argv = ["fit-matrix"] + draw(st.sampled_from([
            ["--models", ","], ["--models", "phong,phong"], ["--models", "glass"], ["--models", "nope"],
            ["-o", "OUT:adir.png"], ["--models", "lambert", "--starts", "0"]]))
    elif cmd == "sweep":
        argv = ["sweep"] + draw(st.sampled_from([
            ["phong", "s", "--steps", "0"], ["phong", "nope"], ["nope", "s"], ["phong", "s", "-o", "OUT:adir.png"],
            ["phong", "s", "--from", "1e39"], ["phong", "s", "--exposure", "1024"]]))
    else:
        argv = ["brdf-report"] + draw(st.sampled_from([
            ["-o", "OUT:adir.png"], ["--samples", "3"], ["--angles", "90"], ["-o", "OUT:x.jpg"]]))
    return argv + ["-q"] if cmd != "brdf-report" else argv


def _other_arguments(argv, capsys):
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        (folder / "adir.png").mkdir()
        real = [(a[4:] if a[4:].startswith("/") else folder / a[4:]) if a.startswith("OUT:") else a for a in argv]
        before = {p.name for p in folder.iterdir()}
        rc, err = run_cli(real, capsys)
        assert rc == 2, (real, rc, err)  # every generated list is bad input
        check_run(real, rc, err, folder, before, [])


_fast, _slow = bounded(12, 100)
test_other_commands_refuse_bad_arguments = _fast(given(argv=other_arguments())(_other_arguments))
test_other_commands_refuse_bad_arguments_many = pytest.mark.slow(
    _slow(given(argv=other_arguments())(_other_arguments)))
