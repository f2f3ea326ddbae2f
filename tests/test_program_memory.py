"""Compiled programs and Linux's limit on a process's memory mappings (`jaxrt.programs.release`).

XLA:CPU maps each compiled program's machine code into mappings of its own and JAX keeps every
executable; at `vm.max_map_count` mappings LLVM aborts the process ("Unable to allocate section
memory"), which is how long-lived processes (the resident worker, test workers) died. Checked: the
count against mappings made here by hand, that `release` gives the mappings of compiled programs
back and later calls still agree, when `relieve` releases, the warning of a stored program's
compilation that released, the worker's release-then-retire rule, and a process that starts a few
hundred mappings short of the limit compiling programs until well past it without aborting.
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import programs, serve

REPO = Path(__file__).resolve().parents[1]

# Page-sized pieces of one anonymous mapping with alternating protections: the kernel cannot merge
# neighbours of different protections, so each piece is one more entry of /proc/self/maps.
_FILL = """
import ctypes
_libc = ctypes.CDLL(None)
_libc.mmap.restype = ctypes.c_void_p
_libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
_libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]

def fill(n):
    base = _libc.mmap(None, 4096 * (n + 1), 3, 0x22, -1, 0)  # PROT_READ|WRITE, MAP_PRIVATE|ANONYMOUS
    for k in range(0, n, 2):
        _libc.mprotect(base + k * 4096, 4096, 1)  # PROT_READ
    return base
"""


def _fill(n: int) -> None:
    ns: dict = {}
    exec(_FILL, ns)  # noqa: S102 -- the helper above, shared with the subprocess
    ns["fill"](n)


def _programs_of(n: int):
    fs = [jax.jit(lambda x, k=k: jnp.sin(x * k) @ jnp.cos(x.T + k) + jnp.exp(x).sum()) for k in range(n)]
    for f in fs:
        f(jnp.ones((4, 4))).block_until_ready()
    return fs


@pytest.mark.skipif(programs.mapped_regions() is None, reason="the kernel reports no mapping count (not Linux)")
def test_mapped_regions_counts_the_mappings_of_the_process():
    used, limit = programs.mapped_regions()
    assert 0 < used < limit
    assert limit == int(Path("/proc/sys/vm/max_map_count").read_text())
    _fill(400)
    after = programs.mapped_regions()[0]
    assert 398 <= after - used <= 420  # the 400 pieces (the end ones may merge with a neighbour)


@pytest.mark.skipif(programs.mapped_regions() is None, reason="the kernel reports no mapping count (not Linux)")
def test_release_gives_back_the_mappings_of_compiled_programs_and_calls_still_agree(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(tmp_path / "cache"))
    stored = programs.cached_jit(lambda x, *, k: jnp.cumsum(jnp.sin(x) * k), name="test.release",
                                 static_argnames=("k",))
    x = np.linspace(0, 1, 64, dtype=np.float32)
    ref = np.asarray(stored(x, k=3))
    compiled = stored.lower(x, k=3).compile()
    before = programs.mapped_regions()[0]
    fs = _programs_of(15)
    grown = programs.mapped_regions()[0] - before
    assert grown >= 30  # ~12 mappings per small program on XLA:CPU here; at least 2 anywhere
    assert programs.release() >= 1  # the stored program's executable
    assert programs.mapped_regions()[0] - before <= 0.2 * grown
    (entry,) = [p for p in stored._programs.values() if p is not programs._UNSTORABLE]
    assert entry._executable is None
    assert np.array_equal(np.asarray(compiled(x, k=3)), ref)  # a compiled object keeps its own
    assert entry._executable is None
    assert np.array_equal(np.asarray(stored(x, k=3)), ref)  # compiles again
    assert entry._executable is not None
    assert float(fs[3](jnp.ones((4, 4)))[0, 0]) == pytest.approx(
        float((jnp.sin(jnp.ones((4, 4)) * 3) @ jnp.cos(jnp.ones((4, 4)) + 3))[0, 0] + 16 * np.e), rel=1e-5)


def test_relieve_releases_past_its_share_only(monkeypatch):
    calls = []
    monkeypatch.setattr(programs, "release", lambda: calls.append(1) or 0)
    monkeypatch.setattr(programs, "mapped_regions", lambda: (75, 100))
    assert not programs.relieve(0.75) and calls == []
    monkeypatch.setattr(programs, "mapped_regions", lambda: (76, 100))
    assert programs.relieve(0.75) and calls == [1]
    monkeypatch.setattr(programs, "mapped_regions", lambda: None)  # no count: nothing to decide on
    assert not programs.relieve(0.0) and calls == [1]


def test_a_stored_program_past_the_share_releases_before_compiling_and_says_so_once(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXRT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setitem(programs._released, "warned", False)
    released = []
    monkeypatch.setattr(programs, "release", lambda: released.append(1) or 0)
    monkeypatch.setattr(programs, "mapped_regions", lambda: (90, 100))
    f = programs.cached_jit(lambda x, *, k: x * k + 1, name="test.relieve", static_argnames=("k",))
    x = np.arange(4, dtype=np.float32)
    with pytest.warns(RuntimeWarning, match=r"75% of the 100 memory mappings .*vm\.max_map_count"):
        assert np.array_equal(np.asarray(f(x, k=2)), x * 2 + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the second release is silent
        assert np.array_equal(np.asarray(f(x, k=5)), x * 5 + 1)
        assert np.array_equal(np.asarray(f(x, k=5)), x * 5 + 1)  # compiled: no check, no release
    assert released == [1, 1]


def test_the_worker_releases_past_its_share_and_retires_if_that_does_not_help(tmp_path, monkeypatch):
    w = serve._Worker(tmp_path / "s", 1.0, None, lambda argv: 0)
    counts = iter([(60, 100), (40, 100)])
    monkeypatch.setattr(programs, "mapped_regions", lambda: next(counts))
    monkeypatch.setattr(programs, "release", lambda: 0)
    assert not w.mappings_full() and w.counts["releases"] == 1  # released, back under: keeps serving
    monkeypatch.setattr(programs, "mapped_regions", lambda: (60, 100))
    assert w.mappings_full() and w.counts["releases"] == 2  # still past it: retires
    monkeypatch.setattr(programs, "mapped_regions", lambda: (50, 100))
    assert not w.mappings_full() and w.counts["releases"] == 2


@pytest.mark.slow  # ~15-35 s on 2 cores: 60 compilations, each after a release
@pytest.mark.skipif(programs.mapped_regions() is None, reason="the kernel reports no mapping count (not Linux)")
def test_a_process_near_the_mapping_limit_keeps_compiling_stored_programs(tmp_path):
    """Without `relieve` before each compilation this process aborts ("LLVM ERROR: Unable to allocate
    section memory") after about 10 programs: it starts 120 mappings short of the limit and each
    program takes ~12 here (60 programs would cross it at 2 each)."""
    code = _FILL + textwrap.dedent("""
        import jax.numpy as jnp, numpy as np
        from jaxrt import programs
        f = programs.cached_jit(lambda x, *, k: jnp.sin(x * k) @ jnp.cos(x.T + k), name="near.limit",
                                static_argnames=("k",))
        x = np.ones((4, 4), np.float32)
        float(f(x, k=-1)[0, 0])  # the libraries a first compilation loads (LAPACK through scipy) are mapped now
        used, limit = programs.mapped_regions()
        fill(limit - used - 120)
        total = sum(float(f(x, k=k)[0, 0]) for k in range(60))
        ref = sum(float((np.sin(x * k) @ np.cos(x.T + k))[0, 0]) for k in range(60))
        print("ok", abs(total - ref) <= 1e-4 * (1 + abs(ref)), programs.mapped_regions()[0] < limit)
    """)
    env = dict(os.environ, JAXRT_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-W", "ignore::RuntimeWarning", "-c", code], capture_output=True,
                       text=True, env=env, timeout=300)
    assert r.returncode == 0 and r.stdout.split() == ["ok", "True", "True"], (r.returncode, r.stdout, r.stderr[-2000:])
