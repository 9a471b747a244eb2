"""Rotors: every patch is a spinning Gaussian patch of surface, a rotor tile.

The columns stay at rest and their surfaces slide in plane, turning about each patch's
centre: patch ``k`` with amplitude Omega_k [rad/s] adds Omega_k times its envelope times
z x (c - p_k) to the surface velocity of the column at c (p_k the patch's centre, the offset
in metres, the short way round a torus); the sum is clipped to ``max_surface_speed``. A sphere
on a turntable spinning at Omega rolls on a circle at 2 Omega / 7 (docs/physics.md), so a
rotor moves a sphere across its side, and two counter-rotating rotors either side of a sphere
throw it between them, as rollers do.
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
def compute_spin(
    model: Model,
    reset_mask: wp.array(dtype=wp.bool),
    use_mask: int,
    max_speed: float,
    position: wp.array2d(dtype=wp.vec2),
    amplitude: wp.array2d(dtype=float),
    frame: wp.array2d(dtype=wp.vec4),
    surface_velocity: wp.array3d(dtype=wp.vec2),
):
    """Sums the rotors' surface velocities at every column. Launch dim: [num_envs, G, G] as
    (env, iy, ix)."""
    e, iy, ix = wp.tid()
    if use_mask != 0 and not reset_mask[e]:
        return
    total = wp.vec2(0.0)
    for k in range(model.num_agents):
        w = envelope(model, position, frame, e, k, ix, iy)
        # z x (dx, dy) = (-dy, dx), the offset from cells to metres
        total += (amplitude[e, k] * w[0] * model.cell_size) * wp.vec2(-w[2], w[1])
    surface_velocity[e, iy, ix] = limited(total, max_speed)


class Rotors(SlidingPatchActuator):
    """Spinning Gaussian patches of surface (rotor tiles)."""

    name = "rotors"
    flow_kernel = compute_spin

    def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
        high = config.max_rotor_speed
        return -high, high, config.rotor_speed_gain
