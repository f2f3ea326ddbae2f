"""Shared pytest fixtures, and a fresh cache folder for the whole run.

The suite must pass with empty caches and never depend on warm ones: unless JAXRT_CACHE_DIR is
set (CI sets a fresh one), the run gets a new temporary folder, shared by the xdist workers (they
inherit the environment), so compiled programs and built scenes are reused within the run only.
"""

import os
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# The CLI subprocesses and `main` calls of the suite run in their own process, never in a resident
# worker (`jaxrt serve`) that may run on this machine; the worker tests turn it on where they mean to.
os.environ["JAXRT_WORKER"] = "off"

if not os.environ.get("JAXRT_CACHE_DIR"):
    os.environ["JAXRT_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxrt-test-cache-")


@pytest.fixture(scope="module", autouse=True)
def _compiled_programs_within_the_mapping_limit():
    """An xdist worker runs hundreds of test modules in one process, and every program they compile
    keeps its machine code mapped: past Linux's `vm.max_map_count` LLVM aborts the worker
    (`jaxrt.programs`). Between modules, past 40 % of the limit, the compiled programs are dropped
    (a module's own compilation counts are never disturbed: nothing is dropped inside one)."""
    yield
    if "jax" in sys.modules:
        from jaxrt import programs

        programs.relieve(0.4)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The Stanford-mesh directory from $JAXRT_DATA; tests that need it skip only when it is unset."""
    d = os.environ.get("JAXRT_DATA")
    if not d:
        pytest.skip("JAXRT_DATA is not set: the Stanford meshes are not configured (CI sets it)")
    path = Path(d)
    assert path.is_dir(), f"JAXRT_DATA={d} is set but is not a directory"
    return path


@pytest.fixture(scope="session")
def brdf_data() -> Path:
    """The folder of the measured-BRDF archives, found through $JAXRT_DATA (the data root, its meshes/
    folder or the brdfs/ folder itself). Skips only when JAXRT_DATA is unset; when it is set, missing
    or corrupt archives fail the test with the lookup's message."""
    d = os.environ.get("JAXRT_DATA")
    if not d:
        pytest.skip("JAXRT_DATA is not set: the measured BRDFs are not configured (CI sets it)")
    from brdfs import measured_data
    from jaxrt.errors import InputError

    try:
        paths = [measured_data.find_archive(c) for c in measured_data.ARCHIVES]
    except InputError as e:
        pytest.fail(f"JAXRT_DATA={d} is set but the measured BRDFs are not usable: {e}")
    return paths[0].parent
