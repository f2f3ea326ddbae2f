"""Atomic output files: nothing is ever half-written."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to `path`; rename it onto `path` only if the block succeeds.

    The temporary file keeps `path`'s suffix (writers such as OpenEXR and matplotlib pick the
    format from it). On any exception the temporary file is removed and `path` is untouched.
    """
    path = Path(path)
    if path.parent and not path.parent.exists():
        raise FileNotFoundError(f"{path}: output directory {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix, dir=path.parent or "."
    )
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        # mkstemp makes the file private (0600); give the result the mode a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def check_output(path: str | os.PathLike, suffix: str, flag: str) -> Path:
    """Validate a CLI output path before any work: the right extension and an existing directory.

    Raises InputError naming the option (`flag`), the path and what is allowed.
    """
    from jaxrt.errors import InputError

    path = Path(path)
    if path.suffix.lower() != suffix:
        raise InputError(f"{flag} {path}: the file name must end in {suffix}")
    if not path.resolve().parent.is_dir():
        raise InputError(f"{flag} {path}: output directory {path.resolve().parent} does not exist")
    return path
