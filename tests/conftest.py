"""Shared pytest fixtures."""

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The Stanford-mesh directory from $JAXRT_DATA; tests that need it skip only when it is unset."""
    d = os.environ.get("JAXRT_DATA")
    if not d:
        pytest.skip("JAXRT_DATA is not set: the Stanford meshes are not configured (CI sets it)")
    path = Path(d)
    assert path.is_dir(), f"JAXRT_DATA={d} is set but is not a directory"
    return path
