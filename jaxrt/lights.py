"""Point lights.

A point light of radiant intensity I [W/sr] at position x_l gives a surface point p the
irradiance E = I·cosθ/d² (Größler & Zettwitz, "An interactive ray tracing system based on Nvidia OptiX", 2015, eq. 3), with d = |x_l − p| and θ the angle between the
surface normal and wi = (x_l − p)/d. Positions and intensities are traced arrays: moving or
dimming a light never recompiles; the number of lights is static.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


class PointLights(eqx.Module):
    """L point lights: position (L, 3) [scene units], intensity (L, 3) linear RGB [W/sr]."""

    position: Float[Array, "L 3"]
    intensity: Float[Array, "L 3"]

    @property
    def count(self) -> int:
        return self.position.shape[0]


def incident(
    lights: PointLights, p: Float[Array, "*batch 3"]
) -> tuple[Float[Array, "*batch L 3"], Float[Array, "*batch L"], Float[Array, "*batch L 3"]]:
    """Direction to, distance to, and unoccluded radiant flux density from every light.

    Args:
        p: shading points (..., 3).
    Returns:
        wi: (..., L, 3) unit vectors from p towards each light;
        dist: (..., L) distances [scene units];
        scale: (..., L, 3) I/d² [W/(m²·sr)·sr = W/m² per unit cosθ]; multiply by cosθ for E.
    """
    delta = lights.position - p[..., None, :]
    # written out: XLA:CPU runs a reduction over an axis of 3 as a slow library (YNNPACK) fusion
    d2 = delta[..., 0] * delta[..., 0] + delta[..., 1] * delta[..., 1] + delta[..., 2] * delta[..., 2]
    # a light exactly on the surface would give 0/0; such a point receives nothing
    safe = d2 > 1e-20
    d2s = jnp.where(safe, d2, 1.0)
    dist = jnp.sqrt(d2s)
    wi = jnp.where(safe[..., None], delta / dist[..., None], 0.0)
    scale = jnp.where(safe[..., None], lights.intensity / d2s[..., None], 0.0)
    return wi, jnp.where(safe, dist, 0.0), scale


class AreaLights(eqx.Module):
    """Emissive triangles: any material may emit (scene-file `emission = [r, g, b]`).

    Attributes:
        emission: (M, 3) RGB radiance [W/(m²·sr)] per material (0 for non-emitters). A triangle
            emits on the side its winding's normal points to (one-sided, as in pbrt and Mitsuba).
        prims: (E,) int32 faces whose material emits at build time; E is static. The sampling
            table (areas and the CDF by area·luminance(emission)) is derived from the current
            vertices and emission values inside the integrator (`jaxrt.integrators.common.emitter_table`), so it
            never goes stale when a value changes.
    """

    emission: Float[Array, "M 3"]
    prims: Int[Array, " E"]

    @property
    def count(self) -> int:
        return self.prims.shape[0]
