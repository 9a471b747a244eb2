"""Wavelets, the paper's actuator: every patch is a Gaussian bump (or basin) of the columns.

A patch's amplitude is a height [m]; the column heights are the sum of the patches'
envelopes times their amplitudes at the column centres, clipped to +-``max_column_height``.
The columns move from the last tick's heights to these over the tick, so their vertical
velocity lifts, tilts and throws the spheres.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import warp as wp

from terrashift_rl.sim.actuators.base import register
from terrashift_rl.sim.actuators.patches import PatchActuator, envelope
from terrashift_rl.sim.types import Model

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig
    from terrashift_rl.sim.simulator import Simulator

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.kernel
def compute_heights(
    model: Model,
    reset_mask: wp.array(dtype=wp.bool),
    use_mask: int,
    keep_velocity: int,
    position: wp.array2d(dtype=wp.vec2),
    amplitude: wp.array2d(dtype=float),
    frame: wp.array2d(dtype=wp.vec4),
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
):
    """Sums the wavelets at every column. Launch dim: [num_envs, G, G] as (env, iy, ix).

    With ``keep_velocity`` the old heights move to ``height_prev`` (the columns then move
    between the two over the tick); otherwise both get the new heights (columns at rest).
    """
    e, iy, ix = wp.tid()
    if use_mask != 0 and not reset_mask[e]:
        return
    total = float(0.0)
    for k in range(model.num_agents):
        total += amplitude[e, k] * envelope(model, position, frame, e, k, ix, iy)[0]
    hmax = model.max_column_height
    h = wp.clamp(total, -hmax, hmax)
    if keep_velocity != 0:
        height_prev[e, iy, ix] = height[e, iy, ix]
    else:
        height_prev[e, iy, ix] = h
    height[e, iy, ix] = h


@register
class Wavelets(PatchActuator):
    """Gaussian wavelets of the column heights (the paper's actuator)."""

    name = "wavelets"
    moves_columns = True
    moves_surface = False

    def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
        high = config.max_amplitude
        return config.min_amplitude_ratio * high, high, config.amplitude_gain

    def load(self, device: wp.context.Device) -> None:
        super().load(device)
        wp.load_module(compute_heights.module, device=device)

    def launch_surface(self, sim: Simulator, *, reset: bool) -> None:
        d, g = sim.data, sim.config.grid_size
        wp.launch(
            compute_heights,
            dim=(sim.num_envs, g, g),
            inputs=[
                sim.model,
                d.reset_mask,
                int(reset),
                int(not reset),
                d.agent_position,
                d.agent_amplitude,
                d.agent_frame,
                d.column_height_prev,
                d.column_height,
            ],
        )
