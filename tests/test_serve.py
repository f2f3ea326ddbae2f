"""The resident worker (`jaxrt serve`, `jaxrt.serve`) and its thin client in `jaxrt.cli.main`.

One worker serves the module (a fresh cache folder, started over a stale socket file, stopped at the
end); the jobs are tiny renders. The reference for every result is the same command run in a
process of its own (JAXRT_WORKER=off), compared bit for bit.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from test_tiles import SCENE_TOML  # the Ctrl-C tests' scene: a sphere on a plane, several tiles in 8 MiB

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--width", "16", "--height", "12"]


def _env(cache: Path, **extra) -> dict:
    env = {**os.environ, "JAXRT_CACHE_DIR": str(cache), "JAXRT_WORKER": "use", **extra}
    return env


def _cli(env, *argv, timeout=300):
    return subprocess.run([sys.executable, "-m", "jaxrt.cli", *argv], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


def _status(env) -> dict | None:
    from jaxrt import serve

    return serve.request(b"S", _socket_path(env))


def _socket_path(env) -> Path:
    from jaxrt import serve

    return serve.socket_path(environ=env)


def _start_foreground(env, idle_timeout: float) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "jaxrt.cli", "serve", "--foreground", "--idle-timeout",
                             str(idle_timeout)], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    line = proc.stdout.readline()
    assert "ready on" in line, line + proc.stdout.read()
    return proc


@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    cache = tmp_path_factory.mktemp("c")
    env = _env(cache)
    path = _socket_path(env)
    # a socket file left by a worker that died: bound, never listened on, closed
    path.parent.mkdir(parents=True, exist_ok=True)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    with pytest.raises(ConnectionRefusedError):  # what the worker sees before it replaces the file
        probe.connect(str(path))
    probe.close()
    proc = _start_foreground(env, idle_timeout=600)
    try:
        yield {"env": env, "path": path, "proc": proc}
    finally:
        _cli(env, "serve", "--stop", timeout=60)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_a_stale_socket_is_replaced_and_private(worker):
    assert worker["path"].stat().st_mode & 0o777 == 0o600
    state = _status(worker["env"])  # the stale file refused connections; the worker's answers
    assert state is not None and state["pid"] == worker["proc"].pid


def test_render_through_the_worker_is_bit_identical_and_the_second_job_compiles_nothing(worker, tmp_path):
    env = worker["env"]
    before = _status(env)
    counts = []
    for k in (1, 2):
        r = _cli(env, "render", "spheres", *SMALL, "-o", str(tmp_path / f"w{k}.exr"), "--png", str(tmp_path / f"w{k}.png"))
        assert r.returncode == 0, r.stderr[-2000:]
        assert "rendering" in r.stderr  # the job's progress bar reaches the client's stderr
        assert re.search(r"spheres.toml: 16x12, .* wrote .*w%d.exr" % k, r.stdout), r.stdout
        counts.append(_status(env))
    # the reference, in a process of its own (after the worker's jobs, so that it finds their compiled programs)
    ref = _cli({**env, "JAXRT_WORKER": "off"}, "render", "spheres", *SMALL, "-o", str(tmp_path / "ref.exr"),
               "--png", str(tmp_path / "ref.png"))
    assert ref.returncode == 0, ref.stderr[-2000:]
    assert _status(env)["jobs"] == before["jobs"] + 2
    for k in (1, 2):
        for ext in ("exr", "png"):
            assert (tmp_path / f"w{k}.{ext}").read_bytes() == (tmp_path / f"ref.{ext}").read_bytes()
    assert counts[0]["jobs"] == before["jobs"] + 1 and counts[1]["jobs"] == before["jobs"] + 2  # ran in the worker
    # the second job traced and compiled nothing: every program came from the worker's memory
    assert counts[1]["compile_requests"] == counts[0]["compile_requests"]
    assert counts[1]["traces"] == counts[0]["traces"]


def test_bad_input_through_the_worker_is_the_same_one_line_and_exit_2(worker, tmp_path):
    env = worker["env"]
    argv = ("render", str(tmp_path / "missing.toml"), *SMALL)
    before = _status(env)["jobs"]
    here = _cli({**env, "JAXRT_WORKER": "off"}, *argv)
    there = _cli(env, *argv)
    assert _status(env)["jobs"] == before + 1
    assert (there.returncode, there.stdout, there.stderr) == (here.returncode, here.stdout, here.stderr)
    assert here.returncode == 2 and len(here.stderr.strip().splitlines()) == 1 and "missing.toml" in here.stderr
    bad_option = _cli(env, "render", "spheres", "--width", "many")
    assert bad_option.returncode == 2 and "invalid int value" in bad_option.stderr


def test_a_client_of_another_environment_runs_in_its_own_process(worker, tmp_path):
    env = worker["env"]
    before = _status(env)["jobs"]
    r = _cli({**env, "JAXRT_CACHE_DIR": str(tmp_path / "other")}, "render", str(tmp_path / "missing.toml"))
    assert r.returncode == 2 and "missing.toml" in r.stderr
    assert _status(env)["jobs"] == before


def _start_client(env, tmp_path, *argv):
    proc = subprocess.Popen([sys.executable, "-m", "jaxrt.cli", *argv], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    err = bytearray()

    def pump():
        while chunk := proc.stderr.read1(4096):
            err.extend(chunk)

    threading.Thread(target=pump, daemon=True).start()
    return proc, err


def test_busy_worker_sends_the_client_home_and_ctrl_c_is_forwarded(worker, tmp_path, monkeypatch):
    from jaxrt import serve

    env = worker["env"]
    before = _status(env)
    out = tmp_path / "out"
    out.mkdir()
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE_TOML)
    proc, err = _start_client(env, tmp_path, "render", str(scene), "--memory", "8M", "--spp", "32",
                              "-o", str(out / "big.exr"))
    t0 = time.monotonic()
    while not re.search(rb"\| *[1-9][0-9]*/[0-9]+ ", err):
        assert proc.poll() is None, err.decode(errors="replace")[-2000:]
        assert time.monotonic() - t0 < 240, err.decode(errors="replace")[-2000:]
        time.sleep(0.02)
    assert _status(env)["busy"]
    # the worker is busy: a second client is told so at once and runs the command itself
    for k in ("JAXRT_CACHE_DIR", "JAXRT_WORKER"):
        monkeypatch.setenv(k, env[k])
    assert serve.forward(["render", str(scene)], "render") is None
    assert _status(env)["busy_refused"] == before["busy_refused"] + 1
    t_sig = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rc = proc.wait(timeout=30)
    took = time.monotonic() - t_sig
    text = err.decode(errors="replace")
    assert rc == 130, text[-2000:]
    assert took < 3.0, took
    assert text.count("jaxrt: interrupted") == 1 and "Traceback" not in text
    assert list(out.iterdir()) == []  # nothing written
    after = _status(env)  # the worker survived the interrupt and is free again
    assert after is not None and not after["busy"] and after["jobs"] == before["jobs"] + 1


def test_idle_timeout_exits_and_removes_the_socket(tmp_path):
    env = _env(tmp_path / "c")
    path = _socket_path(env)
    proc = _start_foreground(env, idle_timeout=1.0)
    try:
        assert path.is_socket()
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert rc == 0 and not path.exists()
    r = _cli(env, "serve", "--status", timeout=60)
    assert r.returncode == 1 and "no worker" in r.stderr and r.stdout == ""


def test_the_socket_name_follows_what_a_warm_process_cannot_change(tmp_path):
    from jaxrt import serve

    base = {"JAXRT_CACHE_DIR": str(tmp_path), "PATH": "/usr/bin"}
    key = serve.worker_key(base)
    assert serve.worker_key(dict(base)) == key
    for change in ({"JAX_PLATFORMS": "cpu"}, {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"},
                   {"CUDA_VISIBLE_DEVICES": "1"}, {"JAXRT_CACHE_DIR": str(tmp_path / "x")}, {"JAXRT_CACHE": "off"}):
        assert serve.worker_key({**base, **change}) != key, change
    # the worker's process sets XLA_PYTHON_CLIENT_PREALLOCATE=false itself where unset: a client
    # whose environment lacks it and one that sets it to that value are the same; "true" is not
    assert serve.worker_key({**base, "XLA_PYTHON_CLIENT_PREALLOCATE": "true"}) != key
    for same in ({"JAXRT_DATA": "/data"}, {"JAXRT_DEBUG": "1"}, {"JAXRT_MEMORY": "1G"}, {"TERM": "dumb"},
                 {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}):
        assert serve.worker_key({**base, **same}) == key, same
    short = Path("/tmp/jx")  # a cache folder short enough that the socket lives in it (tmp_path may not be)
    assert serve.socket_path(environ={**base, "JAXRT_CACHE_DIR": str(short)}).parent == short
    long = {**base, "JAXRT_CACHE_DIR": str(tmp_path / ("d" * 120))}  # too long for a socket's address
    assert len(str(serve.socket_path(environ=long))) <= 100
    assert serve.socket_path(environ=long).parent != tmp_path / ("d" * 120)


@pytest.mark.slow  # a fit compiles its trace and solver: about a minute on 2 cores
def test_a_fit_through_the_worker_equals_the_fit_in_its_own_process(worker, tmp_path):
    env = worker["env"]
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE_TOML.replace("width = 256", "width = 16").replace("height = 256", "height = 12"))
    target = tmp_path / "target.exr"
    r = _cli({**env, "JAXRT_WORKER": "off"}, "render", str(scene), "-o", str(target))
    assert r.returncode == 0, r.stderr[-2000:]
    argv = ("fit", str(target), "--scene", str(scene), "--model", "phong", "--starts", "2", "--max-steps", "30", "-q")
    outs = []
    for where in ("worker", "off", "worker"):
        out = tmp_path / f"fit-{where}-{len(outs)}.json"
        r = _cli({**env, "JAXRT_WORKER": "use" if where == "worker" else "off"}, *argv, "--out", str(out))
        assert r.returncode == 0, r.stderr[-2000:]
        outs.append(json.loads(out.read_text()))
    drop = ("seconds", "time", "elapsed", "us_per")  # timings
    clean = [{k: v for k, v in o.items() if not any(d in k for d in drop)} for o in outs]
    assert clean[0] == clean[1] == clean[2]


def test_jaxrt_worker_start_starts_a_detached_worker_that_runs_the_job(tmp_path):
    env = _env(tmp_path / "c", JAXRT_WORKER="start")
    path = _socket_path(env)
    try:
        r = _cli(env, "render", str(tmp_path / "missing.toml"))
        assert r.returncode == 2 and "missing.toml" in r.stderr
        state = _status(env)
        assert state is not None and state["jobs"] == 1  # the job ran in the worker it started
        assert _cli(env, "serve", "--stop", timeout=60).returncode == 0
        t0 = time.monotonic()
        while path.exists() and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        assert not path.exists()
    finally:
        if path.exists():
            _cli(env, "serve", "--stop", timeout=60)


def test_a_worker_that_dies_during_the_job_gives_one_line_and_exit_1(tmp_path):
    """A stand-in worker on the socket takes the job, writes a line of output and dies (closes the
    connection without an exit code): the client says so in one line and exits 1, without running
    the job again."""
    import struct

    env = _env(tmp_path / "c")
    path = _socket_path(env)
    path.parent.mkdir(parents=True, exist_ok=True)  # (a long tmp_path puts the socket in the temporary folder)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(1)
    seen = {}

    def fake():
        conn, _ = server.accept()
        kind, n = struct.unpack(">cI", conn.recv(5, socket.MSG_WAITALL))
        seen["kind"], seen["job"] = kind, json.loads(conn.recv(n, socket.MSG_WAITALL))
        line = b"partial output\n"
        conn.sendall(struct.pack(">cI", b"O", len(line)) + line)
        conn.close()

    t = threading.Thread(target=fake, daemon=True)
    t.start()
    try:
        r = _cli(env, "render", str(tmp_path / "scene.toml"), "--width", "8", timeout=120)
    finally:
        t.join(10)
        server.close()
        path.unlink()
    assert seen["kind"] == b"J" and seen["job"]["argv"] == ["render", str(tmp_path / "scene.toml"), "--width", "8"]
    assert seen["job"]["cwd"] == str(REPO) and seen["job"]["env"]["JAXRT_CACHE_DIR"] == str(tmp_path / "c")
    assert r.returncode == 1 and r.stdout == "partial output\n"
    assert len(r.stderr.strip().splitlines()) == 1 and "stopped during the job" in r.stderr


def test_auto_mode_starts_a_worker_only_for_a_command_typed_at_a_terminal():
    from jaxrt import serve

    assert serve.wants_worker("start", {}, {}) == serve.DEFAULT_IDLE_TIMEOUT
    tty = {"stdin": True, "stderr": True}
    assert serve.wants_worker("auto", {}, tty) == serve.AUTO_IDLE_TIMEOUT
    for mode, environ, streams in (("auto", {"CI": "true"}, tty), ("auto", {}, {"stdin": False, "stderr": True}),
                                   ("auto", {}, {"stdin": True, "stderr": False}), ("use", {}, tty), ("off", {}, tty)):
        assert serve.wants_worker(mode, environ, streams) is None, (mode, environ, streams)


@pytest.mark.slow  # starts a worker process; 16 s on 2 cores
def test_default_mode_starts_a_worker_from_a_terminal_and_not_from_a_pipe(tmp_path):
    """JAXRT_WORKER unset (auto), CI unset: the same command from a pipe runs in its own process and
    leaves nothing behind; typed at a terminal (a pseudo-terminal for stdin and stderr) it starts a
    worker, says so in one line, and the worker ran the job."""
    import pty

    env = {k: v for k, v in _env(tmp_path / "c").items() if k not in ("JAXRT_WORKER", "CI")}
    argv = ["render", "spheres", *SMALL, "-q"]
    r = subprocess.run([sys.executable, "-m", "jaxrt.cli", *argv, "--out", str(tmp_path / "pipe.exr")], cwd=REPO,
                       env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stderr == "", r.stderr[-2000:]
    assert _status(env) is None and not _socket_path(env).exists()
    primary, secondary = pty.openpty()
    try:
        proc = subprocess.run([sys.executable, "-m", "jaxrt.cli", *argv, "--out", str(tmp_path / "tty.exr")],
                              cwd=REPO, env=env, stdin=secondary, stdout=subprocess.PIPE, stderr=secondary,
                              timeout=300)
        os.close(secondary)
        said = b""
        while True:
            try:
                chunk = os.read(primary, 4096)
            except OSError:
                break
            if not chunk:
                break
            said += chunk
    finally:
        os.close(primary)
    try:
        assert proc.returncode == 0, said[-2000:]
        assert b"starting a resident worker" in said, said[-2000:]
        status = _status(env)
        assert status is not None and status["jobs"] == 1, status
        assert (tmp_path / "pipe.exr").read_bytes() == (tmp_path / "tty.exr").read_bytes()
    finally:
        _cli(env, "serve", "--stop", timeout=60)
