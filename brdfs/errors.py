"""User-facing errors, shared by the whole project.

`InputError` is raised for bad input (a malformed scene file, a missing mesh, a parameter out of
bounds, a target image of the wrong size). Its message names the file/field and what is allowed,
and the CLI prints it as one line instead of a traceback. It lives in the lowest layer (the BRDF
library depends on nothing else of the project), and `jaxrt.errors` re-exports it.
"""

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad user input; the message is complete and meant to be shown as is."""
