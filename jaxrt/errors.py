"""User-facing errors: `InputError` (one line naming the file or field and what is allowed; the CLI
prints it with exit code 2). Defined in the dependency-free `brdfs.errors`, which every layer of the
project can import without importing the renderer."""

from brdfs.errors import InputError

__all__ = ["InputError"]
