"""Fixtures shared by the traversal tests."""

from __future__ import annotations

import pytest

from jaxrt.geometry import data
from jaxrt.geometry import mesh


@pytest.fixture(scope="module")
def bunny(data_dir):
    """The Stanford bunny, loaded from $JAXRT_DATA (skips where it is unset, as `data_dir` does)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("JAXRT_DATA", str(data_dir))
        return mesh.load(data.find("bunny"))
