"""PEP 562 lazy submodules for the packages' `__init__` (`brdfs`, `jaxrt`, `fitting`): an attribute
that names a submodule on disk is imported on first use, and anything else is an AttributeError
without importing anything (a probe such as IPython's `_repr_html_` or a misspelt name).

It lives in `brdfs` because both other packages already import `brdfs` and `brdfs` imports neither.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType

__all__ = ["submodule"]


def submodule(package: str, init_file: str, name: str) -> ModuleType:
    """`package.name` imported, where `name` is a public module or subpackage beside `init_file`
    (the package's `__init__.py`); else AttributeError, as a missing attribute would raise."""
    here = Path(init_file).parent
    if (not name.startswith("_") and name.isidentifier()
            and ((here / f"{name}.py").is_file() or (here / name / "__init__.py").is_file())):
        try:
            return importlib.import_module(f"{package}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{package}.{name}":
                raise
    raise AttributeError(f"module {package!r} has no attribute {name!r}")
