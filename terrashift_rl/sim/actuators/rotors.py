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

from terrashift_rl.sim.actuators.base import register
from terrashift_rl.sim.actuators.patches import SlidingPatchActuator
from terrashift_rl.sim.types import Model

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.func
def spin_velocity(model: Model, amplitude: float, frame: wp.vec4, envelope: wp.vec3) -> wp.vec2:
    """One rotor's surface velocity at a column: its spin rate [rad/s] times its envelope
    times z x (the offset from its centre to the column, in metres) = (-dy, dx)."""
    return (amplitude * envelope[0] * model.cell_size) * wp.vec2(-envelope[2], envelope[1])


@register
class Rotors(SlidingPatchActuator):
    """Spinning Gaussian patches of surface (rotor tiles)."""

    name = "rotors"
    patch_velocity = spin_velocity

    def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
        high = config.max_rotor_speed
        return -high, high, config.rotor_speed_gain
