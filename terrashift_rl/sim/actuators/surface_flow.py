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

from terrashift_rl.sim.actuators.patches import SlidingPatchActuator, envelope, limited
from terrashift_rl.sim.types import Model

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.kernel
def compute_flow(
    model: Model,
    reset_mask: wp.array(dtype=wp.bool),
    use_mask: int,
    max_speed: float,
    position: wp.array2d(dtype=wp.vec2),
    amplitude: wp.array2d(dtype=float),
    frame: wp.array2d(dtype=wp.vec4),
    surface_velocity: wp.array3d(dtype=wp.vec2),
):
    """Sums the patches' flows at every column. Launch dim: [num_envs, G, G] as (env, iy, ix)."""
    e, iy, ix = wp.tid()
    if use_mask != 0 and not reset_mask[e]:
        return
    total = wp.vec2(0.0)
    for k in range(model.num_agents):
        f = frame[e, k]
        weight = amplitude[e, k] * envelope(model, position, frame, e, k, ix, iy)[0]
        total += weight * wp.vec2(f[0], f[1])
    surface_velocity[e, iy, ix] = limited(total, max_speed)


class SurfaceFlow(SlidingPatchActuator):
    """Gaussian patches of in-plane surface velocity along each patch's orientation."""

    name = "surface_flow"
    flow_kernel = compute_flow

    def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
        high = config.max_surface_speed
        return -high, high, config.surface_speed_gain
