"""fitting: recover BRDF parameters from target renders or measured BRDFs with optimistix.

`fit_images(shade, gbuffer, targets, model, ...)` is the renderer-independent core and
`solve_batch(...)` the same solve vmapped over many target sets (see `fitting.solve`); parameters
move in an unconstrained space built from each model's declared bounds (`fitting.transforms`); error
metrics are in `fitting.metrics`. `fitting.brdf_space` fits analytic models to measured materials in
BRDF space and `fitting.study` runs Ngan et al. 2005's study over the measured databases
(`fitting.study_image`: the same study in image space, on renders of the measured materials).
"""

import importlib

from brdfs import lazy as _lazy

__all__ = ["SOLVERS", "FitResult", "Solution", "fit_images", "solve_batch"]


# `import fitting` loads neither JAX nor the solvers: each public name and submodule is imported on
# first use (PEP 562), so a command or a script pays only for what it calls.
def __getattr__(name: str):
    if name in __all__:
        value = getattr(importlib.import_module("fitting.solve"), name)
        globals()[name] = value
        return value
    return _lazy.submodule(__name__, __file__, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
