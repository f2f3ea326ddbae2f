"""A resident worker for the `jaxrt` command: a warm process that runs commands for thin clients.

Every `jaxrt` process pays a fixed start-up cost before its first pixel: importing JAX (1.5-2 CPU s
on a small machine), starting the device runtime (about 2 s on a GPU), loading the stored programs
and reading cached scenes. `jaxrt serve` starts a process that pays it once and then runs the
commands of later `jaxrt` invocations in itself, with everything it has loaded and compiled kept in
memory; the client (`jaxrt.cli.main`) imports no JAX when a worker takes its job.

When. `JAXRT_WORKER=auto` (the default) hands a command to a running worker, and where none runs
starts one only for a command typed at a terminal outside CI (`wants_worker`): there the next
command follows soon, and scripts, pipes, tests and CI never leave a process behind. One line says
that a worker started; it exits after `AUTO_IDLE_TIMEOUT` seconds without a job (`jaxrt serve`
started by hand: `--idle-timeout`, 900 s by default). It holds only the memory its jobs used: jaxrt
turns JAX's preallocation of most of a GPU's memory off (`jaxrt._config.RUNTIME_DEFAULTS`).
`use` only uses a running worker, `start` starts one for any command, `off` never uses one.

Where and which. The worker listens on a Unix socket (mode 0600) named by `worker_key()`: a hash of
what a warm process cannot change for a job: the Python executable, jaxrt's version, where its
packages are and the modification times and sizes of their source files (an edited checkout never
talks to an old worker), and the environment variables JAX, the device runtime or jaxrt read when
they start (`jaxrt._config.WORKER_KEY_VARIABLES` and every JAX_*, XLA_*, ... variable). A client
whose key differs finds no socket and runs the command itself. The socket is in the cache folder
(`jaxrt.cache.cache_dir()`), or where that path would be too long for a socket or the caches are
off, in a private folder of the temporary directory. A socket file left by a worker that died is
detected (connecting fails) and replaced.

One job at a time. The client sends its arguments, working directory, JAXRT_* variables, terminal
size and which of its streams are terminals; the worker runs `jaxrt.cli.execute(argv)` in its main
thread with those (restoring its own directory and variables afterwards), streams the job's stdout
and stderr back as they are written (progress bars included) and returns the exit code. A client
that finds the worker busy runs the command itself rather than wait. Ctrl-C in the client is
forwarded and the job stops as it does in its own process: the KeyboardInterrupt arrives in the
job's main thread (a render that cannot reach a tile boundary within its grace time exits the
process with 130, the worker with it, as an in-process render exits; the client then exits 130). If
the worker dies during a job for any other reason, the client prints one line and exits with 1
rather than run the job again itself: the job may have written part of its output to the terminal
and a job that killed the worker (memory) would most likely do it again, after the same wait.

Not through the worker: `view` (a window belongs to the user's own process), `serve`, `cache`
(`clear` must not remove files under a process that holds them open; `info` needs no JAX), and
runs over several hosts (JAXRT_COORDINATOR).

Bounded memory: the worker keeps the compiled programs of the jobs it ran (that is its point); it
retires (stops listening, removes its socket and exits) after `MAX_JOBS` jobs or when its resident
memory exceeds `max_rss` after a job, and the next `jaxrt serve` starts a fresh one. Compiled
programs also take memory mappings, of which Linux allows a process `vm.max_map_count` (at the
limit the compiler aborts the process: `jaxrt.programs`): past `RELEASE_AT` of them after a job the
worker drops its compiled programs (`jaxrt.programs.release`; later jobs compile again from the
persistent cache), and retires where that does not bring it back under. Results: the
worker runs the same code on the same compiled programs with the same configuration as a process of
its own, so images and fits are bit-identical to in-process runs (tested); warnings shown once per
process (a cache folder that cannot be written) are shown once per worker.

`jaxrt serve --status` reports the worker's counters: jobs run, jobs refused as busy, and JAX's
compile requests, persistent-cache hits and traces (`jax.monitoring` events) since it started.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from jaxrt import _config

__all__ = ["AUTO_IDLE_TIMEOUT", "DEFAULT_IDLE_TIMEOUT", "LOCAL_COMMANDS", "MAX_JOBS", "forward", "remove_stale", "request",
           "serve", "socket_path", "start", "wants_worker", "worker_key"]

#: Seconds a worker waits for a job before it exits.
DEFAULT_IDLE_TIMEOUT = 900.0
#: The same for a worker that `JAXRT_WORKER=auto` started without being asked (shorter: nobody chose
#: to keep it).
AUTO_IDLE_TIMEOUT = 600.0
#: Jobs after which a worker retires (its compiled programs and cached scenes are freed with it).
MAX_JOBS = 200
#: the share of the process's memory-mapping limit above which the worker releases its compiled
#: programs after a job (lower than `jaxrt.programs.RELEASE_AT`: between jobs nothing is running)
RELEASE_AT = 0.5
#: Commands a client never hands to a worker (see the module docstring).
LOCAL_COMMANDS = ("view", "serve", "cache")
#: Seconds `start` waits for a new worker to accept connections (importing JAX, starting devices).
START_TIMEOUT = 120.0

# Messages: one type byte and a 4-byte big-endian length, then the payload.
# client -> worker: J job (JSON), I interrupt, S status, Q stop
# worker -> client: O stdout bytes, E stderr bytes, X exit (JSON), B busy, S status (JSON)
_HEADER = struct.Struct(">cI")
_SOCKET_PATH_MAX = 100  # sun_path holds 108 bytes on Linux, 104 on macOS, with the NUL
_PACKAGES = ("jaxrt", "brdfs", "fitting")
# names of the compile-time events this worker counts (`jax.monitoring`)
_EVENTS = {"/jax/core/compile/backend_compile_duration": "compile_requests",
           "/jax/compilation_cache/cache_hits": "persistent_cache_hits",
           "/jax/core/compile/jaxpr_trace_duration": "traces"}


# ---------------------------------------------------------------------------------------------
# naming


def _sources() -> list[tuple[str, int, int]]:
    """(path, mtime in ns, size) of every source file of jaxrt, brdfs and fitting."""
    root = Path(__file__).resolve().parents[1]
    out = []
    for pkg in _PACKAGES:
        stack = [root / pkg]
        while stack:
            try:
                entries = list(os.scandir(stack.pop()))
            except OSError:
                continue
            for e in entries:
                if e.is_dir(follow_symlinks=False):
                    if e.name != "__pycache__":
                        stack.append(Path(e.path))
                elif e.name.endswith((".py", ".cc", ".h")):
                    st = e.stat()
                    out.append((e.path, st.st_mtime_ns, st.st_size))
    return sorted(out)


def worker_key(environ=None) -> str:
    """A hash of what a running worker cannot change for a job (see the module docstring)."""
    import jaxrt

    # the defaults a worker's own process applies before JAX starts count as set in the client too
    env = _config.command_defaults(dict(os.environ if environ is None else environ))
    names = set(_config.WORKER_KEY_VARIABLES) | {k for k in env if k.startswith(_config.WORKER_KEY_PREFIXES)}
    key = {"python": sys.executable, "prefix": sys.prefix, "version": jaxrt.__version__, "sources": _sources(),
           "environment": {k: env.get(k) for k in sorted(names)}}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]


def socket_path(cfg: _config.Config | None = None, environ=None) -> Path:
    """Where the worker of this environment listens (whether or not one does)."""
    cfg = _config.config(environ) if cfg is None else cfg
    name = f"worker-{worker_key(environ)}.sock"
    if cfg.cache and len(str(cfg.cache_dir / name)) <= _SOCKET_PATH_MAX:
        return cfg.cache_dir / name
    import tempfile

    return Path(tempfile.gettempdir()) / f"jaxrt-{os.getuid()}" / name


def _private_folder(folder: Path) -> None:
    """Create `folder` (0700 where created here) and refuse one that another user owns."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = folder.stat()
    if st.st_uid != os.getuid():
        raise OSError(f"{folder} belongs to another user")


# ---------------------------------------------------------------------------------------------
# messages


def _send(sock: socket.socket, kind: bytes, payload: bytes = b"", lock: threading.Lock | None = None) -> None:
    data = _HEADER.pack(kind, len(payload)) + payload
    if lock is None:
        sock.sendall(data)
    else:
        with lock:
            sock.sendall(data)


def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf.extend(chunk)
    return bytes(buf)


def _recv(sock: socket.socket) -> tuple[bytes, bytes] | None:
    """(type, payload) of the next message, or None at the end of the connection."""
    head = _recv_exact(sock, _HEADER.size)
    if head is None:
        return None
    kind, n = _HEADER.unpack(head)
    payload = _recv_exact(sock, n) if n else b""
    return None if payload is None else (kind, payload)


def _connect(path: Path, timeout: float | None = None) -> socket.socket | None:
    """A connection to the worker at `path`, or None where none listens there."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(path))
    except OSError:
        s.close()
        return None
    s.settimeout(None)
    return s


def remove_stale(folder: Path) -> int:
    """Delete the files (socket, lock, log) of workers in `folder` that no longer listen; returns how
    many workers' files went. A listening worker's files stay. The socket goes under its lock, as a
    starting worker removes a dead one's, so a worker starting at the same moment keeps its own."""
    import fcntl

    removed = 0
    try:
        locks = sorted(folder.glob("worker-*.lock"))
    except OSError:
        return 0
    for lock in locks:
        sock = lock.with_suffix(".sock")
        try:
            with open(lock, "a") as lock_file:
                fcntl.flock(lock_file, fcntl.LOCK_EX)
                probe = _connect(sock, timeout=2.0)
                if probe is not None:
                    probe.close()
                    continue
                for p in (sock, lock.with_suffix(".log"), lock):
                    with contextlib.suppress(FileNotFoundError):
                        p.unlink()
        except OSError:
            continue
        removed += 1
    return removed


def request(kind: bytes, path: Path | None = None, timeout: float = 10.0) -> dict | None:
    """Send a status (S) or stop (Q) request; the worker's JSON answer, or None where none listens."""
    s = _connect(socket_path() if path is None else path, timeout)
    if s is None:
        return None
    with s:
        s.settimeout(timeout)
        _send(s, kind)
        try:
            msg = _recv(s)
        except OSError:
            return None
    return json.loads(msg[1]) if msg is not None and msg[1] else None


# ---------------------------------------------------------------------------------------------
# the client


def forward(argv: list[str], command: str | None) -> int | None:
    """Run `jaxrt ARGV` in a matching worker; its exit code, or None where the caller runs it itself
    (JAXRT_WORKER=off, several hosts, a local command, no worker running, the worker busy)."""
    if command is None or command in LOCAL_COMMANDS:
        return None
    try:
        cfg = _config.config()
    except Exception:  # a bad variable: the command, run in this process, reports it in one line
        return None
    if cfg.worker == "off" or cfg.coordinator is not None:
        return None
    path = socket_path(cfg)
    sock = _connect(path)
    if sock is None:
        want = wants_worker(cfg.worker, os.environ, {n: _isatty(getattr(sys, n)) for n in ("stdin", "stderr")})
        if want is None:
            return None
        if cfg.worker == "auto":
            print(f"jaxrt: starting a resident worker, so that later commands skip JAX's start-up (it exits after "
                  f"{want / 60:.0f} idle minutes; `jaxrt serve --stop` ends it, JAXRT_WORKER=off runs "
                  f"commands without one)", file=sys.stderr, flush=True)
        if start(path, idle_timeout=want) is None:
            return None
        sock = _connect(path)
        if sock is None:
            return None
    with sock:
        return _client(sock, argv, path)


def wants_worker(mode: str, environ, isatty: dict) -> float | None:
    """Whether a command that found no running worker starts one: its idle timeout in seconds, or None.

    `start` always does. `auto` (the default) does only for a command a person typed at a terminal
    (stdin and stderr are terminals) outside continuous integration (no ``CI`` variable), since that is
    where a second command follows soon and waits for the first's start-up: JAX's import and the
    device runtime's start cost 1-2.5 s of every process (~1.3 s on an H200 before the first array),
    which a warm worker pays once. Scripts, pipes, test runs and CI never leave a process behind.
    """
    if mode == "start":
        return DEFAULT_IDLE_TIMEOUT
    if mode == "auto" and isatty.get("stdin") and isatty.get("stderr") and not environ.get("CI"):
        return AUTO_IDLE_TIMEOUT
    return None


def _client(sock: socket.socket, argv: list[str], path: Path) -> int | None:
    import shutil

    size = shutil.get_terminal_size()
    job = {"argv": list(argv), "cwd": os.getcwd(),
           "env": {k: v for k, v in os.environ.items() if k.startswith("JAXRT_")},
           "columns": size.columns, "lines": size.lines,
           "isatty": {name: _isatty(getattr(sys, name)) for name in ("stdin", "stdout", "stderr")}}
    out = {b"O": sys.stdout, b"E": sys.stderr}
    interrupted = False
    try:
        _send(sock, b"J", json.dumps(job).encode())
    except OSError:
        return None
    while True:
        try:
            msg = _recv(sock)
        except KeyboardInterrupt:
            if interrupted:  # a second Ctrl-C: leave now (the worker stops the job when the connection closes)
                print("jaxrt: interrupted", file=sys.stderr, flush=True)
                return 130
            interrupted = True
            with contextlib.suppress(OSError):
                _send(sock, b"I")
            continue
        except OSError:
            msg = None
        if msg is None:
            if interrupted:  # the job exited the worker on Ctrl-C, as it exits its own process
                return 130
            print(f"jaxrt: the worker ({path}) stopped during the job; run the command again "
                  f"(JAXRT_WORKER=off runs it without a worker)", file=sys.stderr, flush=True)
            return 1
        kind, payload = msg
        if kind in out:
            stream = out[kind]
            stream.flush()
            buf = getattr(stream, "buffer", None)
            if buf is not None:
                buf.write(payload)
                buf.flush()
            else:
                stream.write(payload.decode(errors="replace"))
                stream.flush()
        elif kind == b"X":
            return int(json.loads(payload)["code"])
        elif kind == b"B":
            return None


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def start(path: Path | None = None, idle_timeout: float = DEFAULT_IDLE_TIMEOUT,
          timeout: float = START_TIMEOUT) -> Path | None:
    """Start a detached worker for this environment and wait until it accepts jobs; its socket, or
    None where it did not come up in `timeout` seconds (its log, beside the socket, says why)."""
    path = socket_path() if path is None else path
    _private_folder(path.parent)
    log = path.with_suffix(".log")
    cmd = [sys.executable, "-m", "jaxrt.cli", "serve", "--foreground", "--idle-timeout", str(idle_timeout)]
    env = {**os.environ, "JAXRT_WORKER": "off"}
    with open(log, "ab") as f:
        # started in this directory, so that `python -m` finds the same jaxrt as this process (the
        # directory is the first entry of sys.path); in a session of its own, so that a Ctrl-C typed
        # at the terminal reaches the client only (which forwards it to the job)
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=f, stderr=f, env=env, start_new_session=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        s = _connect(path)
        if s is not None:
            s.close()
            return path
        if proc.poll() is not None:  # it exited: another worker won the socket, or it failed
            s = _connect(path)
            if s is not None:
                s.close()
                return path
            return None
        time.sleep(0.05)
    return None


# ---------------------------------------------------------------------------------------------
# the worker


class _Stream(io.TextIOBase):
    """A job's stdout or stderr: each write goes to the client at once."""

    def __init__(self, sock, kind: bytes, lock: threading.Lock, tty: bool, gone: threading.Event):
        self._sock, self._kind, self._lock, self._tty, self._gone = sock, kind, lock, tty, gone

    @property
    def encoding(self):
        return "utf-8"

    @property
    def errors(self):
        return "replace"

    def writable(self):
        return True

    def isatty(self):
        return self._tty

    def write(self, s):
        if s and not self._gone.is_set():
            try:
                _send(self._sock, self._kind, s.encode("utf-8", "replace"), self._lock)
            except OSError:
                self._gone.set()
        return len(s)

    def flush(self):
        pass


class _Worker:
    def __init__(self, path: Path, idle_timeout: float, max_rss: int | None, execute: Callable[[list[str]], int]):
        self.path, self.idle_timeout, self.max_rss, self.execute = path, idle_timeout, max_rss, execute
        self.jobs: list = []
        self.cv = threading.Condition()
        self.busy = False
        self.stopping = False
        self.job_running = False
        self.forwarded = False
        self.counts = {"jobs": 0, "busy_refused": 0, "releases": 0, **{v: 0 for v in _EVENTS.values()}}
        self.started = time.time()

    # -- the listening thread: answers status and stop at once, hands jobs to the main thread
    def accept_loop(self, server: socket.socket) -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            threading.Thread(target=self.first_message, args=(conn,), daemon=True).start()

    def first_message(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(10.0)
            msg = _recv(conn)
            conn.settimeout(None)
        except OSError:
            conn.close()
            return
        if msg is None:
            conn.close()
            return
        kind, payload = msg
        with conn if kind != b"J" else contextlib.nullcontext():
            if kind == b"S":
                with contextlib.suppress(OSError):
                    _send(conn, b"S", json.dumps(self.status()).encode())
            elif kind == b"Q":
                with self.cv:
                    self.stopping = True
                    self.cv.notify_all()
                with contextlib.suppress(OSError):
                    _send(conn, b"S", json.dumps(self.status()).encode())
            elif kind == b"J":
                with self.cv:
                    if self.busy or self.stopping:
                        self.counts["busy_refused"] += 1
                        refuse = True
                    else:
                        self.busy, refuse = True, False
                        self.jobs.append((conn, json.loads(payload)))
                        self.cv.notify_all()
                if refuse:
                    with contextlib.suppress(OSError):
                        _send(conn, b"B")
                    conn.close()

    def status(self) -> dict:
        with self.cv:
            return {"pid": os.getpid(), "socket": str(self.path), "busy": self.busy, "uptime_s": time.time() - self.started,
                    "idle_timeout_s": self.idle_timeout, "rss_bytes": _rss(), **self.counts}

    def on_event(self, event: str, *args, **kwargs) -> None:
        name = _EVENTS.get(event)
        if name is not None:
            with self.cv:
                self.counts[name] += 1

    # -- the main thread
    def run(self) -> None:
        last = time.monotonic()
        while True:
            with self.cv:
                while not self.jobs and not self.stopping:
                    left = self.idle_timeout - (time.monotonic() - last)
                    if left <= 0:
                        return
                    self.cv.wait(min(left, 1.0))
                if not self.jobs:
                    return  # asked to stop
                conn, job = self.jobs.pop(0)
            try:
                self.run_job(conn, job)
            except KeyboardInterrupt:  # an interrupt that arrived as the job ended
                pass
            finally:
                with contextlib.suppress(OSError):
                    conn.close()
                with self.cv:
                    self.busy = False
                    self.counts["jobs"] += 1
                    jobs = self.counts["jobs"]
                last = time.monotonic()
            if jobs >= MAX_JOBS or (self.max_rss is not None and _rss() > self.max_rss) or self.mappings_full():
                return  # retire: the next `jaxrt serve` starts a fresh worker

    def mappings_full(self) -> bool:
        """Past `RELEASE_AT` of the mapping limit: release the compiled programs; True (retire) where
        the process is still past it afterwards."""
        from jaxrt import programs

        if not programs.relieve(RELEASE_AT):
            return False
        with self.cv:
            self.counts["releases"] += 1
        m = programs.mapped_regions()
        return m is not None and m[0] > RELEASE_AT * m[1]

    def run_job(self, conn: socket.socket, job: dict) -> None:
        lock, gone = threading.Lock(), threading.Event()
        tty = job.get("isatty", {})
        out = _Stream(conn, b"O", lock, bool(tty.get("stdout")), gone)
        err = _Stream(conn, b"E", lock, bool(tty.get("stderr")), gone)
        main_id = threading.main_thread().ident

        def listen():  # Ctrl-C from the client, or the client gone: interrupt the job's main thread
            while True:
                try:
                    msg = _recv(conn)
                except OSError:
                    msg = None
                if msg is not None and msg[0] != b"I":
                    continue
                if msg is None:
                    gone.set()
                with self.cv:
                    if self.job_running:
                        self.forwarded = True
                        signal.pthread_kill(main_id, signal.SIGINT)
                if msg is None:
                    return

        saved_env = {k: v for k, v in os.environ.items() if k.startswith("JAXRT_") or k in ("COLUMNS", "LINES")}
        saved_cwd = os.getcwd()
        saved = sys.stdout, sys.stderr, sys.stdin
        code = 1
        try:
            for k in saved_env:
                if k.startswith("JAXRT_") and not _is_key_variable(k):
                    del os.environ[k]
            os.environ.update({k: v for k, v in job.get("env", {}).items()
                               if k.startswith("JAXRT_") and not _is_key_variable(k)})
            os.environ["JAXRT_WORKER"] = "off"
            os.environ["COLUMNS"], os.environ["LINES"] = str(job.get("columns", 80)), str(job.get("lines", 24))
            os.chdir(job["cwd"])
            sys.stdout, sys.stderr, sys.stdin = out, err, io.StringIO()
            with self.cv:
                self.job_running = True
            threading.Thread(target=listen, daemon=True).start()
            try:
                code = self.execute(list(job["argv"]))
            except SystemExit as e:  # argparse: --help, a bad option
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
                if not isinstance(e.code, (int, type(None))):
                    print(e.code, file=sys.stderr)
            except KeyboardInterrupt:
                print("jaxrt: interrupted", file=sys.stderr)
                code = 130
            except BaseException:  # a bug in the job: its traceback goes to the client, the worker goes on
                import traceback

                traceback.print_exc()
                code = 1
            finally:
                with self.cv:
                    self.job_running = False
        finally:
            sys.stdout, sys.stderr, sys.stdin = saved
            with contextlib.suppress(OSError):
                os.chdir(saved_cwd)
            for k in [k for k in os.environ if k.startswith("JAXRT_") or k in ("COLUMNS", "LINES")]:
                if k not in saved_env:
                    del os.environ[k]
            os.environ.update(saved_env)
        if not gone.is_set():
            with contextlib.suppress(OSError):
                _send(conn, b"X", json.dumps({"code": int(code)}).encode(), lock)


def _is_key_variable(name: str) -> bool:
    return name in _config.WORKER_KEY_VARIABLES or name.startswith(_config.WORKER_KEY_PREFIXES)


def _rss() -> int | None:
    """This process's resident memory in bytes (Linux), or None."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def _default_max_rss() -> int | None:
    """Half the machine's memory."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (ValueError, OSError, AttributeError):
        return None


def serve(execute: Callable[[list[str]], int], idle_timeout: float = DEFAULT_IDLE_TIMEOUT, *,
          warm_up: Callable[[], None] | None = None, ready: Callable[[Path], None] | None = None,
          max_rss: int | None = None) -> int:
    """Run a worker in this process: each job is `execute(argv) -> exit code` (`jaxrt.cli.execute`),
    run in the main thread. Returns when it has been idle for `idle_timeout` seconds, is asked to
    stop, or retires: 0; or 1 at once where another worker already listens for this environment.
    `warm_up()` runs before it listens (imports, device start); `ready(path)` once it accepts jobs."""
    import fcntl

    path = socket_path()
    _private_folder(path.parent)
    if warm_up is not None:
        warm_up()
    worker = _Worker(path, idle_timeout, _default_max_rss() if max_rss is None else max_rss, execute)
    import jax.monitoring

    jax.monitoring.register_event_listener(worker.on_event)
    jax.monitoring.register_event_duration_secs_listener(worker.on_event)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    with open(path.with_suffix(".lock"), "a") as lock_file:
        fcntl.flock(lock_file, fcntl.LOCK_EX)  # one starter at a time decides whether the socket is stale
        probe = _connect(path, timeout=2.0)
        if probe is not None:
            probe.close()
            server.close()
            print(f"jaxrt serve: a worker already listens on {path}", file=sys.stderr)
            return 1
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # a socket left by a worker that died
        old = os.umask(0o177)
        try:
            server.bind(str(path))
        finally:
            os.umask(old)
        os.chmod(path, 0o600)
        server.listen(8)
    def on_sigint(signum, frame):
        # Ctrl-C forwarded by a client, or typed at a foreground worker's terminal: stops the job as it
        # stops a process of its own; one that arrives after its job ended is dropped
        forwarded, worker.forwarded = worker.forwarded, False
        if worker.job_running or not forwarded:
            raise KeyboardInterrupt

    def on_sigterm(signum, frame):
        with worker.cv:
            worker.stopping = True
            worker.cv.notify_all()
        if worker.job_running:
            raise KeyboardInterrupt  # the job stops as on Ctrl-C; then the worker exits

    signal.signal(signal.SIGINT, on_sigint)
    signal.signal(signal.SIGTERM, on_sigterm)
    threading.Thread(target=worker.accept_loop, args=(server,), name="jaxrt-serve-accept", daemon=True).start()
    if ready is not None:
        ready(path)
    try:
        worker.run()
    except KeyboardInterrupt:
        pass
    finally:
        with open(path.with_suffix(".lock"), "a") as lock_file:
            # the socket goes under the lock a starter takes, so it cannot remove a successor's socket
            fcntl.flock(lock_file, fcntl.LOCK_EX)
            server.close()
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    return 0
