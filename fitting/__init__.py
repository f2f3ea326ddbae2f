"""fitting: recover BRDF parameters from target renders with optimistix.

`fit_images(shade, gbuffer, targets, model, ...)` is the renderer-independent core (see
`fitting.solve`); parameters move in an unconstrained space built from each model's declared bounds
(`fitting.transforms`); error metrics are in `fitting.metrics`.
"""

from fitting.solve import SOLVERS, FitResult, fit_images

__all__ = ["SOLVERS", "FitResult", "fit_images"]
