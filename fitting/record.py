"""The record of one analytic model fitted to one measured material, shared by the BRDF-space and
image-space studies (`fitting.brdf_space.BrdfFit`, `fitting.study_image.ImageFit`), whose tables,
JSON files and plots read the same fields."""

from __future__ import annotations

import dataclasses

__all__ = ["SOLVER_FIELDS", "FitRecord"]

# The fields copied from the solver's result (`fitting.solve.Solution` or `FitResult`) unchanged.
SOLVER_FIELDS = ("params", "stderr", "fixed", "at_bound", "converged", "iterations", "total_iterations", "starts",
                 "starts_at_best", "condition_number", "ill_conditioned", "correlated")


@dataclasses.dataclass
class FitRecord:
    """One fit's result; subclasses add what their space measures beside it."""

    material: str
    model: str
    metric: str
    unit: str  # of `error`
    error: float  # E of `metric` at the fitted parameters
    errors: dict[str, float]  # every error the space reports, at the fitted parameters
    fit_error: float  # what the solver minimised, in `unit`
    params: dict[str, list[float] | float]
    stderr: dict[str, list[float] | float]
    tied: dict[str, str]  # parameter -> the parameter it was set equal to
    fixed: list[str]
    at_bound: dict[str, str]  # label -> "lower" | "upper"
    converged: bool
    iterations: int
    total_iterations: int
    starts: int
    starts_at_best: int
    condition_number: float
    ill_conditioned: bool
    correlated: list[tuple[str, str, float]]

    @classmethod
    def from_solution(cls, solution, **fields):
        """The record of `solution` (anything with the SOLVER_FIELDS attributes) and the other `fields`."""
        return cls(**{k: getattr(solution, k) for k in SOLVER_FIELDS}, **fields)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)
