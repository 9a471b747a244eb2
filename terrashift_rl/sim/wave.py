"""Wave stage: second-order wavelet parameter dynamics and the column heights they produce.

Each agent owns one Gaussian wavelet with state (x, y, theta, A, sigma_x, sigma_y, v_x, v_y,
omega). An action in [-1, 1]^6 changes the *rates* (v_x, v_y, omega) and the shape (A, sigma_x,
sigma_y) by a gain times the wave step each physics tick, or, with ``action_mode="target"``,
sets the values they move towards at that same limited rate, or, with ``"position"``, sets
where the wavelet goes (its velocity moves, at that rate, towards one that points there) and
changes the rest as ``delta`` does, or, with ``"shape"``, changes the rates as ``delta`` does
and sets the shape as ``target`` does; rates are clamped before they move the wavelet, so the
speed limits hold exactly. Heights are the clipped sum of all wavelets at integer cell
positions, with offsets wrapped into [-G/2, G/2) when the grid is a torus.
"""

from __future__ import annotations

import warp as wp

from terrashift_rl.sim.types import ACTION_POSITION, ACTION_SHAPE, ACTION_TARGET, Model

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
def wavelet_frame(angle: float, sigma: wp.vec2) -> wp.vec4:
    """What the height sum needs of a wavelet's angle and widths: (cos theta, sin theta,
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
    """Applies one physics tick of action deltas to every wavelet and derives its
    :func:`wavelet_frame`. Launch dim: [num_envs, K]."""
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
    frame[e, k] = wavelet_frame(theta, s)


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
    g = float(model.grid_size)
    inverse_g = 1.0 / g
    total = float(0.0)
    for k in range(model.num_agents):
        p = position[e, k]
        dx = float(ix) - p[0]
        dy = float(iy) - p[1]
        if model.wrap_edges != 0:
            dx = wrap_offset(dx, g, inverse_g)
            dy = wrap_offset(dy, g, inverse_g)
        f = frame[e, k]
        # rotate the offset by -theta into the wavelet's frame
        xr = f[0] * dx + f[1] * dy
        yr = -f[1] * dx + f[0] * dy
        total += amplitude[e, k] * wp.exp(-0.5 * (xr * xr * f[2] + yr * yr * f[3]))
    hmax = model.max_column_height
    h = wp.clamp(total, -hmax, hmax)
    if keep_velocity != 0:
        height_prev[e, iy, ix] = height[e, iy, ix]
    else:
        height_prev[e, iy, ix] = h
    height[e, iy, ix] = h
