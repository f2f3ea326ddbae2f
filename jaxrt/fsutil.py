"""Atomic output files: nothing is ever half-written; in a run over several hosts only process 0
writes (the others go through the same code and discard their temporary files)."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path


def writes() -> bool:
    """Whether this process writes output files: True except in processes other than process 0 of a
    run over several hosts (JAXRT_PROCESS_ID, or `jax.process_index()` once JAX is loaded, e.g.
    after a `jax.distributed.initialize` of one's own)."""
    from jaxrt import _config

    if _config.config().process_id != 0:
        return False
    jax = sys.modules.get("jax")
    if jax is not None and jax.distributed.is_initialized():
        return jax.process_index() == 0
    return True


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
        if not writes():
            return
        # mkstemp makes the file private (0600); give the result the mode a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def check_output(path: str | os.PathLike, suffix: str, flag: str) -> Path:
    """Validate a CLI output path before any work; `Outputs.add` without keeping it (see there)."""
    return Outputs().add(path, suffix, flag)


class _Temporaries(dict):
    """{output path: temporary path}, looked up by a str or a Path."""

    def __getitem__(self, path):
        return super().__getitem__(Path(path))


class Outputs:
    """Every output file of one command: checked before any work, written all together or not at all.

        outs = Outputs()
        exr = outs.add(args.output, ".exr", "-o")        # InputError now, before any work
        ...                                              # the work
        with outs.writing() as tmp:                      # tmp[exr]: a temporary file beside exr
            image.write_exr(tmp[exr], img)
        # all outputs renamed into place here, or (on any exception) none, old files untouched

    `add` checks the name (extension), that the path is not a directory, that its folder exists,
    and that a file can be created there (by creating and removing one: permission bits do not
    tell, e.g. for root or in /sys), and that no other output of the command names the same file.
    Failures are one-line InputErrors naming the option and the path.
    """

    def __init__(self):
        self.paths: list[Path] = []
        self._flags: dict[Path, str] = {}

    def add(self, path: str | os.PathLike | None, suffix: str, flag: str) -> Path | None:
        from jaxrt.errors import InputError

        if path is None:
            return None
        path = Path(path)
        shown = f"{flag} {path}"
        if path.suffix.lower() != suffix:
            raise InputError(f"{shown}: the file name must end in {suffix}")
        if path.is_dir():
            raise InputError(f"{shown}: is a directory; give a file name ending in {suffix}")
        folder = path.resolve().parent
        if not folder.is_dir():
            raise InputError(f"{shown}: output directory {folder} does not exist")
        key = folder / path.name
        if key in self._flags:
            raise InputError(f"{shown}: also given as {self._flags[key]}; each output needs its own file")
        try:
            fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=folder)
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise InputError(f"{shown}: cannot write in {folder}: {e.strerror or e}") from None
        self.paths.append(path)
        self._flags[key] = flag
        return path

    @contextlib.contextmanager
    def writing(self) -> Iterator[dict[Path, Path]]:
        """Yield {output path: temporary path beside it}; rename every temporary file onto its
        output after the block, or remove them all if the block (or a rename) fails, restoring
        any output a failed commit had already replaced."""
        tmps: dict[Path, Path] = _Temporaries()
        backups: dict[Path, Path] = {}
        done: list[Path] = []
        try:
            for p in self.paths:
                fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=p.suffix, dir=p.resolve().parent)
                os.close(fd)
                tmps[p] = Path(tmp)
            yield tmps
            if not writes():
                return
            umask = os.umask(0)
            os.umask(umask)
            for p, tmp in tmps.items():
                # mkstemp makes the file private (0600); give the result the mode a plain open() would
                os.chmod(tmp, 0o666 & ~umask)
                if p.exists():
                    fd, bak = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".old", dir=p.resolve().parent)
                    os.close(fd)
                    os.replace(p, bak)
                    backups[p] = Path(bak)
                os.replace(tmp, p)
                done.append(p)
        except BaseException:
            for p in done:
                p.unlink(missing_ok=True)
            for p, bak in backups.items():
                os.replace(bak, p)
            backups.clear()
            raise
        finally:
            for tmp in tmps.values():
                tmp.unlink(missing_ok=True)
            for bak in backups.values():
                bak.unlink(missing_ok=True)
