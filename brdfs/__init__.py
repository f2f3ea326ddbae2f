"""brdfs: analytic reflectance models as pure, differentiable JAX functions (being built)."""
