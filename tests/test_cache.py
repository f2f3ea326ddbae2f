"""The configuration module and the on-disk caches (`jaxrt._config`, `jaxrt.cache`).

Every test uses its own empty cache folder (JAXRT_CACHE_DIR under tmp_path), so none depends on a
warm cache. What a second process reuses is counted (cache entries, hit counters, JAX's compile
events), never timed.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxrt
from jaxrt import _config, cache
from jaxrt.errors import InputError

ROOT = Path(jaxrt.__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------
# helpers


@pytest.fixture
def cdir(tmp_path, monkeypatch) -> Path:
    """An empty cache folder for this test, named by JAXRT_CACHE_DIR (not created yet)."""
    d = tmp_path / "cache"
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(d))
    for v in ("JAXRT_CACHE", "JAXRT_CACHE_SIZE"):
        monkeypatch.delenv(v, raising=False)
    return d


def _env(cache_dir, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAXRT_CACHE", "JAX_COMPILATION_CACHE",
                                                                      "JAX_PERSISTENT_CACHE"))}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env["JAXRT_CACHE_DIR"] = str(cache_dir)
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _py(code: str, cache_dir, *, prefix: tuple[str, ...] = (), **extra) -> dict:
    """Run `code` in a fresh Python; it prints one JSON line last. Returns that, with the warnings seen."""
    p = subprocess.run([*prefix, sys.executable, "-c", textwrap.dedent(code)], env=_env(cache_dir, **extra),
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["stderr"] = p.stderr
    return out


def _arrays_equal(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype, k
        assert a[k].shape == b[k].shape, k
        assert np.array_equal(a[k], b[k]), k


def _entries(d: Path) -> list[Path]:
    return sorted((d / "arrays").glob("*" + cache._SUFFIX)) if (d / "arrays").is_dir() else []


def _delta(before: cache.CacheStats) -> dict:
    after = cache.stats()
    return {f.name: getattr(after, f.name) - getattr(before, f.name) for f in dataclasses.fields(after)}


def _obj(path: Path, degenerate: bool = False) -> Path:
    """A small OBJ (a subdivided sphere with UVs; optionally one zero-area triangle) written to `path`."""
    from jaxrt.geometry import shapes

    m = shapes.sphere(subdivisions=3)
    lines = [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in m.vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in m.uvs]
    faces = [tuple(f) for f in m.faces]
    if degenerate:
        faces.append((0, 0, 1))
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


# ---------------------------------------------------------------------------------------------
# jaxrt._config


def test_config_defaults_and_values(tmp_path):
    c = _config.config({})
    assert c == _config.Config(data=None, debug=False, traversal="auto", cache_dir=Path.home() / ".cache" / "jaxrt",
                               cache=True, cache_size=2 << 30, memory=None, confine=False)
    env = {"JAXRT_DATA": str(tmp_path), "JAXRT_DEBUG": "1", "JAXRT_TRAVERSAL": "xla", "JAXRT_CACHE": "OFF",
           "JAXRT_CACHE_DIR": "rel/dir", "JAXRT_CACHE_SIZE": "1.5G", "JAXRT_MEMORY": "512m", "JAXRT_CONFINE": "yes"}
    c = _config.config(env)
    assert (c.data, c.debug, c.traversal, c.cache, c.cache_size, c.memory, c.confine) == (
        tmp_path, True, "xla", False, 3 << 29, 512 << 20, True)
    assert c.cache_dir == Path.cwd() / "rel" / "dir"  # relative: to the current folder, returned absolute
    assert _config.config({"XDG_CACHE_HOME": str(tmp_path)}).cache_dir == tmp_path / "jaxrt"
    assert _config.config({"JAXRT_DEBUG": "0", "JAXRT_CACHE_SIZE": "0"}).debug is False
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.cache = True  # type: ignore[misc]


def test_config_reads_the_environment_at_each_call(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(tmp_path / "a"))
    assert _config.config().cache_dir == tmp_path / "a"
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(tmp_path / "b"))
    assert _config.config().cache_dir == tmp_path / "b"
    assert cache.cache_dir() == tmp_path / "b"


@pytest.mark.parametrize("name, value", [
    ("JAXRT_DEBUG", "maybe"), ("JAXRT_TRAVERSAL", "fast"), ("JAXRT_CACHE", "1"), ("JAXRT_CACHE", "disabled"),
    ("JAXRT_CACHE_SIZE", "lots"), ("JAXRT_CACHE_SIZE", "-1G"), ("JAXRT_CACHE_SIZE", "2P"), ("JAXRT_MEMORY", "0"),
    ("JAXRT_MEMORY", "8 gigs"), ("JAXRT_CONFINE", "strict"),
])
def test_config_bad_values_are_one_line_errors_naming_the_variable(name, value):
    with pytest.raises(InputError) as e:
        _config.config({name: value})
    msg = str(e.value)
    assert msg.startswith(f"{name}={value!r}:") and "\n" not in msg and "must" in msg


def test_config_cache_dir_must_not_be_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="JAXRT_CACHE_DIR=.*not a folder"):
        _config.config({"JAXRT_CACHE_DIR": str(f)})


def test_config_traversals_match_bvh():
    from jaxrt.accel import bvh

    assert _config.TRAVERSALS == bvh.IMPLS


# ---------------------------------------------------------------------------------------------
# cached_arrays: hits, misses, corruption, unwritable folders, the bound, JAXRT_CACHE=off


def _build(calls: list, n: int = 1000, seed: int = 0):
    def build():
        calls.append(1)
        r = np.random.default_rng(seed)
        return {"f": r.random((n, 3), dtype=np.float32), "i": r.integers(0, 9, n).astype(np.int32),
                "b": r.random(n) < 0.5, "empty": np.zeros((0, 3), np.float64), "scalar": np.array(7, np.int64)}
    return build


def test_miss_then_hit_is_bit_identical(cdir):
    calls: list = []
    before = cache.stats()
    first = cache.cached_arrays("test", {"n": 1, "name": "x"}, _build(calls))
    second = cache.cached_arrays("test", {"name": "x", "n": 1}, _build(calls))  # key order does not matter
    assert len(calls) == 1
    _arrays_equal(first, second)
    _arrays_equal(first, _build([])())
    assert _delta(before) == dict(hits=1, misses=1, writes=1, rebuilds=0, evictions=0, bypasses=0)
    assert len(_entries(cdir)) == 1
    cache.cached_arrays("test", {"n": 2, "name": "x"}, _build(calls))  # another key: another entry
    assert len(calls) == 2 and len(_entries(cdir)) == 2
    i = cache.info()
    assert (i.dir, i.enabled, i.array_entries, i.compiled_entries) == (cdir, True, 2, 0)
    assert i.array_bytes == sum(p.stat().st_size for p in _entries(cdir)) and i.bound == 2 << 30


def _records(path: Path) -> list[np.ndarray]:
    """The .npy records of an entry file, read with numpy's own reader (never pickle)."""
    out = []
    with open(path, "rb") as fh:
        while fh.peek(1):
            out.append(np.lib.format.read_array(fh, allow_pickle=False))
    return out


def test_entries_are_npy_records_without_pickle(cdir):
    built = _build([])()
    cache.cached_arrays("test", {"k": 1}, _build([]))
    (path,) = _entries(cdir)
    meta, *arrays = _records(path)
    meta = json.loads(meta.tobytes())
    assert meta["format"] == cache.FORMAT_VERSION and len(meta["sha256"]) == 64
    assert sorted(meta["arrays"]) == ["b", "empty", "f", "i", "scalar"]
    _arrays_equal(dict(zip(meta["arrays"], arrays)), built)
    with pytest.raises(TypeError, match="object"):
        cache.cached_arrays("test", {"k": 2}, lambda: {"o": np.array([None, 1], dtype=object)})
    with pytest.raises(ValueError, match="kind"):
        cache.cached_arrays("Bad Kind", {}, _build([]))
    with pytest.raises(TypeError, match="JSON"):
        cache.cached_arrays("test", {"k": object()}, _build([]))


def _corrupt(path: Path, how: str, cdir: Path) -> None:
    raw = path.read_bytes()
    if how == "truncated":
        path.write_bytes(raw[: len(raw) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "trailing":  # a whole entry with bytes after its last record
        path.write_bytes(raw + b"\0" * 64)
    elif how == "flipped":  # one byte inside the float payload: the entry's sha256 catches it
        b = bytearray(raw)
        b[len(b) // 3] ^= 0xFF
        path.write_bytes(bytes(b))
    elif how == "garbage":
        path.write_bytes(os.urandom(len(raw)))
    elif how == "stale":  # a whole, valid entry written for another key, under this key's name
        calls: list = []
        cache.cached_arrays("test", {"k": "other"}, _build(calls, seed=5))
        other = [p for p in _entries(cdir) if p != path][0]
        os.replace(other, path)
    elif how == "checksum":  # valid records whose arrays no longer match the recorded sha256
        meta, *arrays = _records(path)
        names = json.loads(meta.tobytes())["arrays"]
        arrays[names.index("f")] = arrays[names.index("f")] + np.float32(1)
        with open(path, "wb") as fh:
            for a in [meta, *arrays]:
                np.lib.format.write_array(fh, a, allow_pickle=False)


@pytest.mark.parametrize("how", ["truncated", "empty", "trailing", "flipped", "garbage", "stale", "checksum"])
def test_bad_entries_are_rebuilt_with_one_warning(cdir, how):
    key = {"k": 1}
    calls: list = []
    good = cache.cached_arrays("test", key, _build(calls))
    (path,) = _entries(cdir)
    _corrupt(path, how, cdir)
    before = cache.stats()
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        again = cache.cached_arrays("test", key, _build(calls))
    said = [x for x in w if issubclass(x.category, cache.CacheWarning)]
    assert len(said) == 1 and str(path) in str(said[0].message) and "rebuilding" in str(said[0].message)
    assert len(calls) == 2
    _arrays_equal(good, again)
    assert _delta(before)["rebuilds"] == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the overwritten entry now reads cleanly: no warning, a hit
        before = cache.stats()
        _arrays_equal(good, cache.cached_arrays("test", key, _build(calls)))
    assert len(calls) == 2 and _delta(before)["hits"] == 1


def test_unwritable_folder_degrades_with_one_warning(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(blocker / "cache"))  # cannot be created: its parent is a file
    calls: list = []
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        a = cache.cached_arrays("test", {"k": 1}, _build(calls))
        b = cache.cached_arrays("test", {"k": 2}, _build(calls, seed=1))
        a2 = cache.cached_arrays("test", {"k": 1}, _build(calls))
    said = [x for x in w if issubclass(x.category, cache.CacheWarning)]
    assert len(said) == 1 and "cannot store" in str(said[0].message)
    assert len(calls) == 3
    _arrays_equal(a, a2)
    _arrays_equal(b, _build([], seed=1)())


def test_full_disk_degrades_with_one_warning_and_leaves_no_temporary_file(cdir, monkeypatch):
    def full(fh, *args, **kwargs):  # the disk fills part-way through the entry's first record
        fh.write(b"\x93NUMPY")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(cache.np.lib.format, "write_array", full)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        for k in range(3):
            cache.cached_arrays("test", {"k": k}, _build([]))
    said = [x for x in w if issubclass(x.category, cache.CacheWarning)]
    assert len(said) == 1 and "No space left" in str(said[0].message)
    assert list((cdir / "arrays").iterdir()) == []


def _read_only_prefix(folder: Path) -> tuple[str, ...] | None:
    """A command prefix that runs a process with `folder` read-only, or None where none works here."""
    if os.geteuid() != 0:
        return ()  # chmod is enough for an ordinary user
    unshare = shutil.which("unshare")
    if unshare is None:
        return None
    f = str(folder)
    prefix = (unshare, "-rm", "sh", "-c", f'mount --bind "{f}" "{f}" && mount -o remount,bind,ro "{f}" "{f}" && '
              'exec "$0" "$@"')
    probe = subprocess.run([*prefix, sys.executable, "-c", f"open({str(folder / 'p')!r}, 'w')"], capture_output=True)
    return prefix if probe.returncode != 0 and not (folder / "p").exists() else None


def test_read_only_folder_still_serves_hits_and_warns_once(tmp_path):
    d = tmp_path / "cache"
    code = """
        import json, warnings, numpy as np
        from jaxrt import cache
        warnings.simplefilter("always")
        got = [cache.cached_arrays("test", {"k": k}, lambda k=k: {"a": np.arange(1000) * k}) for k in (1, 2, 3)]
        assert all(np.array_equal(g["a"], np.arange(1000) * k) for g, k in zip(got, (1, 2, 3)))
        print(json.dumps(cache.stats().__dict__))
    """
    first = _py(code.replace("(1, 2, 3)", "(1,)"), d)
    assert first["writes"] == 1
    names = sorted(p.name for p in (d / "arrays").iterdir())
    prefix = _read_only_prefix(d)
    if prefix is None:
        pytest.skip("cannot make a read-only folder here (root without a working `unshare -rm`)")
    if not prefix:
        for p in [d, d / "arrays"]:
            p.chmod(0o555)
    try:
        out = _py(code, d, prefix=prefix)
    finally:
        for p in [d, d / "arrays"]:
            p.chmod(0o755)
    assert (out["hits"], out["misses"], out["writes"]) == (1, 2, 0)
    assert out["stderr"].count("CacheWarning") == 1 and "cannot store" in out["stderr"]
    assert sorted(p.name for p in (d / "arrays").iterdir()) == names


def test_size_bound_evicts_least_recently_used(cdir, monkeypatch):
    one = sum(a.nbytes for a in _build([])().values())
    monkeypatch.setenv("JAXRT_CACHE_SIZE", str(int(3.5 * (one + 2000))))  # room for three entries, not four
    paths = {}
    for k in "abc":
        cache.cached_arrays("test", {"k": k}, _build([]))
        paths[k] = [p for p in _entries(cdir) if p not in paths.values()][0]
    for t, k in enumerate("abc"):  # distinct, old modification times: a oldest
        os.utime(paths[k], ns=(10**18 + t * 10**9,) * 2)
    (cdir / "xla").mkdir()
    xla = cdir / "xla" / "jit_f-0123-cache"  # a compiled program, older than every array entry
    xla.write_bytes(b"x" * 1000)
    os.utime(xla, ns=(10**17,) * 2)
    calls: list = []
    cache.cached_arrays("test", {"k": "a"}, _build(calls))  # a hit: a becomes the most recently used
    assert calls == []
    before = cache.stats()
    cache.cached_arrays("test", {"k": "d"}, _build(calls))  # too much now: the program and b go
    assert _delta(before)["evictions"] == 2
    assert not xla.exists() and not paths["b"].exists() and paths["a"].exists() and paths["c"].exists()
    assert len(_entries(cdir)) == 3 and cache.info().bytes <= cache.info().bound
    monkeypatch.setenv("JAXRT_CACHE_SIZE", str(one // 2))  # an entry larger than the bound is not stored
    cache.cached_arrays("test", {"k": "e"}, _build(calls))
    assert len(_entries(cdir)) == 3


def test_cache_off_writes_nothing(cdir, monkeypatch):
    monkeypatch.setenv("JAXRT_CACHE", "off")
    calls: list = []
    before = cache.stats()
    for _ in range(2):
        cache.cached_arrays("test", {"k": 1}, _build(calls))
    assert len(calls) == 2 and _delta(before)["bypasses"] == 2
    assert not cdir.exists()
    assert cache.info().enabled is False and cache.info().entries == 0


def test_clear_removes_entries_and_keeps_other_files(cdir):
    cache.cached_arrays("test", {"k": 1}, _build([]))
    (cdir / "xla").mkdir()
    (cdir / "xla" / "jit_g-99-cache").write_bytes(b"y" * 10)
    (cdir / "xla" / "autotune").mkdir()  # XLA's GPU autotuning results live under xla/ too
    (cdir / "xla" / "autotune" / "r.textproto").write_bytes(b"z" * 5)
    other = cdir / "traverse-abc.so"  # the native kernel's library and the data registry's files stay
    other.write_bytes(b"elf")
    assert cache.info().entries == 2 and cache.info().compiled_bytes == 15
    expected = 15 + sum(p.stat().st_size for p in _entries(cdir))
    assert cache.clear() == expected
    assert cache.info().entries == 0 and cache.info().bytes == 0 and other.exists()
    assert list((cdir / "xla").iterdir()) == [] and list((cdir / "arrays").iterdir()) == []


def test_cli_cache_info_and_clear(cdir, capsys):
    import argparse

    from jaxrt.cli import cache as cli_cache

    p = argparse.ArgumentParser()
    cli_cache.configure(p)
    assert cli_cache.run(p.parse_args(["info"])) == 0
    assert str(cdir) in capsys.readouterr().out
    cache.cached_arrays("test", {"k": 1}, _build([]))
    cli_cache.run(p.parse_args(["info"]))
    assert "1 entries" in capsys.readouterr().out
    assert cli_cache.run(p.parse_args(["clear"])) == 0 and cache.info().entries == 0


def test_concurrent_writers_of_one_key_are_safe(tmp_path):
    d = tmp_path / "cache"
    go, done = tmp_path / "go", tmp_path / "done"
    # Two processes build the same keys at the same moment (a short sleep in build keeps both in
    # the miss, so both write each key); a third reads every entry that exists while they write.
    # A reader must only ever see whole entries: a partial one would warn (an error here).
    common = f"""
        import json, os, time, warnings, numpy as np
        from jaxrt import cache
        warnings.simplefilter("error", cache.CacheWarning)
        while not os.path.exists({str(go)!r}):
            time.sleep(0.01)
    """
    writer = common + """
        def build(k):
            time.sleep(0.05)
            return {"a": np.full(2_000_000, k, np.float32), "k": np.array(k)}
        for k in range(12):
            got = cache.cached_arrays("race", {"k": k}, lambda k=k: build(k))
            assert np.all(got["a"] == k) and int(got["k"]) == k
        print(json.dumps(cache.stats().__dict__))
    """
    reader = common + f"""
        def boom():
            raise AssertionError("an existing entry was not read")
        for _ in range(100_000):
            if os.path.exists({str(done)!r}):
                break
            for k in range(12):
                if cache.entry_path("race", {{"k": k}}).exists():
                    assert np.all(cache.cached_arrays("race", {{"k": k}}, boom)["a"] == k)
        print(json.dumps(cache.stats().__dict__))
    """
    procs = [subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], env=_env(d), cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for code in (writer, writer, reader)]
    go.write_text("")
    outs = [p.communicate(timeout=600) for p in procs[:2]]
    done.write_text("")
    outs.append(procs[2].communicate(timeout=600))
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    stats = [json.loads(o.strip().splitlines()[-1]) for o, _ in outs]
    assert all(s["rebuilds"] == 0 for s in stats) and stats[2]["misses"] == 0
    assert sum(s["writes"] for s in stats[:2]) >= 12  # both may write a key; the rename makes that harmless
    files = sorted((d / "arrays").iterdir())
    assert len(files) == 12 and not any(f.name.startswith(".tmp") for f in files)
    check = _py("""
        import json, numpy as np
        from jaxrt import cache
        for k in range(12):
            assert np.all(cache.cached_arrays("race", {"k": k}, lambda: 1 / 0)["a"] == k)
        print(json.dumps(cache.stats().__dict__))
    """, d)
    assert check["hits"] == 12 and check["misses"] == 0


# ---------------------------------------------------------------------------------------------
# load_mesh / build_bvh


def _mesh_arrays(m) -> dict:
    out = {k: getattr(m, k) for k in ("vertices", "faces", "normals", "tangents", "object_id")}
    if m.uvs is not None:
        out["uvs"] = m.uvs
    return out


def _tree_arrays(t) -> dict:
    return {f.name: np.asarray(getattr(t, f.name)) for f in dataclasses.fields(t)
            if not f.metadata.get("static") and getattr(t, f.name) is not None}


@pytest.mark.parametrize("flat", [False, True])
def test_load_mesh_is_bit_identical_and_replays_warnings(cdir, tmp_path, flat):
    from jaxrt.geometry import mesh

    path = _obj(tmp_path / "ball.obj", degenerate=True)
    with pytest.warns(UserWarning, match="zero-area"):
        ref = mesh.load(path, flat=flat)
    before = cache.stats()
    got = []
    for _ in range(2):
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            got.append(cache.load_mesh(path, flat))
        said = [str(x.message) for x in w]
        assert said == [f"{path}: removed 1 zero-area triangle(s) of {len(ref.faces) + 1}"]  # miss and hit alike
    assert _delta(before)["misses"] == 1 and _delta(before)["hits"] == 1
    for m in got:
        _arrays_equal(_mesh_arrays(ref), _mesh_arrays(m))
        assert m.names == ref.names == ("ball",) and (m.uvs is None) == (ref.uvs is None)
    with pytest.warns(UserWarning, match="zero-area"):
        assert cache.load_mesh(path, flat, name="other").names == ("other",)  # name is part of the key
    assert len(_entries(cdir)) == 2


def test_load_mesh_of_a_data_file(cdir, data_dir):
    from jaxrt.geometry import data
    from jaxrt.geometry import mesh

    ref = mesh.load(data.find("bunny"))
    before = cache.stats()
    a = cache.load_mesh(data.find("bunny"))
    b = cache.load_mesh(data.find("bunny"))
    assert _delta(before)["hits"] == 1
    for m in (a, b):
        _arrays_equal(_mesh_arrays(ref), _mesh_arrays(m))
        assert m.names == ref.names


def test_load_mesh_errors_are_the_loaders(cdir, tmp_path):
    with pytest.raises(InputError, match="not found"):
        cache.load_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2 3")
    with pytest.raises(InputError, match="unsupported mesh format"):
        cache.load_mesh(bad)
    assert _entries(cdir) == []


@pytest.mark.parametrize("settings", [dict(), dict(builder="sah", layout="dfs"), dict(leaf_size=4, layout="dfs"),
                                      dict(builder="sah", leaf_size=2)])
def test_build_bvh_is_bit_identical(cdir, settings):
    from jaxrt.accel import bvh
    from jaxrt.geometry import shapes

    m = shapes.sphere(subdivisions=4)
    ref = bvh.build(m.vertices, m.faces, **settings)
    before = cache.stats()
    miss = cache.build_bvh(m.vertices, m.faces, **settings)
    hit = cache.build_bvh(m.vertices, m.faces, **settings)
    assert _delta(before)["misses"] == 1 and _delta(before)["hits"] == 1
    for t in (miss, hit):
        assert type(t) is bvh.BVH and t.leaf_size == ref.leaf_size
        _arrays_equal(_tree_arrays(ref), _tree_arrays(t))
        assert (t.rows is None) == (ref.rows is None)
    o = np.tile(np.array([[0.1, 0.2, 5.0]], np.float32), (64, 1))
    d = np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (64, 1)) + np.linspace(-0.1, 0.1, 64, dtype=np.float32)[:, None]
    h0, h1 = bvh.intersect(ref, o, d), bvh.intersect(hit, o, d)
    assert all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(h0, h1))


def test_build_bvh_key_covers_inputs_and_sah_settings(cdir):
    from jaxrt.accel import sah as bvh_sah
    from jaxrt.geometry import shapes

    m = shapes.sphere(subdivisions=3)
    cache.build_bvh(m.vertices, m.faces, builder="sah")
    before = cache.stats()
    cache.build_bvh(m.vertices, m.faces, builder="sah", leaf_size=2)
    cache.build_bvh(m.vertices * np.float32(2), m.faces, builder="sah")
    cache.build_bvh(m.vertices, m.faces, builder="sah", sah_settings=bvh_sah.SahSettings(sah_min=2 * bvh_sah.DEFAULT.sah_min))
    assert _delta(before)["misses"] == 3 and _delta(before)["hits"] == 0
    with pytest.raises(InputError, match="leaf_size"):
        cache.build_bvh(m.vertices, m.faces, leaf_size=99)


def test_second_process_hits_mesh_and_bvh(tmp_path):
    d = tmp_path / "cache"
    path = _obj(tmp_path / "ball.obj")
    code = f"""
        import json, hashlib, numpy as np
        from jaxrt import cache
        from jaxrt.accel import bvh
        m = cache.load_mesh({str(path)!r})
        t = cache.build_bvh(m.vertices, m.faces, **bvh.RENDER_TREE)
        h = hashlib.sha256()
        for a in (m.vertices, m.faces, m.normals, m.tangents, m.uvs, t.node_box, t.links, t.triangles, t.prim_ids):
            h.update(np.asarray(a).tobytes())
        print(json.dumps(dict(cache.stats().__dict__, digest=h.hexdigest())))
    """
    first, second = _py(code, d), _py(code, d)
    assert (first["misses"], first["writes"], first["hits"]) == (2, 2, 0)
    assert (second["misses"], second["writes"], second["hits"]) == (0, 0, 2)
    assert first["digest"] == second["digest"]
    off = _py(code, tmp_path / "off", JAXRT_CACHE="off")
    assert off["bypasses"] == 2 and off["digest"] == first["digest"] and not (tmp_path / "off").exists()


# ---------------------------------------------------------------------------------------------
# the compilation cache


_COUNT = """
    import collections, json, jax
    from jax import monitoring
    counts = collections.Counter()
    monitoring.register_event_listener(lambda e, **k: counts.update([e]))
    monitoring.register_event_duration_secs_listener(lambda e, d, **k: counts.update([e]))
    def compiled():  # XLA compilations that ran (a persistent-cache hit is not one)
        return counts["/jax/core/compile/backend_compile_duration"] - counts["/jax/compilation_cache/cache_hits"]
"""


@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_second_process_compiles_nothing_for_a_render(tmp_path):
    d = tmp_path / "cache"
    code = _COUNT + """
    import hashlib, warnings
    import jaxrt
    from jaxrt import cache, scene
    from jaxrt.accel import traverse_cpu as bvh_cpu
    warnings.simplefilter("always")
    on = cache.enable_compilation_cache()
    sc = scene.load("spheres", overrides={"camera.width": 24, "camera.height": 16})
    img = jaxrt.render(sc).block_until_ready()
    print(json.dumps(dict(on=on, compiled=compiled(), hits=counts["/jax/compilation_cache/cache_hits"],
                          native=bvh_cpu.available(), image=hashlib.sha256(jax.device_get(img).tobytes()).hexdigest())))
    """
    first = _py(code, d)
    assert first["on"] and first["compiled"] > 0 and first["hits"] == 0
    n = len(list((d / "xla").glob("*-cache")))
    assert n == first["compiled"]  # every compilation was stored (no minimum time or size)
    second = _py(code, d)
    assert second["compiled"] == 0 and second["hits"] == first["compiled"]
    assert second["image"] == first["image"] and second["native"] == first["native"]
    assert len(list((d / "xla").glob("*-cache"))) == n
    # Bad contents never fail a render: every stored program truncated, the third run recompiles.
    for p in (d / "xla").glob("*-cache"):
        p.write_bytes(p.read_bytes()[:10])
    third = _py(code, d)
    assert third["image"] == first["image"] and third["compiled"] == first["compiled"]


@pytest.mark.parametrize("kernel", ["native", pytest.param("pallas", marks=pytest.mark.slow)])
def test_cached_programs_with_the_native_kernel_and_pallas_load_in_a_fresh_process(tmp_path, kernel):
    # The FFI target of the native kernel is registered while the program is traced (jaxrt.accel.bvh
    # calls bvh_cpu.available()), i.e. before JAX looks the compiled program up in the cache.
    # "pallas" is the Triton kernel on a GPU and the Pallas interpreter elsewhere.
    d = tmp_path / "cache"
    code = _COUNT + f"""
    import hashlib
    import numpy as np
    from jaxrt import cache
    from jaxrt.accel import bvh
    from jaxrt.accel import traverse_cpu as bvh_cpu
    from jaxrt.geometry import shapes
    gpu = jax.default_backend() == "gpu"
    if {kernel!r} == "native" and jax.default_backend() != "cpu":
        print(json.dumps(dict(skip="the native kernel runs on the CPU backend only")))
        raise SystemExit
    if {kernel!r} == "native" and not bvh_cpu.available():
        print(json.dumps(dict(skip="the native CPU kernel cannot be compiled here (no C++ compiler)")))
        raise SystemExit
    impl = "cpu" if {kernel!r} == "native" else ("pallas" if gpu else "pallas-interpret")
    assert cache.enable_compilation_cache()
    m = shapes.sphere(subdivisions=3)
    tree = bvh.build(m.vertices, m.faces)
    r = np.random.default_rng(0)
    o = np.tile(np.array([[0.0, 0.0, 4.0]], np.float32), (256, 1))
    dirs = (np.array([0.0, 0.0, -1.0]) + 0.3 * r.standard_normal((256, 3))).astype(np.float32)
    hit = jax.jit(lambda t, o, d: bvh.intersect(t, o, d, impl=impl))(tree, o, dirs)
    blocked = jax.jit(lambda t, o, d: bvh.occluded(t, o, d, 10.0, impl=impl))(tree, o, dirs)
    h = hashlib.sha256(b"".join(np.asarray(x).tobytes() for x in (*hit, blocked))).hexdigest()
    print(json.dumps(dict(compiled=compiled(), hits=counts["/jax/compilation_cache/cache_hits"], digest=h,
                          found=int(np.sum(np.asarray(hit.prim) >= 0)))))
    """
    first = _py(code, d)
    if "skip" in first:
        pytest.skip(first["skip"])
    assert first["compiled"] > 0 and first["found"] > 0
    second = _py(code, d)
    assert second["compiled"] == 0 and second["hits"] == first["compiled"] and second["digest"] == first["digest"]


def test_compilation_cache_unwritable_or_off(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = _COUNT + """
    import warnings
    from jaxrt import cache
    warnings.simplefilter("always")
    first, again = cache.enable_compilation_cache(), cache.enable_compilation_cache()
    y = jax.jit(lambda x: x * 2 + 1)(jax.numpy.arange(4.0))
    print(json.dumps(dict(on=[first, again], y=y.tolist(), dir=jax.config.jax_compilation_cache_dir)))
    """
    bad = _py(code, blocker / "cache")
    assert bad["on"] == [False, False] and bad["y"] == [1.0, 3.0, 5.0, 7.0] and bad["dir"] is None
    assert bad["stderr"].count("CacheWarning") == 1 and "without caching compiled programs" in bad["stderr"]
    off = _py(code, tmp_path / "off", JAXRT_CACHE="off")
    assert off["on"] == [False, False] and off["dir"] is None and "CacheWarning" not in off["stderr"]
    assert not (tmp_path / "off").exists()
    ok = _py(code, tmp_path / "ok")
    assert ok["on"] == [True, True] and ok["dir"] == str(tmp_path / "ok" / "xla")
    assert len(list((tmp_path / "ok" / "xla").glob("*-cache"))) >= 1


def test_compilation_cache_follows_the_folder_and_leaves_a_users_setting(tmp_path):
    code = _COUNT + """
    import os
    from jaxrt import cache
    assert cache.enable_compilation_cache()
    jax.jit(lambda x: x + 1)(jax.numpy.arange(3.0)).block_until_ready()
    os.environ["JAXRT_CACHE_DIR"] = os.environ["SECOND"]  # the folder moves within the process
    assert cache.enable_compilation_cache()
    jax.jit(lambda x: x * 3)(jax.numpy.arange(5.0)).block_until_ready()
    print(json.dumps(dict(dir=jax.config.jax_compilation_cache_dir)))
    """
    out = _py(code, tmp_path / "a", SECOND=tmp_path / "b")
    assert out["dir"] == str(tmp_path / "b" / "xla")
    assert len(list((tmp_path / "a" / "xla").glob("*-cache"))) >= 1 and len(list((tmp_path / "b" / "xla").glob("*-cache"))) >= 1
    mine = _py("""
        import json, jax
        from jaxrt import cache
        print(json.dumps(dict(on=cache.enable_compilation_cache(), dir=jax.config.jax_compilation_cache_dir)))
    """, tmp_path / "c", JAX_COMPILATION_CACHE_DIR=tmp_path / "mine")
    assert mine == dict(mine, on=True, dir=str(tmp_path / "mine")) and not (tmp_path / "c").exists()


def test_scene_objects_come_from_the_cache_bit_identical(cdir, tmp_path):
    """A scene's objects (loaded, split and transformed meshes) are cached whole: the second build
    reads them (no mesh load, no trimesh), gives the same arrays and repeats the load's warnings; a
    changed file or transform is a miss."""
    from jaxrt import scene as S

    path = _obj(tmp_path / "ball.obj", degenerate=True)
    doc = {"camera": {"position": [0, 0, 4], "look_at": [0, 0, 0], "width": 8, "height": 8},
           "lights": [{"position": [1, 2, 3], "intensity": 5.0}],
           "materials": {"m": {"model": "lambert"}},
           "objects": [{"mesh": str(path), "material": "m", "scale": 0.5, "rotate": [10, 20, 30]},
                       {"primitive": "sphere", "material": "m", "translate": [1, 0, 0]}]}
    with pytest.warns(UserWarning, match="zero-area"):
        first = S.load(doc)
    before = cache.stats()
    with pytest.warns(UserWarning, match=f"{path}: removed 1 zero-area"):
        second = S.load(doc)
    d = _delta(before)
    assert d["hits"] >= 3 and d["misses"] == 0  # two objects and the BVH
    for a, b in zip(jax.tree.leaves(first.geometry), jax.tree.leaves(second.geometry)):
        assert np.asarray(a).dtype == np.asarray(b).dtype and np.array_equal(np.asarray(a), np.asarray(b))
    doc["objects"][1]["translate"] = [1, 0, 1e-3]
    before = cache.stats()
    S.load(doc)
    assert _delta(before)["misses"] == 2  # the moved sphere and the new BVH
    _obj(path, degenerate=False)
    before = cache.stats()
    S.load(doc)
    assert _delta(before)["misses"] >= 2  # the changed file's object (and its mesh) and the BVH


def test_cli_cache_clear_removes_ended_workers_files_and_keeps_a_listening_one(cdir, capsys):
    import argparse
    import socket

    from jaxrt.cli import cache as cli_cache

    cdir.mkdir(parents=True, exist_ok=True)
    dead = [cdir / f"worker-gone.{s}" for s in ("sock", "lock", "log")]
    for p in dead:
        p.write_bytes(b"")  # a socket file nobody listens on, as a killed worker leaves it
    live = cdir / "worker-up.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(live))
    server.listen(1)
    (cdir / "worker-up.lock").write_bytes(b"")
    (cdir / "worker-up.log").write_bytes(b"serving")
    try:
        p = argparse.ArgumentParser()
        cli_cache.configure(p)
        assert cli_cache.run(p.parse_args(["clear"])) == 0
        assert "files of 1 ended worker(s) removed" in capsys.readouterr().out
        assert not any(p.exists() for p in dead)
        assert live.exists() and (cdir / "worker-up.lock").exists() and (cdir / "worker-up.log").exists()
    finally:
        server.close()


def test_sharing_trees_reads_each_tree_once_within_the_block(cdir, monkeypatch):
    """`cache.sharing_trees()`: inside, a second `build_bvh` of the same arrays returns the first tree
    (no second read of the entry); other arrays get their own; outside, nothing is held."""
    from jaxrt.geometry import shapes

    m = shapes.sphere(subdivisions=2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    ref = cache.build_bvh(v, f)  # stored
    reads = []
    original = cache._read
    monkeypatch.setattr(cache, "_read", lambda *a: reads.append(1) or original(*a))
    with cache.sharing_trees():
        a = cache.build_bvh(v, f)
        with cache.sharing_trees():  # nested: the same block
            b = cache.build_bvh(v.copy(), f.copy())
        c = cache.build_bvh(v + np.float32(1), f)
    assert a is b and c is not a and len(reads) == 1
    d = cache.build_bvh(v, f)
    assert d is not a and cache._shared_trees is None and len(reads) == 2
    for x, y in zip(jax.tree.leaves(ref), jax.tree.leaves(d)):
        assert np.array_equal(np.asarray(x), np.asarray(y))
