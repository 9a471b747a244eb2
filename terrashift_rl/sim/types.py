"""Static model (constants shared by every environment) and per-environment data arrays.

The model is a Warp struct passed to every kernel; the data are Warp arrays whose leading
dimension is the environment. Kernels read the model and read/write the data; nothing else.
"""

from __future__ import annotations

import functools
import math

import warp as wp

from terrashift_rl.sim.config import ACTION_MODES, COLUMN_SHAPES, TerraShiftConfig

SHAPE_ELLIPSOID = wp.constant(COLUMN_SHAPES.index("ellipsoid"))
SHAPE_BOX = wp.constant(COLUMN_SHAPES.index("box"))
ACTION_TARGET = wp.constant(ACTION_MODES.index("target"))
ACTION_POSITION = wp.constant(ACTION_MODES.index("position"))
ACTION_SHAPE = wp.constant(ACTION_MODES.index("shape"))

OBJECT_FEATURES = 9
"""Per-object observation: position (3), goal position (3), velocity (3)."""
AGENT_FEATURES = 9
"""Per-agent observation: x, y, theta, amplitude, sigma_x, sigma_y, v_x, v_y, omega."""
ACTION_NAMES = ("v_x", "v_y", "omega", "amplitude", "sigma_x", "sigma_y")
"""Per-agent action of every actuator family, each in [-1, 1]: the change or the target of
each of these quantities of the agent's patch (the wavelet, for the paper's actuator), or
with ``position`` actions the target position in place of the velocities
(``TerraShiftConfig.action_mode``)."""
ACTION_DIM = len(ACTION_NAMES)


@wp.struct
class Model:
    """Constants of a scene, in SI units (wave quantities in cell units)."""

    grid_size: int
    num_agents: int
    num_objects: int
    num_goals: int
    cell_size: float
    half_platform: float
    column_shape: int
    column_half_width: float
    column_half_height: float
    column_rest_top: float
    max_column_height: float
    wrap_edges: int

    action_mode: int
    wave_step: float
    velocity_gain: float
    position_gain: float
    angular_velocity_gain: float
    amplitude_gain: float
    sigma_gain: float
    max_velocity: float
    max_angular_velocity: float
    max_amplitude: float
    min_amplitude: float
    sigma_min: float
    sigma_max: float

    sphere_radius: float
    sphere_mass: float
    sphere_inertia: float
    friction: float
    contact_stiffness: float
    column_contact_damping: float
    sphere_contact_damping: float
    linear_damping: float
    angular_damping: float
    gravity: float

    tick_dt: float
    substeps: int
    substep_dt: float

    goal_radius: float
    out_of_bounds_xy: float
    out_of_bounds_z: float
    respawn_fraction: float
    respawn_ticks: int
    spawn_margin: int
    spawn_drop_height: float
    spawn_tries: int
    max_episode_steps: int

    distance_scale: float
    distance_clip: float
    goal_reward: float
    out_of_bounds_penalty: float
    time_penalty: float
    slow_speed: float
    slow_penalty: float
    potential_scale: float
    potential_gamma: float
    alignment_scale: float
    approach_scale: float
    sphere_approach_scale: float
    approach_radius: float
    reward_normalizer: float

    heightmap_resolution: int
    heightmap_max_height: float
    max_object_speed: float
    camera_resolution: int


PHASES = (0.125, 0.375, 0.625, 0.875)


@functools.lru_cache
def damping_ratio_for_restitution(restitution: float, *, step: float = 1.0e-2) -> float:
    """Damping ratio of a non-adhesive linear spring-dashpot contact with the given restitution.

    The contact force ``k x + c x'`` is clipped at zero (a contact never pulls), which ends a
    collision slightly before the spring returns to its rest length, and a time step that is
    not tiny against the contact's duration shifts the outcome too; the classic formula
    ``-ln e / sqrt(pi^2 + ln^2 e)`` ignores both. This integrates the clipped one-dimensional
    collision with the simulator's own scheme (semi-implicit Euler) and bisects on the damping
    ratio, so the restitution holds for the time step in use.

    Args:
        restitution: target coefficient of restitution in (0, 1].
        step: the integration step times the contact's natural frequency sqrt(k / m).

    Example:
        >>> round(damping_ratio_for_restitution(1.0), 6)
        0.0
        >>> 0.45 < damping_ratio_for_restitution(0.3) < 0.55  # the unclipped formula gives 0.36
        True
    """
    if restitution >= 1.0:
        return 0.0

    def exit_speed(zeta: float) -> float:
        # Unit mass, unit natural frequency, unit approach speed; x is the overlap. A contact
        # starts anywhere within a step, so the first overlap is averaged over that phase.
        total = 0.0
        for phase in PHASES:
            x, v = phase * step, 1.0
            while True:
                a = -x - 2.0 * zeta * v
                if a > 0.0 and x > 0.0:  # force would pull: contact has already opened
                    break
                v += a * step
                x += v * step
                if x <= 0.0:
                    break
            total += -v
        return total / len(PHASES)

    # Beyond 2 zeta step = 1 one step of damping alone reverses the approach: the explicit
    # scheme is no longer a contact model, and the exit speed stops falling with zeta.
    low, high = 0.0, 0.5 / step
    if exit_speed(high) > restitution:
        raise ValueError(
            f"restitution {restitution} is out of reach at this time step (step * frequency = "
            f"{step:.3f}); raise substeps or lower contact_stiffness"
        )
    for _ in range(40):
        mid = 0.5 * (low + high)
        if exit_speed(mid) > restitution:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


def build_model(config: TerraShiftConfig) -> Model:
    """Derives the kernel constants from a validated config; the actuator family then sets its
    own (:meth:`~terrashift_rl.sim.actuators.Actuator.configure`)."""
    m = Model()
    cell = config.cell_size
    m.grid_size = config.grid_size
    m.num_agents = config.num_agents
    m.num_objects = config.num_objects
    m.num_goals = config.num_goals
    m.cell_size = cell
    m.half_platform = 0.5 * config.platform_size
    m.column_shape = COLUMN_SHAPES.index(config.column_shape)
    m.column_half_width = 0.5 * cell
    m.column_half_height = 0.5 * config.column_aspect * cell
    m.column_rest_top = config.column_rest_top
    m.max_column_height = config.max_column_height
    m.wrap_edges = int(config.wrap_edges)

    m.action_mode = ACTION_MODES.index(config.action_mode)
    m.wave_step = config.wave_step
    m.velocity_gain = config.velocity_gain
    m.position_gain = config.position_gain
    m.angular_velocity_gain = config.angular_velocity_gain
    m.sigma_gain = config.sigma_gain
    m.max_velocity = config.max_velocity
    m.max_angular_velocity = config.max_angular_velocity
    m.sigma_min = config.sigma_min
    m.sigma_max = config.sigma_max

    mass = config.sphere_mass
    m.sphere_radius = config.sphere_radius
    m.sphere_mass = mass
    m.sphere_inertia = 0.4 * mass * config.sphere_radius**2
    m.friction = config.friction
    m.contact_stiffness = config.contact_stiffness
    # The damping scales with the reduced mass of the pair: a column is kinematic (infinite
    # mass), so a sphere-column pair has the sphere's mass, a sphere pair half of it.
    k, dt = config.contact_stiffness, config.substep_dt
    for name, reduced_mass in (("column", mass), ("sphere", 0.5 * mass)):
        frequency = math.sqrt(k / reduced_mass)
        if frequency * dt > 1.0:
            raise ValueError(
                f"contact_stiffness {k} N/m is too stiff for a substep of {dt * 1e3:.2f} ms "
                f"(the {name} contact needs substep * sqrt(k / m) <= 1, here "
                f"{frequency * dt:.2f}); raise substeps or lower contact_stiffness"
            )
        zeta = damping_ratio_for_restitution(config.restitution, step=frequency * dt)
        setattr(m, f"{name}_contact_damping", 2.0 * zeta * math.sqrt(k * reduced_mass))
    m.linear_damping = config.linear_damping
    m.angular_damping = config.angular_damping
    m.gravity = config.gravity

    m.tick_dt = config.tick_dt
    m.substeps = config.substeps
    m.substep_dt = config.substep_dt

    m.goal_radius = config.goal_radius
    m.out_of_bounds_xy = config.out_of_bounds_xy
    m.out_of_bounds_z = config.out_of_bounds_z
    # evaluation mode is no environment respawning
    m.respawn_fraction = config.respawn_fraction if config.respawn else 0.0
    m.respawn_ticks = config.respawn_ticks
    m.spawn_margin = config.spawn_margin
    m.spawn_drop_height = config.spawn_drop_height
    m.spawn_tries = config.spawn_tries
    m.max_episode_steps = config.max_episode_steps

    m.distance_scale = config.distance_scale
    m.distance_clip = config.distance_clip
    m.goal_reward = config.goal_reward
    m.out_of_bounds_penalty = config.out_of_bounds_penalty
    m.time_penalty = config.time_penalty
    m.slow_speed = config.slow_speed
    m.slow_penalty = config.slow_penalty
    m.potential_scale = config.potential_scale
    m.potential_gamma = config.potential_gamma
    m.alignment_scale = config.alignment_scale
    m.approach_scale = config.approach_scale
    m.sphere_approach_scale = config.sphere_approach_scale
    m.approach_radius = config.approach_radius
    m.reward_normalizer = config.reward_normalizer

    m.heightmap_resolution = config.heightmap_resolution
    m.heightmap_max_height = config.heightmap_max_height
    m.max_object_speed = config.max_object_speed
    m.camera_resolution = config.camera_resolution
    return m


class Data:
    """Per-environment state and outputs; every array's leading dimension is the environment.

    The arrays named in :attr:`SCRATCH` are not state: every step and reset writes them before
    it reads them. The actuator family adds its own state arrays
    (:meth:`~terrashift_rl.sim.actuators.Actuator.allocate`).

    Args:
        config: the scene's config.
        num_envs: number of environments.
        device: Warp device.
        surface_flow: allocate ``surface_velocity`` (the family slides the surface in plane).
    """

    SCRATCH = (
        "surface_velocity",
        "sphere_position_next",
        "sphere_velocity_next",
        "sphere_angular_velocity_next",
    )

    def __init__(
        self,
        config: TerraShiftConfig,
        *,
        num_envs: int,
        device: wp.context.Device,
        surface_flow: bool = False,
    ):
        n, k, m = num_envs, config.num_agents, config.num_objects
        g, r = config.grid_size, config.heightmap_resolution

        def zeros(shape, dtype=float):
            return wp.zeros(shape, dtype=dtype, device=device)

        self.num_envs = n
        self.action = zeros((n, k, ACTION_DIM))
        """Current per-agent actions in [-1, 1], shape [num_envs, K, 6]."""
        # columns
        self.column_height_prev = zeros((n, g, g))
        """Wave heights at the start of the current tick [m], shape [num_envs, G(y), G(x)]."""
        self.column_height = zeros((n, g, g))
        """Wave heights at the end of the current tick [m], shape [num_envs, G(y), G(x)]."""
        self.surface_velocity = zeros((n, g, g) if surface_flow else (n, 0, 0), wp.vec2)
        """In-plane velocity with which each column's surface slides over the current tick
        [m/s], shape [num_envs, G(y), G(x)], vec2; empty unless ``surface_flow`` (the actuator
        family slides the surface)."""
        # spheres: the substep kernel reads one buffer and writes the other
        self.sphere_position = zeros((n, m), wp.vec3)
        """Sphere centres [m], shape [num_envs, M], vec3."""
        self.sphere_velocity = zeros((n, m), wp.vec3)
        """Sphere linear velocities [m/s], shape [num_envs, M], vec3."""
        self.sphere_angular_velocity = zeros((n, m), wp.vec3)
        """Sphere angular velocities [rad/s], shape [num_envs, M], vec3."""
        self.sphere_position_next = zeros((n, m), wp.vec3)
        self.sphere_velocity_next = zeros((n, m), wp.vec3)
        self.sphere_angular_velocity_next = zeros((n, m), wp.vec3)
        self.sphere_active = zeros((n, m), wp.int32)
        """1 where the sphere is in play, shape [num_envs, M]."""
        self.spawn_timer = zeros((n, m), wp.int32)
        """Ticks until an inactive sphere (re)spawns; -1 once resolved for good, [num_envs, M]."""
        self.surface_work = zeros((n, m))
        """Positive work the surface has done on the sphere in each slot since the episode
        began [J], [num_envs, M]; counted only with ``count_surface_work``."""
        self.goal_distance = zeros((n, m))
        """Distance of each active sphere to its goal at the last tick [m], [num_envs, M]."""
        self.approach_gap = wp.full((n, k), -1.0, dtype=float, device=device)
        """Each wavelet's distance beyond ``approach_radius`` to its nearest active sphere at
        the last tick [cells], -1 where that is not known (no sphere, a new episode, or
        ``approach_scale`` 0), [num_envs, K]."""
        self.sphere_approach_gap = wp.full((n, m), -1.0, dtype=float, device=device)
        """Each sphere's distance beyond ``approach_radius`` to its nearest wavelet at the last
        tick [cells], -1 where that is not known (the sphere not in play, or
        ``sphere_approach_scale`` 0), [num_envs, M]."""
        self.goal_cell = zeros((n, config.num_goals), wp.vec2i)
        """Column (ix, iy) each goal is attached to, shape [num_envs, num_goals], vec2i."""
        # bookkeeping
        self.rng = zeros(n, wp.uint32)
        """Per-environment random state."""
        self.step_count = zeros(n, wp.int32)
        """Decisions since the last reset, shape [num_envs]."""
        self.reward = zeros(n)
        """Team reward of the last decision (summed over the action repeat), [num_envs]."""
        self.terminated = zeros(n, wp.bool)
        """True once every object is resolved in evaluation mode, shape [num_envs]."""
        self.truncated = zeros(n, wp.bool)
        """True at the step limit, shape [num_envs]."""
        self.episode_goals = zeros(n, wp.int32)
        """Goals reached since the last reset, shape [num_envs]."""
        self.episode_out_of_bounds = zeros(n, wp.int32)
        """Objects lost out of bounds since the last reset, shape [num_envs]."""
        self.reset_mask = zeros(n, wp.bool)
        """Environments selected for a reset, shape [num_envs]."""
        # observations
        self.heightmap = zeros((n, 1, r, r))
        """Ray heights mapped to [-1, 1], rows along y, shape [num_envs, 1, R, R]."""
        self.object_features = zeros((n, m, OBJECT_FEATURES))
        """Normalised object sequence, zeros where inactive, shape [num_envs, M, 9]."""
        self.object_mask = zeros((n, m), wp.bool)
        """True where the object slot holds an active sphere, shape [num_envs, M]."""
        self.agent_features = zeros((n, k, AGENT_FEATURES))
        """Normalised agent (patch) parameters in [-1, 1], shape [num_envs, K, 9]."""
        c = config.camera_resolution
        self.camera = zeros((n, 1, c, c))
        """Overhead greyscale image in [0, 1], rows along y (``sim/camera.py``), shape
        [num_envs, 1, C, C]; empty (C = 0) without a camera."""
