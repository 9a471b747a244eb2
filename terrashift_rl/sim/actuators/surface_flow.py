"""Surface flow: every patch is a Gaussian patch of surface sliding along its orientation.

A conveyor or ciliary surface: the columns stay at rest and their surfaces slide in plane.
Patch ``k`` with amplitude A_k [m/s] and orientation theta_k adds A_k times its envelope
along (cos theta_k, sin theta_k) to every column's surface velocity; the sum is clipped to
``max_surface_speed``. The spheres are driven by the friction of their contacts with the
moving surface: a sphere put at rest on a surface sliding at u slips until it rolls, at
2u/7 (docs/physics.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import warp as wp

from terrashift_rl.sim.actuators.base import register
from terrashift_rl.sim.actuators.patches import SlidingPatchActuator
from terrashift_rl.sim.types import Model

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.func
def flow_velocity(model: Model, amplitude: float, frame: wp.vec4, envelope: wp.vec3) -> wp.vec2:
    """One patch's surface velocity at a column: its amplitude [m/s] times its envelope, along
    its orientation (cos theta, sin theta)."""
    return (amplitude * envelope[0]) * wp.vec2(frame[0], frame[1])


@register
class SurfaceFlow(SlidingPatchActuator):
    """Gaussian patches of in-plane surface velocity along each patch's orientation."""

    name = "surface_flow"
    patch_velocity = flow_velocity

    def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
        high = config.max_surface_speed
        return -high, high, config.surface_speed_gain
