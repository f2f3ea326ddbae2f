"""fitting: recover BRDF parameters from target renders or measured BRDFs with optimistix.

`fit_images(shade, gbuffer, targets, model, ...)` is the renderer-independent core and
`solve_batch(...)` the same solve vmapped over many target sets (see `fitting.solve`); parameters
move in an unconstrained space built from each model's declared bounds (`fitting.transforms`); error
metrics are in `fitting.metrics`. `fitting.brdf_space` fits analytic models to measured materials in
BRDF space and `fitting.study` runs Ngan et al. 2005's study over the measured databases
(`fitting.study_image`: the same study in image space, on renders of the measured materials).
"""

from fitting.solve import SOLVERS, FitResult, Solution, fit_images, solve_batch

__all__ = ["SOLVERS", "FitResult", "Solution", "fit_images", "solve_batch"]
