"""`jaxrt.programs.cached_jit`: traced programs stored on disk and reused by later processes.

Checked: a stored program gives bit-identical results to `jax.jit`; a new function object (as in a
new process) reuses it without tracing; every part of the key (static arguments, shapes, dtypes,
structure) selects its own program; transformations and JAXRT_CACHE=off fall back to `jax.jit`; a
second process renders a scene from the stored frame program (no tracing of the integrator) with
the same pixels.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import cache as _cache
from jaxrt import programs as _programs

from test_cache import _py


@pytest.fixture
def cdir(tmp_path, monkeypatch):
    d = tmp_path / "cache"
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(d))
    monkeypatch.delenv("JAXRT_CACHE", raising=False)
    return d


TRACES = []


def _fun(p, x, *, power=2):
    TRACES.append(1)  # runs once per trace
    return {"y": p["a"] * x**power + jnp.sum(jnp.sin(p["b"])), "n": jnp.sum(x)}


def _stats():
    s = _programs.program_stats()
    return np.array([s.hits, s.misses, s.fallbacks])


def test_a_stored_program_serves_a_new_function_object_without_tracing(cdir):
    p = {"a": np.float32(1.5), "b": np.arange(3, dtype=np.float32)}
    x = np.linspace(0, 1, 3, dtype=np.float32)
    ref = jax.jit(_fun, static_argnames=("power",))(p, x, power=3)
    s0 = _stats()
    f = _programs.cached_jit(_fun, name="test.fun", static_argnames=("power",))
    out = f(p, x, power=3)
    assert list(_stats() - s0) == [0, 1, 0]
    for k in ref:
        assert np.array_equal(np.asarray(out[k]), np.asarray(ref[k])) and out[k].dtype == ref[k].dtype
    assert sorted((cdir / "arrays").glob("program-*" + _cache._SUFFIX))
    TRACES.clear()
    g = _programs.cached_jit(_fun, name="test.fun", static_argnames=("power",))  # as a new process has
    out2 = g(p, {"a": 1, "b": 2}["a"] * x)  # another value, same structure
    again = g(p, x, power=3)
    assert TRACES == [1]  # only the first call (power=2 is a new program) traced
    assert np.array_equal(np.asarray(again["y"]), np.asarray(ref["y"]))
    assert np.array_equal(np.asarray(out2["y"]), np.asarray(jax.jit(_fun)(p, x)["y"]))
    assert len(g._programs) == 2  # two stored programs in this process


@pytest.mark.parametrize("change", ["static", "shape", "dtype", "structure", "name"])
def test_each_part_of_the_key_selects_its_own_program(cdir, change):
    p = {"a": np.float32(2.0), "b": np.zeros(2, np.float32)}
    x = np.ones(4, np.float32)
    f = _programs.cached_jit(_fun, name="test.key", static_argnames=("power",))
    f(p, x)
    s0 = _stats()
    args, kw, name = (p, x), {}, "test.key"
    if change == "static":
        kw = {"power": 3}
    elif change == "shape":
        args = (p, np.ones(5, np.float32))
    elif change == "dtype":
        args = (p, np.ones(4, np.int32))
    elif change == "structure":
        args = ({"a": np.float32(2.0), "b": np.zeros(2, np.float32), "c": 1.0}, x)
    else:
        name = "test.key2"
    g = _programs.cached_jit(_fun, name=name, static_argnames=("power",))
    out = g(*args, **kw)
    assert list(_stats() - s0) == [0, 1, 0]  # a miss, not the stored program of the first call
    ref = jax.jit(_fun, static_argnames=("power",))(*args, **kw)
    assert np.array_equal(np.asarray(out["y"]), np.asarray(ref["y"]))


def test_transformations_and_cache_off_fall_back_to_jit(cdir, monkeypatch):
    f = _programs.cached_jit(lambda a, x: jnp.sum(a * x**2), name="test.grad")
    x = np.arange(3, dtype=np.float32)
    s0 = _stats()
    g = jax.grad(f)(np.float32(2.0), x)  # tracers: jax.jit's path
    v = jax.vmap(f, in_axes=(0, None))(np.ones(2, np.float32), x)
    assert list(_stats() - s0) == [0, 0, 2]
    assert float(g) == pytest.approx(5.0) and np.allclose(v, 5.0)
    monkeypatch.setenv("JAXRT_CACHE", "off")
    assert float(f(np.float32(1.0), x)) == pytest.approx(5.0)
    assert list(_stats() - s0) == [0, 0, 3] and not (cdir / "arrays").exists()


class _Pair(eqx.Module):  # a pytree type jax.export does not serialize (as a GBuffer, a FitBuffer)
    y: jax.Array
    n: jax.Array


def _pair(x):
    TRACES.append(1)
    return _Pair(x + 1, jnp.sum(x))


def test_outputs_of_other_pytree_types_are_stored_with_their_structure(cdir):
    """A program whose output is an equinox Module is stored (its structure beside it); a new function
    object reads it without tracing, gives the output's shapes before any call (`lower(...).out_info`,
    from `jax.ShapeDtypeStruct` arguments) and the same values as `jax.jit`."""
    x = np.arange(3, dtype=np.float32)
    s0 = _stats()
    ref = _programs.cached_jit(_pair, name="test.pair")(x)
    assert list(_stats() - s0) == [0, 1, 0]
    TRACES.clear()
    g = _programs.cached_jit(_pair, name="test.pair")  # as a new process has
    lowered = g.lower(jax.ShapeDtypeStruct((3,), np.float32))
    info = lowered.out_info
    assert isinstance(info, _Pair) and info.y.shape == (3,) and info.n.shape == () and info.n.dtype == np.float32
    c = lowered.compile()
    out, again = g(x), c(x)
    assert TRACES == [] and list(_stats() - s0) == [1, 1, 0] and len(g._programs) == 1
    exact = jax.jit(_pair)(x)
    for o in (ref, out, again):
        assert isinstance(o, _Pair)
        assert np.array_equal(np.asarray(o.y), np.asarray(exact.y)) and float(o.n) == float(exact.n)


def test_unserializable_outputs_fall_back_to_jit(cdir):
    class Out(eqx.Module):  # defined in a function: its structure cannot be stored (pickle names no such type)
        y: jax.Array

    traced = []
    f = _programs.cached_jit(lambda x: (traced.append(1), Out(x + 1))[1], name="test.module")
    s0 = _stats()
    out = f(np.float32(1.0))
    assert isinstance(out, Out) and float(out.y) == 2.0
    assert list(_stats() - s0) == [0, 0, 1] and len(traced) == 2  # the export's trace, then jax.jit's
    f(np.float32(2.0))  # the failed export is remembered: jax.jit serves, nothing is traced again
    assert list(_stats() - s0) == [0, 0, 2] and len(traced) == 2


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
# opaque glass shadows: on a CPU with Embree the frame's hits and shadow rays are one native call of
# its own FFI target, which the second process must register before the stored program compiles
@pytest.mark.parametrize("glass_shadows", ["transmit", "opaque"])
def test_a_second_process_renders_from_the_stored_frame_program(tmp_path, glass_shadows):
    code = """
    import hashlib, json, sys
    import jax
    import jaxrt
    from jaxrt import programs as _programs, integrators, scene
    traced = []
    whitted, doc = integrators.REGISTRY["whitted"]
    def counting(*a, **k):  # runs each time the integrator is traced
        traced.append(1)
        return whitted(*a, **k)
    integrators.REGISTRY["whitted"] = (counting, doc)
    sc = scene.load("spheres", overrides={"camera.width": 24, "camera.height": 16, "render.glass_shadows": GS})
    img = jax.device_get(jaxrt.render(sc))
    s = _programs.program_stats()
    print(json.dumps(dict(hits=s.hits, misses=s.misses, traced=len(traced), lean="optimistix" not in sys.modules,
                          image=hashlib.sha256(img.tobytes()).hexdigest())))
    """
    code = code.replace("GS", repr(glass_shadows))
    d = tmp_path / "cache"
    first, second = _py(code, d), _py(code, d)
    off = _py(code, tmp_path / "off", JAXRT_CACHE="off")
    assert (first["misses"], first["hits"]) == (1, 0) and (second["misses"], second["hits"]) == (0, 1)
    assert second["image"] == first["image"] == off["image"]
    assert first["traced"] >= 1 and second["traced"] == 0  # the second process never traced the integrator
    assert first["lean"] and second["lean"]  # keying the program imports no fitting code (optimistix)


def test_ahead_of_time_lowering_returns_the_stored_program(cdir):
    f = _programs.cached_jit(_fun, name="test.aot", static_argnames=("power",))
    p = {"a": np.float32(3.0), "b": np.ones(2, np.float32)}
    x = np.arange(4, dtype=np.float32)
    c = f.lower(p, x, power=3).compile()
    assert c.memory_analysis() is not None or jax.default_backend() != "cpu"
    s0 = _stats()
    out = c(p, x, power=3)
    again = f(p, x, power=3)  # the call runs the program compiled ahead of time: nothing new
    assert list(_stats() - s0) == [0, 0, 0] and len(f._programs) == 1
    ref = jax.jit(_fun, static_argnames=("power",))(p, x, power=3)
    assert np.array_equal(np.asarray(out["y"]), np.asarray(ref["y"])) and np.array_equal(again["y"], out["y"])


@pytest.mark.slow
def test_a_second_process_fits_from_stored_programs_without_importing_the_solver_library(tmp_path):
    """A fit's large programs (the scene's trace, the target render, the solver and its Jacobians) are
    stored: a second process traces none of them, so it never imports optimistix (imported where a
    solver is first built), and recovers the same parameters and target bit for bit, as `jax.jit` does
    with the cache off. Neither imports colour-science."""
    code = """
    import hashlib, json, sys
    import numpy as np
    import brdfs
    from fitting import setup as scene_fit
    from jaxrt import programs as _programs
    model = brdfs.get("cook_torrance")
    setup = scene_fit.prepare([scene_fit.variant("spheres", camera={"width": 20, "height": 14})], model)
    truth = model.params(rho_d=0.3, rho_s=0.6, m=0.25, eta=1.8)
    target = np.asarray(scene_fit.render_with(setup, truth))
    r, _ = scene_fit.fit(None, target, model, setup=setup, rgb=False, starts=1, progress=False, fix={"eta": 1.8})
    s = _programs.program_stats()
    print(json.dumps(dict(hits=s.hits, misses=s.misses, fallbacks=s.fallbacks, solver="optimistix" in sys.modules,
                          colour="colour" in sys.modules,
                          params={k: np.asarray(v).tolist() for k, v in r.params.items()},
                          target=hashlib.sha256(target.tobytes()).hexdigest())))
    """
    d = tmp_path / "cache"
    first, second = _py(code, d), _py(code, d)
    assert first["misses"] > 0 and first["solver"]
    assert second["misses"] == 0 and second["hits"] == first["misses"] + first["hits"]
    assert not second["solver"]
    assert not first["colour"] and not second["colour"]  # the ΔE needs no colour-science (scipy, matplotlib)
    assert second["params"] == first["params"] and second["target"] == first["target"]
    off = _py(code, tmp_path / "off", JAXRT_CACHE="off")
    assert off["hits"] == off["misses"] == 0 and off["fallbacks"] > 0
    assert off["params"] == first["params"] and off["target"] == first["target"]
    assert abs(first["params"]["m"] - 0.25) < 1e-3  # the fit itself worked


_CLI_FIT = """
    import json, os, re, sys, threading
    from jax import monitoring
    from jaxrt import programs, scene
    from jaxrt.cli import main
    from jaxrt.integrators import whitted
    events, hits, traced = [], [0], [0]
    def on_compile(event, duration, **kw):  # every XLA compilation request, a persistent-cache hit or not
        if event == "/jax/core/compile/backend_compile_duration":
            events.append((kw.get("fun_name"), threading.current_thread().name))
    monitoring.register_event_duration_secs_listener(on_compile)
    monitoring.register_event_listener(lambda e, **k: hits.__setitem__(0, hits[0] + (e == "/jax/compilation_cache/cache_hits")))
    loop = whitted._trace_loop
    def counting(*a, record, **k):  # runs each time a fit's trace program is traced (record=True)
        traced[0] += record
        return loop(*a, record=record, **k)
    whitted._trace_loop = counting
    os.chdir({work!r})
    def run(argv):
        n, h, t, m = len(events), hits[0], traced[0], programs.program_stats().misses
        assert main(argv) == 0
        new = events[n:]
        return dict(requests=len(new), compiled=len(new) - (hits[0] - h), traced=traced[0] - t,
                    misses=programs.program_stats().misses - m, trace_jit=[e[0] for e in new].count("jit(trace)"),
                    threads=sorted(set(e[1] for e in new)), ahead=[e[1] for e in new].count("fitting-trace-ahead"),
                    after=[e[1] for e in new].count("fitting-trace-compile"))
    out = {{}}
    if not os.path.exists("target.exr"):  # the target: the scene's own render (no trace program in it)
        text = re.sub(r"(?m)^width = \\\\d+", "width = 24", scene.find_scene("spheres").read_text())
        open("scene.toml", "w").write(re.sub(r"(?m)^height = \\\\d+", "height = 16", text))
        out["render"] = run(["render", "scene.toml", "-o", "target.exr", "--png", "target.png", "-q"])
    fit = ["fit", "target.exr", "--scene", "scene.toml", "--model", "cook_torrance", "--grey", "--object",
           "cook_torrance", "-q"]
    tag = os.environ.get("JAXRT_CACHE", "on")
    out["fit"] = run(fit + ["--out", f"a-{{tag}}.json", "--fix", "eta=1.5", "--starts", "2", "--max-steps", "40"])
    # other fixed and initial values, starts and step limit (below the compiled bound, 64)
    out["again"] = run(fit + ["--out", f"b-{{tag}}.json", "--fix", "eta=1.8", "--init", "m=0.3", "--starts", "3",
                              "--max-steps", "60"])
    out["a"], out["b"] = (json.load(open(f"{{x}}-{{tag}}.json"))["params"] for x in "ab")
    print(json.dumps(out))
"""


@pytest.mark.slow  # three fresh processes with fits: about a minute and a half on 2 cores
def test_cli_fit_compiles_its_trace_once_and_a_second_process_compiles_nothing(tmp_path):
    """`jaxrt fit TARGET.exr ...`: preparing the fit traces the scene's trace program once and compiles
    it once, in the thread that compiles it while the BVH is built (`fitting.setup._compile_trace_ahead`);
    a second fit in the same process with other --fix and --init values, starts and step limit
    compiles nothing; a second process with the same cache traces no program (every one is stored:
    the trace, the shading, the solver and its Jacobians) and compiles nothing (every compilation
    request is a persistent-cache hit), and fits the same parameters bit for bit; so does a process
    with the cache off, which compiles the trace program once too."""
    work = tmp_path / "work"
    work.mkdir()
    d = tmp_path / "cache"
    first = _py(_CLI_FIT.format(work=str(work)), d)
    assert first["render"]["traced"] == 0, first
    assert first["fit"]["traced"] == 1 and first["fit"]["ahead"] == 1 and first["fit"]["after"] == 0, first
    assert first["fit"]["misses"] > 0 and first["fit"]["trace_jit"] == 0, first
    assert first["again"]["requests"] == 0 and first["again"]["traced"] == 0, first
    second = _py(_CLI_FIT.format(work=str(work)), d)
    assert "render" not in second and second["fit"]["requests"] > 0, second
    assert second["fit"]["compiled"] == 0 and second["again"]["requests"] == 0, second
    assert second["fit"]["traced"] == 0 and second["fit"]["misses"] == 0, second
    assert second["a"] == first["a"] and second["b"] == first["b"]
    assert first["a"]["eta"] == np.float32(1.5) and first["b"]["eta"] == np.float32(1.8)  # the fixed values were used
    off = _py(_CLI_FIT.format(work=str(work)), tmp_path / "off", JAXRT_CACHE="off")
    assert off["fit"]["traced"] == 1 and off["fit"]["trace_jit"] == 1 and off["again"]["requests"] == 0, off
    assert off["a"] == first["a"] and off["b"] == first["b"]


_CLI_RENDER = """
    import hashlib, json, os, sys, threading
    from jax import monitoring
    from jaxrt.cli import main
    events, hits = [], [0]
    def on_compile(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append([kw.get("fun_name"), threading.current_thread().name])
    monitoring.register_event_duration_secs_listener(on_compile)
    monitoring.register_event_listener(
        lambda e, **k: hits.__setitem__(0, hits[0] + (e == "/jax/compilation_cache/cache_hits")))
    os.chdir({work!r})
    assert main(["render", "spheres", "--width", "24", "--height", "16", "-o", "a.exr", "--png", "a.png", "-q"]) == 0
    print(json.dumps(dict(events=events, hits=hits[0], exr=hashlib.sha256(open("a.exr", "rb").read()).hexdigest(),
                          png=hashlib.sha256(open("a.png", "rb").read()).hexdigest())))
"""


@pytest.mark.slow  # three fresh processes, two of them compiling a frame: about a minute on 2 cores
def test_cli_render_compiles_its_frame_once_beside_the_tree_build_and_a_second_process_compiles_nothing(tmp_path):
    """`jaxrt render`: the frame program is compiled once, in the thread that compiles it while the
    BVH is built (`render_tiles.compile_ahead`); a second process with the same cache compiles nothing
    (the request is a persistent-cache hit); with JAXRT_CACHE=off the same one compilation; the EXR
    and PNG are byte-identical in all three."""
    work = tmp_path / "work"
    work.mkdir()
    d = tmp_path / "cache"
    first = _py(_CLI_RENDER.format(work=str(work)), d)
    second = _py(_CLI_RENDER.format(work=str(work)), d)
    off = _py(_CLI_RENDER.format(work=str(work)), tmp_path / "off", JAXRT_CACHE="off")
    assert first["events"] == [["jit(call)", "jaxrt-compile"]] and first["hits"] == 0, first["events"]
    assert second["events"] == [["jit(call)", "jaxrt-compile"]] and second["hits"] == 1, second["events"]
    assert off["events"] == [["jit(_frame)", "jaxrt-compile"]] and off["hits"] == 0, off["events"]
    assert first["exr"] == second["exr"] == off["exr"] and first["png"] == second["png"] == off["png"]
    # the kernel the frame calls was built in this folder (Embree's where installed, else jaxrt's), not the other
    built = sorted(p.name.split("-")[0] for p in (d / "native").glob("*.so"))
    assert built in (["embree"], ["traverse"]), built


def test_every_native_ffi_target_is_known_to_stored_programs():
    """A stored program that calls a native kernel registers that kernel's FFI target before it is
    compiled; a target missing from the map would leave the program unloadable in a second process
    ("No FFI handler registered"). Every *TARGET constant of the native modules is in their TARGETS,
    and every one is mapped to its module."""
    import importlib

    for name in _programs._NATIVE_MODULES:
        mod = importlib.import_module(f"jaxrt.accel.{name}")
        consts = {v for k, v in vars(mod).items() if (k == "TARGET" or k.endswith("_TARGET")) and isinstance(v, str)}
        assert consts and consts == set(mod.TARGETS), name
        for t in mod.TARGETS:
            assert _programs._native()[t] == name
