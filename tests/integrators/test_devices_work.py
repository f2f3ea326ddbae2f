"""Progressive path-tracing passes, fits, the measured-material study and several hosts, spread over
devices (`jaxrt._devices`, `render_tiles.accumulate`, `fitting.solve`'s `devices=`, JAXRT_COORDINATOR).

Each multi-device check runs in a fresh Python with four virtual CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=4``) and prints one JSON line. The references are
independent of the split: the one-device code paths (`integrators.accumulate`, the sequential
multi-start fit, the per-model fit matrix, the one-device study), closed forms (√x by a lane-dependent
number of Newton steps) and renders on other device counts. The default suite runs the cheap checks
(the batch splitter, the launch configuration, process-0-only output); the passes, the fits and the
two-process run compile several programs per device and are marked slow.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from jaxrt import _config, fsutil
from jaxrt.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"


def _run(code: str, *args: str, devices: int = 4, env: dict | None = None, timeout: int = 600) -> dict:
    e = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    e.update(env or {})
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], cwd=ROOT, env=e, capture_output=True,
                       text=True, timeout=timeout, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


# ---- the batch splitter (default suite: one small program) -------------------------------------------------

_BATCHED = r"""
import json
import numpy as np
import jax, jax.numpy as jnp
from jaxrt import _devices

def newton_sqrt(x, steps):
    # a while loop whose trip count differs per lane: lanes stop at their own step count
    def one(x, n):
        def body(c):
            y, k = c
            return 0.5 * (y + x / y), k + 1
        return jax.lax.while_loop(lambda c: c[1] < n, body, (jnp.maximum(x, 1.0), 0))
    return jax.vmap(one)(x, steps)

x = np.linspace(0.5, 40.0, 7).astype(np.float32)   # 7 problems: not a multiple of 3 or 4
steps = np.array([2, 30, 5, 30, 1, 30, 30], np.int32)
one = jax.tree.map(np.asarray, jax.jit(newton_sqrt)(x, steps))
out = {"devices": len(jax.devices())}
for n in (3, 4):
    devs = _devices.select(n)
    m = _devices.padded(len(x), devs)
    xs, ss = _devices.pad_rows((x, steps), m)
    y, k = _devices.batched(newton_sqrt, devs, (True, True), xs, ss)
    out[str(n)] = dict(rows=int(y.shape[0]), padded=m, equal=bool(np.array_equal(y[:7], one[0])),
                       steps=k[:7].tolist(), y=y[:7].tolist(), pad_same=bool(np.all(y[7:] == y[6])))
try:
    _devices.batched(newton_sqrt, _devices.select(4), (True, True), x, steps)
    out["unpadded"] = None
except ValueError as e:
    out["unpadded"] = str(e)
print(json.dumps(out))
"""


def test_batched_splits_independent_problems_over_devices():
    """`_devices.batched`: 7 problems padded to 9 rows on 3 devices and 8 on 4, each device running its
    own while loop; the rows come back in order, equal to the one-device program and to √x."""
    out = _run(_BATCHED)
    assert out["devices"] == 4
    for n, m in (("3", 9), ("4", 8)):
        r = out[n]
        assert r["padded"] == m and r["rows"] == m and r["pad_same"]
        assert r["equal"], r  # the same program on every device: the same floats
        assert r["steps"] == [2, 30, 5, 30, 1, 30, 30]
        x = np.linspace(0.5, 40.0, 7)
        done = np.array(r["steps"]) == 30  # converged lanes: √x to float32 rounding
        np.testing.assert_allclose(np.array(r["y"])[done], np.sqrt(x[done]), rtol=2e-7)
    assert "multiple of the device count" in out["unpadded"]


# ---- one device per core on a CPU: the command's default, and solvers that never starve the pool ----------

_STARVE = r"""
import json, time
import jax, jax.numpy as jnp
import numpy as np
from jaxrt import _config, _devices

def solve(a, b):
    # a vmapped loop of QR factorisations: jaxlib's batched LAPACK kernel fans out onto the intra-op
    # thread pool it runs on and waits for its tasks
    def one(a, b):
        def body(i, x):
            q, r = jnp.linalg.qr(a + 1e-3 * i * jnp.eye(a.shape[0], a.shape[1]))
            return x + jax.scipy.linalg.solve_triangular(r[: a.shape[1]], q.T @ b)[0]
        return jax.lax.fori_loop(0, 50, body, 0.0)
    return jax.vmap(one)(a, b)

devs = jax.devices()
rng = np.random.default_rng(0)
a = rng.normal(size=(64, 400, 8)).astype(np.float32)
b = rng.normal(size=(64, 400)).astype(np.float32)
one = np.asarray(jax.jit(solve)(a, b))
outs = [_devices.batched(solve, devs, (True, True), a, b) for _ in range(10)]
print(json.dumps(dict(devices=len(devs), cores=_config.cores(), concurrent=_devices.concurrent(devs),
                      equal=all(bool(np.array_equal(o, one)) for o in outs))))
"""


def test_solvers_split_over_one_cpu_device_per_core_do_not_wait_forever():
    """With one CPU device per core (the command's default), a batch of QR-based solves split over all of
    them by `_devices.batched` finishes, equal to the one-device program: at most cores − 1 programs run
    at once, so the pool keeps a thread for the tasks the LAPACK kernels wait on. With every device's
    program dispatched at once this stopped with its threads idle (the 120 s timeout below; seen with
    gdb in jaxlib's `ParallelBatchMap`)."""
    n = min(_config.cores(), _config.MAX_CPU_DEVICES)
    out = _run(_STARVE, devices=n, env={"XLA_FLAGS": "", "JAX_NUM_CPU_DEVICES": str(n)}, timeout=120)
    assert out["devices"] == n and out["concurrent"] == max(1, min(n, out["cores"] - 1))
    assert out["equal"]


class _Dev:
    def __init__(self, platform, i):
        self.platform, self.id = platform, i


@pytest.mark.parametrize("platform, cores, want", [("cpu", 2, 1), ("cpu", 4, 3), ("cpu", 16, 5), ("cpu", 1, 1),
                                                   ("gpu", 2, 5)])
def test_concurrent_solvers_leave_a_core_on_a_cpu(monkeypatch, platform, cores, want):
    from jaxrt import _devices

    monkeypatch.setattr(_config, "cores", lambda: cores)
    devs = [_Dev(platform, i) for i in range(5)]
    assert _devices.concurrent(devs) == want
    monkeypatch.setattr(_devices, "select", lambda devices=None, label="": tuple(devs))
    assert _devices.solver_devices() == tuple(devs[:want]) == _devices.solver_devices(" ALL ")
    assert _devices.solver_devices(5) == tuple(devs)  # an explicit count or list is kept


def test_commands_ask_for_one_cpu_device_per_core(monkeypatch):
    monkeypatch.setattr(_config, "cores", lambda: 12)
    env = _config.command_defaults({})
    assert env["JAX_NUM_CPU_DEVICES"] == str(_config.MAX_CPU_DEVICES) == "8"  # capped
    assert env["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"  # and the runtime defaults
    monkeypatch.setattr(_config, "cores", lambda: 2)
    assert _config.command_defaults({})["JAX_NUM_CPU_DEVICES"] == "2"
    assert _config.command_defaults({"JAX_NUM_CPU_DEVICES": "1"})["JAX_NUM_CPU_DEVICES"] == "1"  # set wins
    flags = {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false --xla_force_host_platform_device_count=3"}
    assert "JAX_NUM_CPU_DEVICES" not in _config.command_defaults(dict(flags))  # so does the XLA flag
    assert "JAX_NUM_CPU_DEVICES" not in _config.apply_runtime_defaults({})  # the Python API: JAX's default
    assert 1 <= _config.cores() <= (os.cpu_count() or 1)


@pytest.mark.slow  # 20 s on 2 cores: two fresh processes compile a render
def test_a_command_renders_on_one_cpu_device_per_core(tmp_path):
    """`jaxrt render` in a fresh process sees one CPU device per core (at most 8) and spreads the tiles over
    them; JAX_NUM_CPU_DEVICES=1 renders on one. Both images agree to the rounding of another XLA module
    (`jaxrt._devices`: the partitioned program)."""
    code = r"""
import json, sys
from jaxrt.cli import main
rc = main(["render", "spheres", "--width", "24", "--height", "16", "-q", "-o", sys.argv[1]])
import jax
print(json.dumps(dict(rc=rc, devices=len(jax.devices()), platform=jax.default_backend())))
"""
    outs = []
    for k, extra in enumerate(({}, {"JAX_NUM_CPU_DEVICES": "1"})):
        e = dict(os.environ, JAX_PLATFORMS="cpu", JAXRT_WORKER="off",
                 PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
        e.pop("JAX_NUM_CPU_DEVICES", None)
        e["XLA_FLAGS"] = ""
        e.update(extra)
        r = subprocess.run([sys.executable, "-c", textwrap.dedent(code), str(tmp_path / f"{k}.exr")], cwd=ROOT, env=e,
                           capture_output=True, text=True, timeout=600, check=False)
        assert r.returncode == 0, r.stderr[-3000:]
        outs.append(json.loads(r.stdout.strip().splitlines()[-1]))
    assert outs[0] == dict(rc=0, devices=min(_config.cores(), _config.MAX_CPU_DEVICES), platform="cpu")
    assert outs[1] == dict(rc=0, devices=1, platform="cpu")
    from jaxrt import image

    a, b = (np.asarray(image.read_exr(tmp_path / f"{k}.exr")) for k in range(2))
    assert a.shape == b.shape == (16, 24, 3) and a.max() > 0.1
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


# ---- several hosts: the launch configuration and process-0-only output ---------------------------------------


def test_process_variables_are_read_and_validated_in_config():
    c = _config.config({})
    assert (c.coordinator, c.process_count, c.process_id) == (None, 1, 0)
    c = _config.config({"JAXRT_COORDINATOR": " 10.0.0.1:1234 ", "JAXRT_PROCESS_COUNT": "4", "JAXRT_PROCESS_ID": "3"})
    assert (c.coordinator, c.process_count, c.process_id) == ("10.0.0.1:1234", 4, 3)
    assert _config.config({"JAXRT_COORDINATOR": "node-1.cluster:80", "JAXRT_PROCESS_COUNT": "1",
                           "JAXRT_PROCESS_ID": "0"}).coordinator == "node-1.cluster:80"
    assert {"JAXRT_COORDINATOR", "JAXRT_PROCESS_COUNT", "JAXRT_PROCESS_ID"} <= set(_config.VARIABLES)


@pytest.mark.parametrize("env, name, allowed", [
    ({"JAXRT_COORDINATOR": "10.0.0.1"}, "JAXRT_COORDINATOR", "host:port"),
    ({"JAXRT_COORDINATOR": "h:99999", "JAXRT_PROCESS_COUNT": "2", "JAXRT_PROCESS_ID": "0"}, "JAXRT_COORDINATOR",
     "1 to 65535"),
    ({"JAXRT_COORDINATOR": "h:1", "JAXRT_PROCESS_ID": "0"}, "JAXRT_PROCESS_COUNT", "1 or more"),
    ({"JAXRT_COORDINATOR": "h:1", "JAXRT_PROCESS_COUNT": "two", "JAXRT_PROCESS_ID": "0"}, "JAXRT_PROCESS_COUNT",
     "1 or more"),
    ({"JAXRT_COORDINATOR": "h:1", "JAXRT_PROCESS_COUNT": "2"}, "JAXRT_PROCESS_ID", "0 to 1"),
    ({"JAXRT_COORDINATOR": "h:1", "JAXRT_PROCESS_COUNT": "2", "JAXRT_PROCESS_ID": "2"}, "JAXRT_PROCESS_ID", "0 to 1"),
    ({"JAXRT_PROCESS_ID": "1"}, "JAXRT_PROCESS_ID", "JAXRT_COORDINATOR"),
    ({"JAXRT_PROCESS_COUNT": "2"}, "JAXRT_PROCESS_COUNT", "JAXRT_COORDINATOR"),
])
def test_bad_process_variables_are_one_line_errors(env, name, allowed):
    with pytest.raises(InputError) as e:
        _config.config(env)
    msg = str(e.value)
    assert msg.startswith(f"{name}=") and "\n" not in msg and allowed in msg, msg


def test_only_process_0_writes_outputs(tmp_path, monkeypatch):
    """Processes other than 0 go through the same writers and leave nothing behind; process 0 and a
    single process write atomically."""
    from jaxrt import image

    img = np.full((2, 3, 3), 0.5, np.float32)
    for pid, writes in (("1", False), ("0", True)):
        monkeypatch.setenv("JAXRT_COORDINATOR", "127.0.0.1:1")
        monkeypatch.setenv("JAXRT_PROCESS_COUNT", "2")
        monkeypatch.setenv("JAXRT_PROCESS_ID", pid)
        assert fsutil.writes() is writes
        d = tmp_path / pid
        d.mkdir()
        image.write_exr(d / "a.exr", img)  # atomic_path
        outs = fsutil.Outputs()
        outs.add(d / "b.json", ".json", "--out")
        with outs.writing() as tmp:
            Path(tmp[d / "b.json"]).write_text("{}")
        assert sorted(p.name for p in d.iterdir()) == (["a.exr", "b.json"] if writes else [])
    for name in ("JAXRT_COORDINATOR", "JAXRT_PROCESS_COUNT", "JAXRT_PROCESS_ID"):
        monkeypatch.delenv(name)
    assert fsutil.writes()


# ---- progressive path-tracing passes on 4 devices (slow: three compiled pass programs) ------------------------

_PASSES = r"""
import json, sys
import numpy as np
import jax
sys.path.insert(0, sys.argv[1])
import test_tiles as T
from jaxrt import integrators, render_tiles, scene as S
from jaxrt.errors import InputError

ps = S.load(T.path_doc(w=24, h=18, spp=3))
one = None
for _ in range(2):
    one = integrators.accumulate(ps, one)
p4 = render_tiles.plan(ps, memory="8G", devices=4)
p3 = render_tiles.plan(ps, memory="8G", devices=3)
four = three = None
for _ in range(2):
    four = render_tiles.accumulate(ps, four, use_plan=p4)
    three = render_tiles.accumulate(ps, three, use_plan=p3)
first = render_tiles.accumulate(ps, None, use_plan=p4)
A, B, C = (np.asarray(s.image, np.float64) for s in (one, four, three))
d = np.abs(A - B)
rel = d / np.maximum(np.abs(A), 1e-2)
solo = render_tiles.accumulate(ps, None, devices=1)
try:
    render_tiles.accumulate(S.load("spheres", overrides={"camera.width": 8, "camera.height": 6}), devices=4)
    err = None
except InputError as e:
    err = str(e)
print(json.dumps(dict(tiles=[p4.tiles, p3.tiles], shape=p4.shape, count=[int(four.count), int(four.passes)],
                      equal43=bool(np.array_equal(B, C)), beyond=float(np.mean(rel.max(-1) > 1e-4)),
                      mean=float(d.mean() / A.mean()), max=float(A.max()),
                      second_pass=float(np.abs(np.asarray(four.total) - 2 * np.asarray(first.total)).max()),
                      solo=bool(np.array_equal(np.asarray(solo.total), np.asarray(integrators.accumulate(ps).total))),
                      error=err)))
"""


@pytest.mark.slow  # 70 s cold on the loaded 2-core CPU: the pass program on 3 and 4 devices, one-device pass
def test_progressive_passes_on_4_and_3_devices_equal_the_one_device_passes():
    out = _run(_PASSES, str(TESTS))
    assert out["tiles"][0] % 4 and out["tiles"][0] >= 8  # 4 devices do not divide the tiles: an idle device
    assert out["shape"][2] == 3  # every tile holds all samples of its pixels
    assert out["count"] == [6, 2]
    assert out["equal43"]  # the same partitioned program on any number of devices >= 2
    # against one device: the rounding of another XLA module (`tests/test_tiles.py`'s bound)
    assert out["beyond"] <= 0.01 and out["mean"] <= 1e-5 and out["max"] > 0.1, out
    assert out["second_pass"] > 1e-3  # pass 1 has its own random stream, not pass 0 again
    assert out["solo"]  # devices=1 is `integrators.accumulate`, bit for bit
    assert "integrator" in out["error"] and "path" in out["error"]


# ---- fits on several devices (slow: the solvers compile once per device on a CPU) ------------------------------

_STUDY = r"""
import json
from fitting import study

# the measured-material study: 3 materials on 2 devices (padded to 4 lanes, 2 per device)
mats = ["merl/alum-bronze", "merl/white-paint", "merl/blue-acrylic"]
kw = dict(fit_resolution=(8, 6, 6), eval_resolution=(10, 8, 8), starts=3, max_steps=40, progress=False)
a = study.run(mats, ["ward"], **kw)
b = study.run(mats, ["ward"], devices=2, **kw)
print(json.dumps(dict(devices=[a.settings["devices"], b.settings["devices"]], batch=b.settings["batch"],
                      err=[[a.error(m, "ward"), b.error(m, "ward")] for m in mats],
                      params=[[a.fits[(m, "ward")].params, b.fits[(m, "ward")].params] for m in mats],
                      stderr=[a.fits[(m, "ward")].stderr for m in mats])))
"""


@pytest.mark.slow  # 90 s on the loaded 2-core CPU: the batch solver and Jacobians compile once per device
def test_study_on_2_devices_equals_one_device(brdf_data):
    st = _run(_STUDY)
    assert st["devices"] == [1, 2] and st["batch"] == 2  # 1 material per device and call on a CPU
    for (e1, e2), (p1, p2), se in zip(st["err"], st["params"], st["stderr"]):
        # the same lanes in another compiled program: the reported error agrees to rounding, and each
        # parameter well within its standard error (a poorly determined one moves along its valley)
        assert e2 == pytest.approx(e1, rel=1e-4)
        for k, v in p1.items():
            np.testing.assert_allclose(p2[k], v, rtol=1e-3, atol=0.1 * np.max(se.get(k, 0.0)) + 1e-6, err_msg=k)


_FITS = r"""
import json
import numpy as np
import brdfs
from fitting import setup as fs
from jaxrt.cli.fit import hidden_params

out = {}
# fit-matrix: the fits of each model to both targets split over 2 devices, against one fit after another
ov = {"camera.width": 24, "camera.height": 18}
names = ["lambert", "phong"]
setups = {m: fs.prepare("spheres", m, object="ward", overrides=[ov]) for m in names}
truths = {m: hidden_params(brdfs.get(m), seed=7 + i) for i, m in enumerate(names)}
opts = dict(starts=3, max_steps=60, progress=False)
out["matrix"] = [fs.cross_model_matrix(setups, truths, **opts).tolist(),
                 fs.cross_model_matrix(setups, truths, devices=2, **opts).tolist()]

# one fit's 5 starts on 2 devices (one padded row) against the starts one after another
s = setups["phong"]
target = np.asarray(fs.render_with(setups["lambert"], setups["lambert"].model.params(**truths["lambert"])))
r1, _ = fs.fit(None, target, "phong", setup=s, starts=5, max_steps=60, progress=False)
r2, _ = fs.fit(None, target, "phong", setup=s, starts=5, max_steps=60, progress=False, devices=2)
out["starts"] = [r.to_json() for r in (r1, r2)]

# one fit's nodes split over 3 devices (padded with weight-0 nodes), the partial images added by a psum
rn, _ = fs.fit(None, target, "phong", setup=s, starts=5, max_steps=60, progress=False, devices=3, split="nodes")
out["nodes"] = dict(fit=rn.to_json(), nodes=int(s.fitbuffer.pixel.shape[0]))
print(json.dumps(out))
"""


@pytest.mark.slow  # 160 s on the loaded 2-core CPU: each solver program compiles once per device
def test_fit_matrix_starts_and_split_nodes_on_devices_equal_one_device():
    out = _run(_FITS)
    m1, m2 = (np.array(m) for m in out["matrix"])
    assert np.all(np.diag(m1) < 1e-4) and np.all(np.diag(m2) < 1e-4)  # each model recovers its own target
    off = ~np.eye(2, dtype=bool)
    np.testing.assert_allclose(m2[off], m1[off], rtol=1e-4)
    assert m1[1, 0] > 100 * m1[1, 1]  # Lambert cannot imitate the Phong target: not a trivial matrix
    f1, f2 = out["starts"]
    assert f2["starts"] == f1["starts"] == 5 and f2["iterations"] == f1["iterations"]
    for k, v in f1["params"].items():
        np.testing.assert_allclose(f2["params"][k], v, rtol=1e-4, err_msg=k)
    assert f2["rmse"] == pytest.approx(f1["rmse"], rel=1e-3)
    fn = out["nodes"]["fit"]
    assert out["nodes"]["nodes"] % 3  # the nodes do not split evenly: padded
    # the same iterates up to the summation order of the psum: the same step counts and parameters
    assert fn["iterations"] == f1["iterations"] and fn["total_iterations"] == f1["total_iterations"]
    for k, v in f1["params"].items():
        np.testing.assert_allclose(fn["params"][k], v, rtol=1e-4, err_msg=k)
    assert fn["rmse"] == pytest.approx(f1["rmse"], rel=1e-3)


# ---- two processes on this host with jax.distributed (slow) ---------------------------------------------------

_HOST = r"""
import json, sys
import numpy as np
import jax
import jaxrt
from jaxrt import cli

joined = jaxrt.join_hosts()
pid = jax.process_index()
rc = cli.main(["render", "spheres", "--width", "40", "--height", "30", "-o", sys.argv[1] + f"/p{pid}.exr"])

# a batch of independent problems over the 4 devices of both processes: each computes its own
# devices' rows, and every process gets all rows in device order
import jax.numpy as jnp
from jaxrt import _devices

def affine(x, k):
    return jax.vmap(lambda a, b: a * 3.0 + b)(x, k)

x = np.arange(8, dtype=np.float32)
k = np.arange(8, dtype=np.float32) * 100.0
y = _devices.batched(affine, tuple(jax.devices()), (True, True), x, k)
print(json.dumps(dict(joined=joined, rc=rc, processes=jax.process_count(), devices=len(jax.devices()),
                      local=len(jax.local_devices()), batched=y.tolist())))
"""

_REFERENCE = r"""
import json, sys
import numpy as np
from jaxrt import cli, image
rc = cli.main(["render", "spheres", "--width", "40", "--height", "30", "-q", "--devices", "4", "-o", sys.argv[1] + "/one.exr"])
a, b = image.read_exr(sys.argv[1] + "/p0.exr"), image.read_exr(sys.argv[1] + "/one.exr")
print(json.dumps(dict(rc=rc, equal=bool(np.array_equal(a, b)), max=float(b.max()))))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # 80 s on the loaded 2-core CPU: two processes compile the render, then a reference
def test_two_processes_render_the_one_process_image_and_only_process_0_writes(tmp_path):
    """Two processes of 2 virtual CPU devices each join through JAXRT_COORDINATOR on localhost (the CPU
    backend's collectives, gloo), render over the 4 devices of both with the same command, and
    process 0 alone writes: its image equals a one-process render on 4 devices bit for bit."""
    port = _free_port()
    e = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
             JAXRT_COORDINATOR=f"127.0.0.1:{port}", JAXRT_PROCESS_COUNT="2")
    procs = [subprocess.Popen([sys.executable, "-c", textwrap.dedent(_HOST), str(tmp_path)], cwd=ROOT,
                              env=dict(e, JAXRT_PROCESS_ID=str(i)), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for i in range(2)]
    outs = []
    for p in procs:
        so, se = p.communicate(timeout=600)
        assert p.returncode == 0, se[-3000:]
        # The collectives' library writes its connection lines on the same stdout from C, at any time and
        # without regard to Python's buffer, so one may share a line with the result: decode the object that
        # starts at the result's first key and ignore what follows it.
        at = so.rindex('{"joined"')
        outs.append(json.JSONDecoder().raw_decode(so, at)[0])
        outs[-1]["reported"] = "40x30, 1 spp" in so
    assert [o.pop("reported") for o in outs] == [True, False]  # process 0 alone reports on stdout
    for o in outs:
        assert o.pop("batched") == [3.0 * i + 100.0 * i for i in range(8)]  # every row, in order, on both
        assert o == {"joined": True, "rc": 0, "processes": 2, "devices": 4, "local": 2}, o
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p0.exr"]  # process 1 wrote nothing, no temporaries
    ref = _run(_REFERENCE, str(tmp_path))
    assert ref["rc"] == 0 and ref["max"] > 0.1 and ref["equal"]


@pytest.mark.parametrize("argv, bad, allowed", [
    (["fit", "--demo", "-q"], "0", "1 or more"),
    (["fit-matrix", "--models", "lambert,phong", "-q"], "x", "1 or more"),
    (["fit-matrix", "--models", "lambert,phong", "-q"], "99", "from 1 to"),
    (["study", "--materials", "merl/alum-bronze", "--models", "ward", "-q"], "99", "from 1 to"),
])
def test_bad_devices_of_the_fitting_commands_are_one_line_errors(argv, bad, allowed, capsys, tmp_path,
                                                                 monkeypatch):
    from jaxrt import cli

    monkeypatch.chdir(tmp_path)
    rc = cli.main(argv + ["--devices", bad])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and f"error: --devices {bad}: must be" in err and allowed in err, err
    assert list(tmp_path.iterdir()) == []  # refused before any work or output
