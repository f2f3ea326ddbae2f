"""Shading: the surface at a hit and its frames, material gathering (with textures), direct
lighting, and the AOVs every integrator returns.

Integrators import these public functions; none of them imports another integrator.
"""

from jaxrt.shading.aovs import NAMES as AOV_NAMES
from jaxrt.shading.aovs import build_aovs
from jaxrt.shading.surface import Surface

__all__ = ["AOV_NAMES", "Surface", "build_aovs"]
