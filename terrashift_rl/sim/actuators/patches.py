"""Patch agents: mobile Gaussian patches, the agents of every family in this package.

Each agent owns one patch with state (x, y, theta, A, sigma_x, sigma_y, v_x, v_y, omega): a
centre [cells], an orientation, an amplitude A in the family's unit (a height for the
wavelets, a surface speed for the surface flow, a spin rate for the rotors), the widths of its
Gaussian envelope along and across theta [cells], and the rates of the centre and the
orientation. An action in [-1, 1]^6 changes the *rates* (v_x, v_y, omega) and the shape (A,
sigma_x, sigma_y) by a gain times the wave step each physics tick, or, with
``action_mode="target"``, sets the values they move towards at that same limited rate, or,
with ``"position"``, sets where the patch goes (its velocity moves, at that rate, towards one
that points there) and changes the rest as ``delta`` does, or, with ``"shape"``, changes the
rates as ``delta`` does and sets the shape as ``target`` does; rates are clamped before they
move the patch, so the speed limits hold exactly. A family (:class:`PatchActuator`) says what
the patches do to the surface: its kernel evaluates the envelopes at the columns
(:func:`envelope`), with offsets wrapped into [-G/2, G/2) when the grid is a torus.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, ClassVar

import warp as wp

from terrashift_rl.sim.actuators.base import Actuator
from terrashift_rl.sim.types import (
    ACTION_NAMES,
    ACTION_POSITION,
    ACTION_SHAPE,
    ACTION_TARGET,
    Data,
    Model,
)

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig
    from terrashift_rl.sim.simulator import Simulator

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it

TWO_PI = wp.constant(6.283185307179586)


@wp.func
def wrap_offset(d: float, period: float, inverse_period: float) -> float:
    """Maps an offset to [-period / 2, period / 2) (``inverse_period`` is 1 / period: a
    product costs less than a quotient)."""
    return d - period * wp.floor(d * inverse_period + 0.5)


@wp.func
def towards(target: float, value: float, gain: float) -> float:
    """The action that moves ``value`` towards ``target`` in one tick, in units of a full delta
    action's change ``gain``: at most one either way (the actuators' rate limit)."""
    return wp.clamp((target - value) / gain, -1.0, 1.0)


@wp.func
def envelope_frame(angle: float, sigma: wp.vec2) -> wp.vec4:
    """What the envelope needs of a patch's angle and widths: (cos theta, sin theta,
    1 / sigma_x^2, 1 / sigma_y^2)."""
    return wp.vec4(
        wp.cos(angle), wp.sin(angle), 1.0 / (sigma[0] * sigma[0]), 1.0 / (sigma[1] * sigma[1])
    )


@wp.kernel
def update_agents(
    model: Model,
    action: wp.array3d(dtype=float),
    position: wp.array2d(dtype=wp.vec2),
    velocity: wp.array2d(dtype=wp.vec2),
    angle: wp.array2d(dtype=float),
    angular_velocity: wp.array2d(dtype=float),
    amplitude: wp.array2d(dtype=float),
    sigma: wp.array2d(dtype=wp.vec2),
    frame: wp.array2d(dtype=wp.vec4),
):
    """Applies one physics tick of action deltas to every patch and derives its
    :func:`envelope_frame`. Launch dim: [num_envs, K]."""
    e, k = wp.tid()
    step = model.wave_step
    vmax = model.max_velocity
    omax = model.max_angular_velocity
    amax = model.max_amplitude
    # the action's dims in ACTION_NAMES order, each in [-1, 1]
    a = wp.vec2(wp.clamp(action[e, k, 0], -1.0, 1.0), wp.clamp(action[e, k, 1], -1.0, 1.0))
    a_omega = wp.clamp(action[e, k, 2], -1.0, 1.0)
    a_amplitude = wp.clamp(action[e, k, 3], -1.0, 1.0)
    a_sigma = wp.vec2(wp.clamp(action[e, k, 4], -1.0, 1.0), wp.clamp(action[e, k, 5], -1.0, 1.0))
    v0 = velocity[e, k]
    w0 = angular_velocity[e, k]
    amp0 = amplitude[e, k]
    s0 = sigma[e, k]

    d_velocity = a
    d_omega = a_omega
    d_amplitude = a_amplitude
    d_sigma = a_sigma
    g = float(model.grid_size)
    v_gain = model.velocity_gain * step
    if model.action_mode == ACTION_TARGET or model.action_mode == ACTION_SHAPE:
        # the change towards each target, in units of a full delta action's change per tick
        d_amplitude = towards(a_amplitude * amax, amp0, model.amplitude_gain * step)
        half_range = 0.5 * (model.sigma_max - model.sigma_min)
        s_gain = model.sigma_gain * step
        d_sigma = wp.vec2(
            towards(model.sigma_min + (a_sigma[0] + 1.0) * half_range, s0[0], s_gain),
            towards(model.sigma_min + (a_sigma[1] + 1.0) * half_range, s0[1], s_gain),
        )
    if model.action_mode == ACTION_TARGET:
        d_velocity = wp.vec2(
            towards(a[0] * vmax, v0[0], v_gain), towards(a[1] * vmax, v0[1], v_gain)
        )
        d_omega = towards(a_omega * omax, w0, model.angular_velocity_gain * step)
    elif model.action_mode == ACTION_POSITION:
        # a servo: the velocity moves towards one that points to the target position (the short
        # way round a wrapping grid), at most a full delta action's change per tick
        offset = (a + wp.vec2(1.0, 1.0)) * (0.5 * g) - position[e, k]
        if model.wrap_edges != 0:
            offset = wp.vec2(wrap_offset(offset[0], g, 1.0 / g), wrap_offset(offset[1], g, 1.0 / g))
        aim = model.position_gain * offset
        d_velocity = wp.vec2(
            towards(wp.clamp(aim[0], -vmax, vmax), v0[0], v_gain),
            towards(wp.clamp(aim[1], -vmax, vmax), v0[1], v_gain),
        )

    v = v0 + v_gain * d_velocity
    v = wp.vec2(wp.clamp(v[0], -vmax, vmax), wp.clamp(v[1], -vmax, vmax))
    w = wp.clamp(w0 + model.angular_velocity_gain * step * d_omega, -omax, omax)
    amp = wp.clamp(amp0 + model.amplitude_gain * step * d_amplitude, model.min_amplitude, amax)
    s = s0 + model.sigma_gain * step * d_sigma
    s = wp.vec2(
        wp.clamp(s[0], model.sigma_min, model.sigma_max),
        wp.clamp(s[1], model.sigma_min, model.sigma_max),
    )

    p = position[e, k] + step * v
    if model.wrap_edges != 0:
        p = wp.vec2(p[0] - g * wp.floor(p[0] / g), p[1] - g * wp.floor(p[1] / g))
    else:
        p = wp.vec2(wp.clamp(p[0], 0.0, g - 1.0), wp.clamp(p[1], 0.0, g - 1.0))
    theta = angle[e, k] + step * w
    theta = theta - TWO_PI * wp.floor(theta / TWO_PI)

    position[e, k] = p
    velocity[e, k] = v
    angle[e, k] = theta
    angular_velocity[e, k] = w
    amplitude[e, k] = amp
    sigma[e, k] = s
    frame[e, k] = envelope_frame(theta, s)


@wp.func
def envelope(
    model: Model,
    position: wp.array2d(dtype=wp.vec2),
    frame: wp.array2d(dtype=wp.vec4),
    e: int,
    k: int,
    ix: int,
    iy: int,
) -> wp.vec3:
    """Patch ``k``'s Gaussian envelope at column (ix, iy), exp(-(x'^2 / sigma_x^2 + y'^2 /
    sigma_y^2) / 2), and the offset (dx, dy) [cells] from the patch's centre to the column (the
    short way round a torus); (x', y') is that offset rotated by -theta."""
    g = float(model.grid_size)
    p = position[e, k]
    dx = float(ix) - p[0]
    dy = float(iy) - p[1]
    if model.wrap_edges != 0:
        inverse_g = 1.0 / g
        dx = wrap_offset(dx, g, inverse_g)
        dy = wrap_offset(dy, g, inverse_g)
    f = frame[e, k]
    # rotate the offset by -theta into the patch's frame
    xr = f[0] * dx + f[1] * dy
    yr = -f[1] * dx + f[0] * dy
    return wp.vec3(wp.exp(-0.5 * (xr * xr * f[2] + yr * yr * f[3])), dx, dy)


@wp.func
def uniform(rng: wp.array(dtype=wp.uint32), e: int, low: float, high: float) -> float:
    """Draws from U[low, high) with environment ``e``'s random stream."""
    state = rng[e]
    x = wp.randf(state, low, high)
    rng[e] = state
    return x


@wp.kernel
def reset_agents(
    model: Model,
    reset_mask: wp.array(dtype=wp.bool),
    rng: wp.array(dtype=wp.uint32),
    position: wp.array2d(dtype=wp.vec2),
    velocity: wp.array2d(dtype=wp.vec2),
    angle: wp.array2d(dtype=float),
    angular_velocity: wp.array2d(dtype=float),
    amplitude: wp.array2d(dtype=float),
    sigma: wp.array2d(dtype=wp.vec2),
    frame: wp.array2d(dtype=wp.vec4),
):
    """Draws every patch's state uniformly from its ranges where ``reset_mask`` is set.
    Launch dim: [num_envs]."""
    e = wp.tid()
    if not reset_mask[e]:
        return
    g = float(model.grid_size)
    for k in range(model.num_agents):
        position[e, k] = wp.vec2(uniform(rng, e, 0.0, g - 1.0), uniform(rng, e, 0.0, g - 1.0))
        vmax = model.max_velocity
        velocity[e, k] = wp.vec2(uniform(rng, e, -vmax, vmax), uniform(rng, e, -vmax, vmax))
        angle[e, k] = uniform(rng, e, 0.0, 6.283185307179586)
        omax = model.max_angular_velocity
        angular_velocity[e, k] = uniform(rng, e, -omax, omax)
        amplitude[e, k] = uniform(rng, e, model.min_amplitude, model.max_amplitude)
        sigma[e, k] = wp.vec2(
            uniform(rng, e, model.sigma_min, model.sigma_max),
            uniform(rng, e, model.sigma_min, model.sigma_max),
        )
        frame[e, k] = envelope_frame(angle[e, k], sigma[e, k])


@wp.kernel
def gather_agent_features(
    model: Model,
    position: wp.array2d(dtype=wp.vec2),
    velocity: wp.array2d(dtype=wp.vec2),
    angle: wp.array2d(dtype=float),
    angular_velocity: wp.array2d(dtype=float),
    amplitude: wp.array2d(dtype=float),
    sigma: wp.array2d(dtype=wp.vec2),
    agent_features: wp.array3d(dtype=float),
):
    """Writes [x, y, theta, A, sigma_x, sigma_y, v_x, v_y, omega], each mapped from its range
    to [-1, 1]. Launch dim: [num_envs, K]."""
    e, i = wp.tid()
    g = float(model.grid_size)
    srange = model.sigma_max - model.sigma_min
    c = position[e, i]
    u = velocity[e, i]
    s = sigma[e, i]
    agent_features[e, i, 0] = 2.0 * c[0] / g - 1.0
    agent_features[e, i, 1] = 2.0 * c[1] / g - 1.0
    agent_features[e, i, 2] = angle[e, i] / 3.141592653589793 - 1.0
    agent_features[e, i, 3] = amplitude[e, i] / model.max_amplitude
    sx = float(0.0)
    sy = float(0.0)
    if srange > 0.0:
        sx = 2.0 * (s[0] - model.sigma_min) / srange - 1.0
        sy = 2.0 * (s[1] - model.sigma_min) / srange - 1.0
    agent_features[e, i, 4] = sx
    agent_features[e, i, 5] = sy
    agent_features[e, i, 6] = u[0] / model.max_velocity
    agent_features[e, i, 7] = u[1] / model.max_velocity
    agent_features[e, i, 8] = angular_velocity[e, i] / model.max_angular_velocity


class PatchActuator(Actuator):
    """A family whose agents are mobile Gaussian patches (this module's state, dynamics, start
    and features); a subclass says what the amplitude is (:meth:`amplitude_limits`) and what
    the patches do to the surface (:meth:`launch_surface`)."""

    action_names = ACTION_NAMES
    scratch = ("agent_frame",)

    def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
        """(lowest, highest, change per unit action per wave step) of the amplitude, in the
        family's unit."""
        raise NotImplementedError

    def configure(self, model: Model, config: TerraShiftConfig) -> None:
        model.min_amplitude, model.max_amplitude, model.amplitude_gain = self.amplitude_limits(
            config
        )

    def allocate(self, data: Data, config: TerraShiftConfig, device: wp.context.Device) -> None:
        n, k = data.num_envs, config.num_agents

        def zeros(dtype=float):
            return wp.zeros((n, k), dtype=dtype, device=device)

        data.agent_position = zeros(wp.vec2)
        """Patch centres [cells], shape [num_envs, K], vec2."""
        data.agent_velocity = zeros(wp.vec2)
        """Patch velocities [cells / wave step], shape [num_envs, K], vec2."""
        data.agent_angle = zeros()
        """Patch orientations theta in [0, 2 pi) [rad], shape [num_envs, K]."""
        data.agent_angular_velocity = zeros()
        """Patch angular velocities [rad / wave step], shape [num_envs, K]."""
        data.agent_amplitude = zeros()
        """Patch amplitudes [the family's unit], shape [num_envs, K]."""
        data.agent_sigma = zeros(wp.vec2)
        """Patch widths sigma_x, sigma_y [cells], shape [num_envs, K], vec2."""
        data.agent_frame = zeros(wp.vec4)
        """What the envelope needs of each patch's angle and widths, (cos theta, sin theta,
        1 / sigma_x^2, 1 / sigma_y^2) [1, 1, 1/cells^2, 1/cells^2]: derived once per tick, not
        at every column. Shape [num_envs, K], vec4."""

    def _state(self, data: Data) -> list[wp.array]:
        return [
            data.agent_position,
            data.agent_velocity,
            data.agent_angle,
            data.agent_angular_velocity,
            data.agent_amplitude,
            data.agent_sigma,
        ]

    def load(self, device: wp.context.Device) -> None:
        wp.load_module(reset_agents.module, device=device)

    def launch_reset(self, sim: Simulator) -> None:
        d = sim.data
        wp.launch(
            reset_agents,
            dim=sim.num_envs,
            inputs=[sim.model, d.reset_mask, d.rng, *self._state(d), d.agent_frame],
        )

    def launch_update(self, sim: Simulator) -> None:
        d = sim.data
        wp.launch(
            update_agents,
            dim=(sim.num_envs, sim.config.num_agents),
            inputs=[sim.model, d.action, *self._state(d), d.agent_frame],
        )

    def launch_observe(self, sim: Simulator) -> None:
        d = sim.data
        wp.launch(
            gather_agent_features,
            dim=(sim.num_envs, sim.config.num_agents),
            inputs=[sim.model, *self._state(d), d.agent_features],
        )


@wp.func
def limited(velocity: wp.vec2, limit: float) -> wp.vec2:
    """``velocity`` scaled down, where needed, to a norm of at most ``limit``."""
    speed = wp.length(velocity)
    if speed > limit:
        return velocity * (limit / speed)
    return velocity


@functools.cache
def sliding_kernel(patch_velocity: wp.Function) -> wp.Kernel:
    """The kernel that sums ``patch_velocity(model, amplitude, frame, envelope)``, one patch's
    in-plane surface velocity [m/s] at a column (``envelope``: :func:`envelope` there, ``frame``:
    :func:`envelope_frame`), over the patches at every column and clips it to ``max_speed``.
    Launched with (model, reset_mask, use_mask, max_speed, position, amplitude, frame,
    surface_velocity) over [num_envs, G(y), G(x)]; with ``use_mask`` only where ``reset_mask``
    is set."""

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def compute_surface_velocity(
        model: Model,
        reset_mask: wp.array(dtype=wp.bool),
        use_mask: int,
        max_speed: float,
        position: wp.array2d(dtype=wp.vec2),
        amplitude: wp.array2d(dtype=float),
        frame: wp.array2d(dtype=wp.vec4),
        surface_velocity: wp.array3d(dtype=wp.vec2),
    ):
        e, iy, ix = wp.tid()
        if use_mask != 0 and not reset_mask[e]:
            return
        total = wp.vec2(0.0)
        for k in range(model.num_agents):
            weight = envelope(model, position, frame, e, k, ix, iy)
            total += wp.static(patch_velocity)(model, amplitude[e, k], frame[e, k], weight)
        surface_velocity[e, iy, ix] = limited(total, max_speed)

    return compute_surface_velocity


class SlidingPatchActuator(PatchActuator):
    """A patch family that slides the surface in plane and leaves the columns at rest; its
    ``patch_velocity``, a Warp function, gives one patch's surface velocity at a column
    (:func:`sliding_kernel`)."""

    moves_columns = False
    moves_surface = True
    patch_velocity: ClassVar[wp.Function]

    def load(self, device: wp.context.Device) -> None:
        super().load(device)
        wp.load_module(sliding_kernel(self.patch_velocity).module, device=device)

    def launch_surface(self, sim: Simulator, *, reset: bool) -> None:
        d, g = sim.data, sim.config.grid_size
        wp.launch(
            sliding_kernel(self.patch_velocity),
            dim=(sim.num_envs, g, g),
            inputs=[
                sim.model,
                d.reset_mask,
                int(reset),
                sim.config.max_surface_speed,
                d.agent_position,
                d.agent_amplitude,
                d.agent_frame,
                d.surface_velocity,
            ],
        )
