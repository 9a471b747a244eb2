"""Scripted scenes: set column heights, place spheres, step the physics, read states back.

A scripted scene bypasses the agents and the episode logic (goals, respawns, reward), so
tests and tutorials can pose exact physical situations.
"""

from __future__ import annotations

import torch

from terrashift_rl.sim.actuators import ACTUATORS
from terrashift_rl.sim.config import TerraShiftConfig
from terrashift_rl.sim.simulator import Simulator


class ScriptedScene:
    """Columns, surface velocities and spheres under direct control.

    Args:
        config: scene parameters; ``num_objects`` is the number of sphere slots.
        num_envs: number of independent scenes.
        device: torch/Warp device.

    Example:
        >>> import torch
        >>> scene = ScriptedScene(TerraShiftConfig(column_shape="box", num_objects=1, num_goals=1))
        >>> scene.place_spheres(torch.tensor([[0.0, 0.0, 0.3]]))
        >>> scene.step(ticks=60)  # one second
        >>> z = scene.sphere_position[0, 0, 2].item()
        >>> abs(z - (0.12 + 0.075)) < 0.002  # resting on the flat column tops
        True
    """

    def __init__(
        self,
        config: TerraShiftConfig | None = None,
        *,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
    ):
        self.sim = Simulator(config, num_envs=num_envs, device=device)
        self.config = self.sim.config
        self.time = 0.0
        """Simulated time since construction [s]."""
        self.sim.view("column_height").zero_()
        self.sim.view("column_height_prev").zero_()
        self.sim.view("sphere_active").zero_()

    # --- state ----------------------------------------------------------------------------
    @property
    def sphere_position(self) -> torch.Tensor:
        """Sphere centres [m], shape [num_envs, M, 3] (a copy)."""
        return self.sim.view("sphere_position").clone()

    @property
    def sphere_velocity(self) -> torch.Tensor:
        """Sphere velocities [m/s], shape [num_envs, M, 3] (a copy)."""
        return self.sim.view("sphere_velocity").clone()

    @property
    def sphere_angular_velocity(self) -> torch.Tensor:
        """Sphere angular velocities [rad/s], shape [num_envs, M, 3] (a copy)."""
        return self.sim.view("sphere_angular_velocity").clone()

    @property
    def column_heights(self) -> torch.Tensor:
        """Column wave heights [m], shape [num_envs, G(y), G(x)] (a copy)."""
        return self.sim.view("column_height").clone()

    # --- control --------------------------------------------------------------------------
    def set_column_heights(self, heights: torch.Tensor | float) -> None:
        """Sets the column heights [m] reached at the end of the next tick.

        The columns move there linearly during that tick, so a change of ``dh`` is felt by
        touching spheres as a vertical column velocity ``dh * physics_hz``. Heights outside
        +-max_column_height raise ``ValueError``.
        """
        target = self.sim.view("column_height")
        heights = torch.as_tensor(heights, dtype=target.dtype, device=target.device)
        heights = heights.expand_as(target)
        limit = self.config.max_column_height
        if heights.abs().max() > limit + 1e-9:
            raise ValueError(f"column heights must lie in [-{limit}, {limit}] m")
        target.copy_(heights)

    def set_surface_velocity(self, velocity: torch.Tensor) -> None:
        """Sets the in-plane velocity [m/s] with which each column's surface slides, shape
        [num_envs, G(y), G(x), 2] or broadcastable to it; it holds until set again. Needs an
        actuator family that slides the surface (``ValueError`` otherwise)."""
        if not self.sim.actuator.moves_surface:
            raise ValueError(
                f"the {self.config.actuator!r} actuator does not slide the surface; choose one "
                f"of {[name for name, family in ACTUATORS.items() if family.moves_surface]}"
            )
        target = self.sim.view("surface_velocity")
        target.copy_(torch.as_tensor(velocity, dtype=target.dtype).expand_as(target))

    def place_spheres(
        self,
        positions: torch.Tensor,
        velocities: torch.Tensor | None = None,
        angular_velocities: torch.Tensor | None = None,
    ) -> None:
        """Puts spheres at ``positions`` [m], shape [num_envs, n, 3] or [n, 3] with n <= M.

        Slots beyond ``n`` are emptied. Velocities [m/s] and angular velocities [rad/s] default
        to zero.
        """
        n_env, m = self.sim.num_envs, self.config.num_objects
        positions = torch.as_tensor(positions, dtype=torch.float32)
        if positions.dim() == 2:
            positions = positions.expand(n_env, *positions.shape)
        if positions.dim() != 3 or positions.shape[-1] != 3 or positions.shape[1] > m:
            raise ValueError(
                f"positions must have shape [num_envs, n <= {m}, 3] or [n, 3], got "
                f"{tuple(positions.shape)}"
            )
        count = positions.shape[1]
        for name, value in (
            ("sphere_position", positions),
            ("sphere_velocity", velocities),
            ("sphere_angular_velocity", angular_velocities),
        ):
            view = self.sim.view(name)
            view.zero_()
            if value is not None:
                value = torch.as_tensor(value, dtype=torch.float32)
                if value.shape[-2:] != positions.shape[-2:]:
                    raise ValueError(
                        f"{name} must match positions' shape {tuple(positions.shape[-2:])}, "
                        f"got {tuple(value.shape)}"
                    )
                view[:, :count] = value.to(view.device)
        active = self.sim.view("sphere_active")
        active.zero_()
        active[:, :count] = 1

    def step(self, ticks: int = 1) -> None:
        """Advances the physics by ``ticks`` ticks; the columns stop after the first one."""
        for _ in range(ticks):
            self.sim.physics_tick()
            self.sim.view("column_height_prev").copy_(self.sim.view("column_height"))
            self.time += self.config.tick_dt
