"""Configuration of a TerraShift scene: geometry, wave agents, spheres, timing, reward.

Every length is in metres, every time in seconds, every mass in kilograms. Wave-agent
quantities live in *cell units* (one cell is the spacing of the column grid), as the wave is
defined on the grid. The defaults are the paper's pretraining run (``pretrain``); ``finetune``
is the 30 x 30 grid with 16 agents; ``large`` is a 45 x 45 grid with 24 agents, 8 spheres and
8 goals on the same platform.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

COLUMN_SHAPES = ("ellipsoid", "box", "smooth")
"""Column shapes: ellipsoids (the paper's), boxes (classic pins), a smooth interpolated surface."""

MAX_CAMERA_RESOLUTION = 256
"""Largest camera image side [pixels]: 65,536 environments at 256 x 256 already hold 16 GiB."""

ACTION_MODES = ("delta", "target", "position", "shape")
"""What an action sets: the change of each wavelet quantity (the paper's), its target value,
the wavelet's target position (and the change of the rest), or the change of the rates and the
target of the shape."""

REWARD_TERMS = {
    "goal_reward": "task",
    "out_of_bounds_penalty": "task",
    "distance_scale": "task",
    "slow_penalty": "task",
    "time_penalty": "task",
    "potential_scale": "shaping",
    "alignment_scale": "shaping",
    "approach_scale": "shaping",
    "sphere_approach_scale": "shaping",
}
"""Every term of the reward, by the config field that scales it, and its role. ``task``: the
benchmark's reward (the paper's reported run: goal, out of bounds, distance gained, slow spheres,
time), which every reported reward per decision holds. ``shaping``: a training aid, off at 0,
that evaluation switches off (:meth:`TerraShiftConfig.without_shaping`) so that the reward per
decision compares across recipes and with the baselines. A term's field ends in ``_scale``,
``_reward`` or ``_penalty``; the fields that only tune a term (``distance_clip``,
``potential_gamma``, ``slow_speed``, ``approach_radius``, ``reward_normalizer``) are not terms.
A new term goes here, or the tests that compare this table with the config and the reward
kernel fail."""


@dataclass
class TerraShiftConfig:
    """All parameters of a TerraShift scene.

    The field docstrings give the unit and the allowed range; :meth:`validate` enforces the
    ranges and raises :class:`ValueError` naming the field. Usable as a Hydra structured config.

    Example:
        >>> cfg = TerraShiftConfig.preset("finetune")
        >>> cfg.grid_size, cfg.num_agents, cfg.num_objects
        (30, 16, 4)
        >>> TerraShiftConfig(grid_size=1)
        Traceback (most recent call last):
        ...
        ValueError: grid_size must be an integer >= 2, got 1
    """

    # --- geometry -------------------------------------------------------------------------
    grid_size: int = 15
    """Columns per side of the square grid, G [count], >= 2."""
    platform_size: float = 1.0
    """Side of the square platform centred at the origin [m], > 0."""
    column_shape: str = "ellipsoid"
    """Collision and ray shape of a column: one of ``ellipsoid``, ``box``, ``smooth``."""
    column_aspect: float = 2.0
    """Vertical extent of an ellipsoid column over its diameter (one cell) [ratio], > 0."""
    column_rest_top: float = 0.12
    """Height of a column's top above the platform when its wave height is zero [m], > 0."""
    max_column_height: float = 0.06
    """Wave heights are clipped to [-max_column_height, max_column_height] [m], > 0."""
    wrap_edges: bool = True
    """Wrap wavelets around the grid edges (a torus); False clamps positions at the edges."""

    # --- agents and their actuator family ---------------------------------------------------
    actuator: str = "wavelets"
    """Actuator family, a name in ``terrashift_rl.sim.ACTUATORS``: ``wavelets`` (the paper's:
    each agent a Gaussian bump or basin of the column heights), ``surface_flow`` (each agent a
    Gaussian patch of in-plane surface velocity, a conveyor or ciliary surface) or ``rotors``
    (each agent a spinning Gaussian patch of surface, a rotor tile). Every family's agent is a
    mobile patch with the same action and observation layout (docs/actuators.md)."""
    num_agents: int = 8
    """Agents K (one patch each: a Gaussian wavelet with the default actuator) [count], >= 1."""
    action_mode: str = "delta"
    """What an action in [-1, 1] sets, one of ``delta``, ``target``, ``position`` or ``shape``.
    ``delta`` (the paper's): the change of each wavelet quantity per physics tick,
    ``gain * wave_step * action``. ``target``: the value each quantity moves towards, mapped
    from [-1, 1] onto its range (velocities, spin and amplitude onto +-their limits, widths onto
    [sigma_min, sigma_max]); each tick it moves by at most a full ``delta`` action's change, so
    the actuators' rate limits are the same in every mode. ``position``: the first two dims
    set where the wavelet should go, in the coordinates of the agent observation (cell
    ``(a + 1) * G / 2``), and its velocity moves, as with ``target``, towards
    ``position_gain`` times the offset to there (the short way round a wrapping grid), clipped
    to the speed limit: a position servo, as PD targets are for robot joints. The other four
    dims are deltas, as with ``delta`` (random set points would hold the shape still).
    ``shape``: the velocities and the spin change as with ``delta``, the amplitude and the
    widths are targets as with ``target``, so a wavelet's depth or height is chosen afresh at
    every decision rather than integrated from changes (the main job's mode)."""
    wave_step: float = 0.1
    """Integration step of the wavelet parameters per physics tick [dimensionless], > 0."""
    velocity_gain: float = 1.0
    """Wavelet velocity change per unit action per wave step [cells / wave step], > 0."""
    angular_velocity_gain: float = 0.78
    """Wavelet angular velocity change per unit action per wave step [rad / wave step], > 0."""
    amplitude_gain: float = 0.03
    """Wavelet amplitude change per unit action per wave step [m], > 0."""
    sigma_gain: float = 0.5
    """Wavelet width change per unit action per wave step [cells], > 0."""
    position_gain: float = 1.0
    """With ``action_mode="position"``, the velocity aimed at per cell of offset from the
    wavelet to its target position [1 / wave step], > 0."""
    max_velocity: float = 1.0
    """Wavelet speed limit per axis [cells / wave step], > 0."""
    max_angular_velocity: float = 0.785
    """Wavelet angular speed limit [rad / wave step], > 0."""
    max_amplitude: float = 0.06
    """Wavelet amplitude limit, A in [min_amplitude_ratio * max_amplitude, max_amplitude] [m],
    > 0."""
    min_amplitude_ratio: float = -1.0
    """The lowest wavelet amplitude as a fraction of ``max_amplitude``: -1, the paper's range,
    lets a wavelet dig a basin as deep as a bump is high; 0 allows bumps only [ratio], in
    [-1, 1]."""
    sigma_min: float = 0.2
    """Smallest wavelet width [cells], > 0."""
    sigma_max: float = 2.0
    """Largest wavelet width [cells], >= sigma_min."""
    max_surface_speed: float = 1.0
    """In-plane surface speed limit of the families that slide the surface (``surface_flow``,
    ``rotors``): every column's surface velocity is clipped to this norm, and it is the
    ``surface_flow`` patch's amplitude limit, A in [-max_surface_speed, max_surface_speed]
    [m/s], > 0."""
    surface_speed_gain: float = 0.5
    """``surface_flow`` patch amplitude change per unit action per wave step [m/s], > 0."""
    max_rotor_speed: float = 25.0
    """``rotors`` patch spin rate limit, A in [-max_rotor_speed, max_rotor_speed] [rad/s], > 0."""
    rotor_speed_gain: float = 12.5
    """``rotors`` patch spin rate change per unit action per wave step [rad/s], > 0."""
    count_surface_work: bool = False
    """Count the work the surface does on the spheres (``surface_work``, the actuator's
    energy figure). Compiled into the sphere kernels only when on: it costs them registers."""

    # --- spheres --------------------------------------------------------------------------
    num_objects: int = 4
    """Spheres M per environment [count], >= 1."""
    num_goals: int = 4
    """Goals per environment; object j is assigned goal j mod num_goals [count], >= 1."""
    sphere_radius: float = 0.075
    """Sphere radius [m], > 0."""
    sphere_mass: float = 0.18
    """Sphere mass [kg], > 0."""
    friction: float = 0.7
    """Coulomb friction coefficient of every contact [dimensionless], >= 0."""
    restitution: float = 0.3
    """Coefficient of restitution of every contact [dimensionless], in (0, 1]."""
    linear_damping: float = 0.01
    """Linear velocity damping [1/s], >= 0."""
    angular_damping: float = 0.0
    """Angular velocity damping [1/s], >= 0."""
    contact_stiffness: float = 2.0e3
    """Normal stiffness of the penalty contact [N/m], > 0."""
    gravity: float = 9.81
    """Gravitational acceleration, pointing along -z [m/s^2], >= 0."""

    # --- timing ---------------------------------------------------------------------------
    physics_hz: float = 60.0
    """Physics tick rate [Hz], > 0."""
    substeps: int = 8
    """Integration substeps per physics tick [count], >= 1."""
    action_repeat: int = 2
    """Physics ticks per decision; the reward is summed over them [count], >= 1."""
    max_episode_steps: int = 512
    """Decisions per episode before ``truncated`` [count], >= 1."""

    # --- goals, events, spawning ----------------------------------------------------------
    goal_radius: float = 0.10
    """Success when the sphere centre is within this 3-D distance of its goal [m], > 0."""
    out_of_bounds_xy: float = 0.49
    """Out of bounds when |x| or |y| exceeds this [m], > 0."""
    out_of_bounds_z: float = 0.40
    """Out of bounds when z exceeds this height above the platform (or drops below 0) [m], > 0."""
    respawn: bool = True
    """Training mode: respawn resolved objects after ``respawn_delay``. False is evaluation
    mode: no respawn, and the episode terminates once every object is resolved."""
    respawn_fraction: float = 1.0
    """With ``respawn``, the fraction of environments that respawn, spread evenly over their
    indices (0.5: every second one); the others run as in evaluation mode, so that training
    also meets an episode's last spheres [ratio], in [0, 1]."""
    respawn_delay: float = 0.2
    """Delay between an object's goal/out-of-bounds event and its respawn; also the stagger
    between object spawns after a reset [s], >= 0."""
    spawn_margin: int = 2
    """Objects and goals spawn at least this many cells from the grid edges [cells], >= 0."""
    spawn_drop_height: float = 0.01
    """Gap between a spawned sphere's bottom and the highest column top [m], >= 0."""
    spawn_tries: int = 30
    """Random cells tried per spawn before waiting for the next tick [count], >= 1."""

    # --- reward (per physics tick, summed over the action repeat) --------------------------
    distance_scale: float = 100.0
    """Reward per metre of distance-to-goal improvement [1/m], >= 0."""
    distance_clip: float = 1.0
    """Distance improvement per tick is clipped to [-distance_clip, distance_clip] [m], > 0."""
    goal_reward: float = 10.0
    """Reward when an object reaches its goal [reward]."""
    out_of_bounds_penalty: float = -2.5
    """Reward when an object goes out of bounds [reward]."""
    time_penalty: float = -1.0e-4
    """Reward added every tick [reward]."""
    slow_speed: float = 0.1
    """Active spheres slower than this incur ``slow_penalty`` [m/s], >= 0."""
    slow_penalty: float = -0.01
    """Reward per slow active sphere per tick [reward]."""
    potential_scale: float = 0.0
    """Scale of potential-based shaping, Phi = -distance [1/m]; 0 turns it off."""
    potential_gamma: float = 0.95
    """Discount used by the potential-based shaping term, in [0, 1]."""
    alignment_scale: float = 0.0
    """Scale of the velocity-alignment (cosine) term [reward]; 0 turns it off."""
    approach_scale: float = 0.0
    """Reward per cell by which a wavelet closes on its nearest active sphere, counted only
    beyond ``approach_radius`` (a potential, Phi = -scale * that gap, summed over the
    wavelets; ticks on which a sphere spawns or is resolved earn none) [1/cell]; 0 turns it
    off."""
    sphere_approach_scale: float = 0.0
    """Reward per cell by which each active sphere's nearest wavelet closes on it, counted
    only beyond ``approach_radius`` (a potential, Phi = -scale * that gap, summed over the
    spheres, so that a sphere no wavelet attends costs the team; a sphere's first tick in
    play earns none) [1/cell]; 0 turns it off."""
    approach_radius: float = 2.5
    """Distance from a sphere within which a wavelet earns no approach reward (either
    term) [cells], >= 0."""
    reward_normalizer: float = 4.0
    """The team reward per tick is (time penalty + sum over objects and wavelets) /
    reward_normalizer, > 0."""

    # --- observations ---------------------------------------------------------------------
    heightmap_resolution: int = 32
    """Rays per side of the heightmap lattice spanning the platform edges [count], >= 2."""
    heightmap_max_height: float = 0.40
    """Ray heights are clipped to [0, heightmap_max_height] and mapped to [-1, 1] [m], > 0."""
    max_object_speed: float = 1.0
    """Sphere velocity components are clipped to +-this, then divided by it [m/s], > 0."""
    camera_resolution: int = 0
    """Pixels per side of the overhead greyscale camera image at ``"camera"``, sampled on a
    lattice spanning the platform edge to edge like the heightmap's (``sim/camera.py`` gives
    the encoding) [count]; 0 turns the camera off, otherwise in [2, MAX_CAMERA_RESOLUTION]."""
    observe_objects: bool = True
    """Observe the object sequence (sphere and goal positions, velocities); False leaves the
    heightmap, the camera and the wavelets' own parameters as the only observations."""
    privileged_objects: bool = False
    """With ``observe_objects=False``, hand the object sequence out all the same, apart from the
    observations, at ``("privileged", "objects")`` and ``("privileged", "objects_mask")``: for
    critics that see more than the policy during training (centralised training, decentralised
    execution), never for a policy. Refused with ``observe_objects``, which observes it."""

    def __post_init__(self) -> None:
        self.validate()

    # --- derived quantities ---------------------------------------------------------------
    @property
    def cell_size(self) -> float:
        """Spacing of the column grid [m]."""
        return self.platform_size / self.grid_size

    @property
    def tick_dt(self) -> float:
        """Duration of one physics tick [s]."""
        return 1.0 / self.physics_hz

    @property
    def substep_dt(self) -> float:
        """Duration of one integration substep [s]."""
        return self.tick_dt / self.substeps

    @property
    def respawn_ticks(self) -> int:
        """Respawn delay in whole physics ticks."""
        return round(self.respawn_delay * self.physics_hz)

    @property
    def decision_dt(self) -> float:
        """Simulated time per decision [s]."""
        return self.tick_dt * self.action_repeat

    # --- presets --------------------------------------------------------------------------
    @classmethod
    def preset(cls, name: str, **overrides: Any) -> TerraShiftConfig:
        """Returns a named preset (``pretrain``, ``finetune`` or ``large``) with ``overrides``
        applied."""
        presets = {
            "pretrain": {},
            "finetune": {"grid_size": 30, "num_agents": 16, "num_objects": 4, "time_penalty": 0.0},
            "large": {
                "grid_size": 45,
                "num_agents": 24,
                "num_objects": 8,
                "num_goals": 8,
                "time_penalty": 0.0,
            },
        }
        if name not in presets:
            raise ValueError(f"unknown preset {name!r}; choose one of {sorted(presets)}")
        return cls(**{**presets[name], **overrides})

    def replace(self, **overrides: Any) -> TerraShiftConfig:
        """Returns a copy with ``overrides`` applied; unknown names raise ``ValueError``."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ValueError(f"unknown TerraShiftConfig field(s) {unknown}")
        return dataclasses.replace(self, **overrides)

    def without_shaping(self) -> TerraShiftConfig:
        """Returns a copy with every shaping term of the reward (:data:`REWARD_TERMS`) at 0
        and every task term as it was.

        Example:
            >>> scene = TerraShiftConfig(approach_scale=0.3, potential_scale=0.5)
            >>> plain = scene.without_shaping()
            >>> plain.approach_scale, plain.potential_scale, plain.distance_scale
            (0.0, 0.0, 100.0)
        """
        return self.replace(
            **{name: 0.0 for name, role in REWARD_TERMS.items() if role == "shaping"}
        )

    # --- validation -----------------------------------------------------------------------
    def validate(self) -> None:
        """Raises ``ValueError`` naming the first field outside its allowed range."""
        for name in ("grid_size", "heightmap_resolution"):
            _check_int(self, name, minimum=2)
        for name in (
            "num_agents",
            "num_objects",
            "num_goals",
            "substeps",
            "action_repeat",
            "max_episode_steps",
            "spawn_tries",
        ):
            _check_int(self, name, minimum=1)
        _check_int(self, "spawn_margin", minimum=0)
        for name in (
            "platform_size",
            "column_aspect",
            "column_rest_top",
            "max_column_height",
            "wave_step",
            "velocity_gain",
            "position_gain",
            "angular_velocity_gain",
            "amplitude_gain",
            "sigma_gain",
            "max_velocity",
            "max_angular_velocity",
            "max_amplitude",
            "sigma_min",
            "sigma_max",
            "max_surface_speed",
            "surface_speed_gain",
            "max_rotor_speed",
            "rotor_speed_gain",
            "sphere_radius",
            "sphere_mass",
            "contact_stiffness",
            "physics_hz",
            "goal_radius",
            "out_of_bounds_xy",
            "out_of_bounds_z",
            "distance_clip",
            "reward_normalizer",
            "heightmap_max_height",
            "max_object_speed",
        ):
            _check_float(self, name, low=0.0, low_open=True)
        for name in (
            "friction",
            "linear_damping",
            "angular_damping",
            "gravity",
            "respawn_delay",
            "spawn_drop_height",
            "distance_scale",
            "slow_speed",
            "approach_radius",
        ):
            _check_float(self, name, low=0.0)
        _check_float(self, "restitution", low=0.0, high=1.0, low_open=True)
        _check_float(self, "respawn_fraction", low=0.0, high=1.0)
        _check_float(self, "min_amplitude_ratio", low=-1.0, high=1.0)
        _check_float(self, "potential_gamma", low=0.0, high=1.0)
        for name in (
            "goal_reward",
            "out_of_bounds_penalty",
            "time_penalty",
            "slow_penalty",
            "potential_scale",
            "alignment_scale",
            "approach_scale",
            "sphere_approach_scale",
        ):
            _check_float(self, name)
        resolution = self.camera_resolution
        if (
            isinstance(resolution, bool)
            or not isinstance(resolution, int)
            or not (resolution == 0 or 2 <= resolution <= MAX_CAMERA_RESOLUTION)
        ):
            raise ValueError(
                f"camera_resolution must be 0 (no camera) or an integer in "
                f"[2, {MAX_CAMERA_RESOLUTION}], got {resolution!r}"
            )
        for name in (
            "wrap_edges",
            "respawn",
            "count_surface_work",
            "observe_objects",
            "privileged_objects",
        ):
            value = getattr(self, name)
            if not isinstance(value, bool):
                raise ValueError(f"{name} must be true or false, got {value!r}")
        if self.privileged_objects and self.observe_objects:
            raise ValueError(
                "privileged_objects=true hands out the object sequence that observe_objects=true "
                "already observes: set observe_objects=false (the policy then sees the images "
                "alone) or privileged_objects=false"
            )
        # imported here: the families' modules import this one
        from terrashift_rl.sim.actuators import ACTUATORS

        if self.actuator not in ACTUATORS:
            raise ValueError(
                f"actuator must be one of {tuple(sorted(ACTUATORS))}, got {self.actuator!r}"
            )
        if self.action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {self.action_mode!r}")
        if self.column_shape not in COLUMN_SHAPES:
            raise ValueError(
                f"column_shape must be one of {COLUMN_SHAPES}, got {self.column_shape!r}"
            )
        if self.sigma_min > self.sigma_max:
            raise ValueError(
                f"sigma_min ({self.sigma_min}) must be <= sigma_max ({self.sigma_max})"
            )
        if self.num_goals > self.num_objects:
            raise ValueError(
                f"num_goals ({self.num_goals}) must be <= num_objects ({self.num_objects})"
            )
        if self.column_rest_top - self.max_column_height <= 0.0:
            raise ValueError(
                f"column_rest_top ({self.column_rest_top}) must exceed max_column_height "
                f"({self.max_column_height}) so columns stay above the platform"
            )
        free = self.grid_size - 2 * self.spawn_margin
        if free < 1:
            raise ValueError(
                f"spawn_margin ({self.spawn_margin}) leaves no spawn cells on a "
                f"{self.grid_size}x{self.grid_size} grid; it must be < grid_size / 2"
            )
        # Spawned objects and goals keep one sphere diameter apart: the spawn square must hold
        # at least num_objects + num_goals such discs.
        spacing = max(1, math.ceil(2.0 * self.sphere_radius / self.cell_size))
        capacity = math.ceil(free / spacing) ** 2
        if self.num_objects + self.num_goals > capacity:
            raise ValueError(
                f"num_objects ({self.num_objects}) + num_goals ({self.num_goals}) exceeds the "
                f"{capacity} spawn places that a {self.grid_size}x{self.grid_size} grid with "
                f"spawn_margin={self.spawn_margin} and sphere_radius={self.sphere_radius} m "
                f"holds; use a larger grid_size or fewer objects"
            )
        if 2.0 * self.sphere_radius >= self.platform_size:
            raise ValueError(
                f"sphere_radius ({self.sphere_radius} m) must be below half the platform_size "
                f"({self.platform_size} m)"
            )


def _check_int(cfg: TerraShiftConfig, name: str, *, minimum: int) -> None:
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _check_float(
    cfg: TerraShiftConfig,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
) -> None:
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    too_low = low is not None and (value <= low if low_open else value < low)
    too_high = high is not None and value > high
    if too_low or too_high:
        lo = "-inf" if low is None else f"{low}"
        hi = "inf" if high is None else f"{high}"
        bracket = "(" if low_open else "["
        raise ValueError(f"{name} must be in {bracket}{lo}, {hi}], got {value!r}")
