"""User-facing errors.

`InputError` is raised for bad input (a malformed scene file, a missing mesh, a parameter out of
bounds, a target image of the wrong size). Its message names the file/field and what is allowed,
and the CLI prints it as one line instead of a traceback.
"""


class InputError(ValueError):
    """Bad user input; the message is complete and meant to be shown as is."""
