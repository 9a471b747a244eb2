"""Baseline policies for TerraShift: random, zero and a scripted heuristic.

Each policy is a plain callable ``policy(td) -> td`` that reads the observation keys of a
:class:`~terrashift_rl.envs.TerraShiftEnv` tensordict and writes ``("agents", "action")``
([*batch, K, 6] in [-1, 1], float32, on the tensordict's device). None touches the simulator;
they work for any batch shape (one environment, a batch, a batch of time steps) and any device.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from terrashift_rl.sim import ACTUATORS
from terrashift_rl.sim.config import TerraShiftConfig
from terrashift_rl.sim.types import ACTION_DIM

OBSERVATION_KEY = ("agents", "observation")
ACTION_KEY = ("agents", "action")

__all__ = ["RandomPolicy", "ScriptedHeuristicPolicy", "ZeroPolicy"]


def _action_shape(td: TensorDictBase) -> torch.Size:
    """[*batch, K, ACTION_DIM], from the agents' observation."""
    return td.get(OBSERVATION_KEY).shape[:-1] + (ACTION_DIM,)


class RandomPolicy:
    """Actions drawn uniformly from [-1, 1], independently per environment, agent and dimension.

    Args:
        seed: seed of the policy's own generator (one per device, created on first use), so a
            seeded evaluation is reproducible and leaves torch's global generator alone; None
            draws from torch's global generator.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({("agents", "observation"): torch.zeros(2, 8, 9)}, batch_size=[2])
        >>> action = RandomPolicy(seed=0)(td)["agents", "action"]
        >>> action.shape, bool(action.abs().max() <= 1)
        (torch.Size([2, 8, 6]), True)
    """

    def __init__(self, *, seed: int | None = None):
        self.seed = seed
        self._generators: dict[torch.device, torch.Generator] = {}

    def _generator(self, device: torch.device) -> torch.Generator | None:
        if self.seed is None:
            return None
        if device not in self._generators:
            self._generators[device] = torch.Generator(device=device).manual_seed(self.seed)
        return self._generators[device]

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        observation = td.get(OBSERVATION_KEY)
        device = observation.device
        u = torch.rand(_action_shape(td), generator=self._generator(device), device=device)
        td.set(ACTION_KEY, u * 2.0 - 1.0)
        return td


class ZeroPolicy:
    """All-zero actions: every wavelet keeps its initial velocity, spin, amplitude and width.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({("agents", "observation"): torch.zeros(3, 8, 9)}, batch_size=[3])
        >>> ZeroPolicy()(td)["agents", "action"].abs().sum().item()
        0.0
    """

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        observation = td.get(OBSERVATION_KEY)
        td.set(ACTION_KEY, torch.zeros(_action_shape(td), device=observation.device))
        return td


class ScriptedHeuristicPolicy:
    """Pushes each sphere towards its goal with its agents' patches, for every actuator family:
    a Gaussian bump just behind it (``wavelets``), a patch of surface flowing under it towards
    the goal (``surface_flow``), or rotors beside it whose rims move towards the goal
    (``rotors``).

    The policy reads only the observation (``("agents", "observation")``, ``"objects"``,
    ``"objects_mask"``) and the scene constants of ``config``; it never touches the simulator.

    **Assignment.** Agent ``k`` serves object slot ``k % M``. If that slot holds no sphere
    (not spawned yet, or already resolved), the agent serves the ``(k mod n)``-th active
    sphere instead (n active spheres), so every agent works while any sphere is in play. With
    no active sphere an agent stops and flattens its wavelet.

    **Where to stand.** Sphere and goal positions are converted from metres to cell units, the
    wavelet's own coordinates (column ``ix`` is centred at ``x = (ix + 0.5) cell - 0.5 *
    platform`` m and a wavelet at ``x = ix`` sits on it). With ``u`` the unit vector from the
    sphere to its goal, the agent's target is ``sphere - offset * u``: a bump that far behind
    the sphere, on the side away from its goal, tilts the columns under the sphere towards the
    goal, and the sphere rolls down the bump's flank. Serving agents beyond the first of a
    sphere (``k >= M``) stand ``extra_offset`` cells further back, widening the slope. With
    ``surface_flow`` the target is the sphere itself (the later agents ``extra_offset`` behind
    it) and the patch turns its flow towards the goal. With ``rotors`` the first agent of a
    sphere stands ``sigma`` cells (where its rim is fastest) to the right of the line from the
    sphere to its goal and spins anticlockwise, the later ones as far to the left, spinning
    clockwise: either rim moves the sphere towards its goal.

    **How to get there.** The wavelet position is second-order: an action changes its velocity
    by ``velocity_gain * wave_step`` per physics tick. A PD-like law sets a desired velocity
    ``v* = sphere velocity + position_gain * e``, where ``e`` is the torus-wrapped offset from
    the wavelet to its target (the grid wraps) and the sphere's velocity (converted to cells
    per wave step) is a feed-forward term that keeps the bump behind a rolling sphere;
    ``v*`` is clipped to the speed limit. With ``delta`` actions the action is the velocity
    error divided by the change one decision of full action produces (``velocity_gain *
    wave_step * action_repeat``), clipped to [-1, 1]: a proportional velocity loop on top of the
    position loop, that is, PD on the position. With ``target`` actions it is ``v*`` itself
    (over the speed limit), and the simulator's rate-limited tracking closes the loop; with
    ``position`` actions it is the point ``v* / position_gain`` (the scene's servo gain) from
    the wavelet, towards which the simulator's servo aims that same velocity; ``shape``
    actions move it as ``delta`` actions do.

    **Shape.** The same rule drives the other parameters to set points: amplitude towards
    ``amplitude`` times the family's largest (with the rotors' sign) once the patch is within
    ``engage_distance`` cells of its target (towards zero while it travels, so it does not
    disturb spheres on its way), both widths towards ``sigma`` cells, and the spin towards
    zero, or with ``surface_flow`` towards ``heading_gain`` times the angle from the patch's
    orientation to the goal's direction. With ``target`` and ``shape`` actions the amplitude
    and width actions are those set points themselves.

    **Keeping the spheres apart** (``surface_flow``, ``rotors``). A sliding surface moves a
    rolling sphere only by changing speed under it: a sphere that it presses against another
    spins up until it rolls in place, and from then on only a faster flow moves it further
    that way, none at all if the flow ran at the speed limit (docs/actuators.md). So the way
    each sphere is driven turns away from every other sphere in play whose centre lies within
    ``clearance`` sphere diameters of its own, by the unit vector away from that sphere times
    its nearness (1 touching, 0 at ``clearance``), and the amplitude is scaled by one minus
    the largest nearness of a sphere ahead (times the cosine of the angle between the way to
    it and the goal's), so that a sphere closing on another straight ahead stops before it
    touches. The flow turns onto that way; the rotors stand on either side of it.

    Args:
        config: the scene's config (grid, platform, gains, limits, timing).
        offset: distance [cells] from the sphere centre back to the bump centre (2 cells
            worked best on the pretraining scene: 1 barely tilts the sphere, 2.5 often misses it).
        extra_offset: additional distance [cells] for the second and later agents of a sphere.
        amplitude: set-point amplitude as a fraction of ``max_amplitude``, in (0, 1].
        sigma: set-point width [cells], clipped to [sigma_min, sigma_max].
        position_gain: desired velocity per cell of position error [1 / wave step].
        engage_distance: distance [cells] to the target below which the bump is raised.
        heading_gain: with ``surface_flow``, the spin aimed at per radian between the flow's
            direction and the goal's [1 / wave step].
        clearance: with ``surface_flow`` and ``rotors``, the distance between sphere centres
            [sphere diameters], > 1, within which a patch steers its sphere clear of another;
            None steers none clear.

    Example:
        >>> from tensordict import TensorDict
        >>> cfg = TerraShiftConfig(num_agents=1, num_objects=1, num_goals=1)
        >>> policy = ScriptedHeuristicPolicy(cfg)
        >>> agent = torch.zeros(1, 1, 9)  # wavelet at the grid centre, at rest
        >>> objects = torch.zeros(1, 1, 9)
        >>> objects[0, 0, 3] = -0.8  # sphere at the centre, goal far to the left (-x)
        >>> td = TensorDict({("agents", "observation"): agent, "objects": objects,
        ...                  "objects_mask": torch.ones(1, 1, dtype=torch.bool)}, batch_size=[1])
        >>> policy(td)["agents", "action"][0, 0, 0].item() > 0  # move right, behind the sphere
        True
    """

    def __init__(
        self,
        config: TerraShiftConfig,
        *,
        offset: float = 2.0,
        extra_offset: float = 0.5,
        amplitude: float = 1.0,
        sigma: float = 1.0,
        position_gain: float = 1.0,
        engage_distance: float = 1.5,
        heading_gain: float = 1.0,
        clearance: float | None = 2.0,
    ):
        if not 0.0 < amplitude <= 1.0:
            raise ValueError(f"amplitude must be in (0, 1], got {amplitude}")
        for name, value in (
            ("offset", offset),
            ("extra_offset", extra_offset),
            ("position_gain", position_gain),
            ("engage_distance", engage_distance),
            ("heading_gain", heading_gain),
        ):
            if not math.isfinite(value) or value < 0.0:
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        if clearance is not None and not (math.isfinite(clearance) and clearance > 1.0):
            raise ValueError(f"clearance must be a finite number > 1 or None, got {clearance}")
        self.config = config
        self.offset = offset
        self.extra_offset = extra_offset
        self.amplitude = amplitude
        self.sigma = min(max(sigma, config.sigma_min), config.sigma_max)
        self.position_gain = position_gain
        self.engage_distance = engage_distance
        self.heading_gain = heading_gain
        self.clearance = clearance
        self.amplitude_limit, self.amplitude_gain = ACTUATORS[config.actuator].amplitude_limits(
            config
        )[1:]

    # --- observation decoding -------------------------------------------------------------
    def _metres_to_cells(self, normalised: torch.Tensor) -> torch.Tensor:
        """Object x or y from the observation (metres over the half platform) to cell units."""
        cfg = self.config
        half = 0.5 * cfg.platform_size
        return (normalised * half + half) / cfg.cell_size - 0.5

    def _assign(self, mask: torch.Tensor, num_agents: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Object slot of every agent, [B, K] (long), and whether it has one, [B, K] (bool)."""
        b, m = mask.shape
        agents = torch.arange(num_agents, device=mask.device)
        preferred = (agents % m).expand(b, num_agents)
        count = mask.sum(-1, keepdim=True)  # [B, 1]
        rank = mask.long().cumsum(-1) - 1  # rank of each active slot among the active ones
        wanted = agents.unsqueeze(0) % count.clamp(min=1)  # [B, K]
        match = mask.unsqueeze(1) & (rank.unsqueeze(1) == wanted.unsqueeze(-1))  # [B, K, M]
        fallback = match.long().argmax(-1)
        slot = torch.where(mask.gather(-1, preferred), preferred, fallback)
        return slot, (count > 0).expand(b, num_agents)

    def _steer_clear(
        self,
        sphere: torch.Tensor,
        slot: torch.Tensor,
        objects: torch.Tensor,
        mask: torch.Tensor,
        direction: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each agent's driving direction [B, K, 2] turned away from the other spheres in play
        near its sphere (``sphere``, [B, K, 2] cells, in slot ``slot``), and the factor [B, K]
        on its amplitude (see "Keeping the spheres apart")."""
        cfg = self.config
        others = self._metres_to_cells(objects[..., 0:2]).unsqueeze(1)  # [B, 1, M, 2]
        away = sphere.unsqueeze(-2) - others  # [B, K, M, 2]
        distance = away.norm(dim=-1).clamp(min=1e-6)
        away = away / distance.unsqueeze(-1)
        diameter = 2.0 * cfg.sphere_radius / cfg.cell_size
        nearness = ((self.clearance - distance / diameter) / (self.clearance - 1.0)).clamp(0, 1)
        slots = torch.arange(mask.shape[-1], device=mask.device)
        nearness = nearness * (mask.unsqueeze(1) & (slots != slot.unsqueeze(-1)))
        steered = direction + (nearness.unsqueeze(-1) * away).sum(-2)
        ahead = -(away * direction.unsqueeze(-2)).sum(-1)
        speed = 1.0 - (nearness * ahead.clamp(min=0.0)).amax(-1)
        return steered / steered.norm(dim=-1, keepdim=True).clamp(min=1e-6), speed

    # --- policy ---------------------------------------------------------------------------
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        observation = td.get(OBSERVATION_KEY)
        batch = observation.shape[:-2]
        k = observation.shape[-2]
        agent = observation.reshape(-1, k, observation.shape[-1]).float()
        objects = td.get("objects").reshape(agent.shape[0], -1, td.get("objects").shape[-1])
        mask = td.get("objects_mask").reshape(agent.shape[0], -1).bool()
        g = float(cfg.grid_size)

        # wavelet state in physical units (cells, cells / wave step, m, rad / wave step)
        position = (agent[..., 0:2] + 1.0) * (0.5 * g)
        amplitude = agent[..., 3] * self.amplitude_limit
        angle = (agent[..., 2] + 1.0) * math.pi
        widths = (agent[..., 4:6] + 1.0) * (0.5 * (cfg.sigma_max - cfg.sigma_min)) + cfg.sigma_min
        velocity = agent[..., 6:8] * cfg.max_velocity
        spin = agent[..., 8] * cfg.max_angular_velocity

        # each agent's sphere and goal, in cells; sphere velocity in cells per wave step
        slot, engaged = self._assign(mask, k)
        mine = objects.float().gather(1, slot.unsqueeze(-1).expand(-1, -1, objects.shape[-1]))
        sphere = self._metres_to_cells(mine[..., 0:2])
        goal = self._metres_to_cells(mine[..., 3:5])
        cells_per_second = mine[..., 6:8] * cfg.max_object_speed / cfg.cell_size
        sphere_velocity = cells_per_second / (cfg.wave_step * cfg.physics_hz)

        # target: behind the sphere (wavelets, flow) or beside it (rotors)
        to_goal = goal - sphere
        direction = to_goal / to_goal.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        later = torch.arange(k, device=agent.device) >= mask.shape[-1]
        desired_spin = torch.zeros_like(spin)
        sign = torch.ones_like(spin)
        speed = torch.ones_like(spin)
        steered = direction
        if self.clearance is not None and cfg.actuator in ("surface_flow", "rotors"):
            steered, speed = self._steer_clear(sphere, slot, objects.float(), mask, direction)
        if cfg.actuator == "rotors":
            sign = torch.where(later, -1.0, 1.0).expand_as(spin)
            right = torch.stack([steered[..., 1], -steered[..., 0]], dim=-1)
            target = sphere - (sign * self.sigma).unsqueeze(-1) * right
        else:
            back = self.extra_offset * later
            if cfg.actuator == "wavelets":
                back = back + self.offset
            target = sphere - back.unsqueeze(-1) * direction
        if cfg.actuator == "surface_flow":
            heading = torch.atan2(steered[..., 1], steered[..., 0])
            turn_by = torch.remainder(heading - angle + math.pi, 2 * math.pi) - math.pi
            desired_spin = (self.heading_gain * turn_by).clamp(
                -cfg.max_angular_velocity, cfg.max_angular_velocity
            )
        error = target - position
        if cfg.wrap_edges:
            error = error - g * torch.floor(error / g + 0.5)
        distance = error.norm(dim=-1)

        # PD-like law: desired velocity from the position error
        desired = sphere_velocity + self.position_gain * error
        desired = torch.where(engaged.unsqueeze(-1), desired, torch.zeros_like(desired))
        desired = desired.clamp(-cfg.max_velocity, cfg.max_velocity)

        # shape set points: a positive bump of width sigma, no spin; flat while travelling
        close = engaged & (distance <= self.engage_distance)
        amplitude_target = torch.where(
            close, sign * speed * self.amplitude * self.amplitude_limit, 0.0
        )
        # a set point is the action itself where the mode sets targets; otherwise the action
        # is the error over the change that one decision of full action produces
        per_decision = cfg.wave_step * cfg.action_repeat
        if cfg.action_mode in ("target", "shape"):
            half_range = 0.5 * (cfg.sigma_max - cfg.sigma_min)
            grow = amplitude_target / self.amplitude_limit
            width = (self.sigma - cfg.sigma_min) / half_range - 1.0 if half_range > 0 else 0.0
            widen = torch.full_like(widths, width)
        else:
            grow = (amplitude_target - amplitude) / (self.amplitude_gain * per_decision)
            widen = (self.sigma - widths) / (cfg.sigma_gain * per_decision)
        if cfg.action_mode == "target":
            move = desired / cfg.max_velocity
            turn = desired_spin / cfg.max_angular_velocity
        else:
            move = (desired - velocity) / (cfg.velocity_gain * per_decision)
            turn = (desired_spin - spin) / (cfg.angular_velocity_gain * per_decision)
            if cfg.action_mode == "position":
                # the point whose offset the simulator's servo turns into that same velocity
                aim = position + desired / cfg.position_gain
                aim = aim - g * torch.floor(aim / g) if cfg.wrap_edges else aim.clamp(0.0, g - 1)
                move = 2.0 * aim / g - 1.0

        action = torch.cat([move, turn.unsqueeze(-1), grow.unsqueeze(-1), widen], dim=-1)
        action = action.clamp(-1.0, 1.0).to(torch.float32)
        td.set(ACTION_KEY, action.reshape(*batch, k, ACTION_DIM))
        return td
