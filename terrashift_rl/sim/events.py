"""Events stage: episode resets, spawning, goals, out-of-bounds, reward and episode limits.

Kernels here run one thread per environment, so every per-environment sum (the team reward,
the event counts) is accumulated in a fixed order and a seeded run is bit-reproducible.
"""

from __future__ import annotations

import warp as wp

from terrashift_rl.sim.columns import column_center
from terrashift_rl.sim.types import Model

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.func
def random_spawn_cell(model: Model, rng: wp.array(dtype=wp.uint32), e: int) -> wp.vec2i:
    """A uniformly random cell at least ``spawn_margin`` cells from every edge."""
    state = rng[e]
    lo = model.spawn_margin
    hi = model.grid_size - model.spawn_margin
    ix = wp.randi(state, lo, hi)
    iy = wp.randi(state, lo, hi)
    rng[e] = state
    return wp.vec2i(ix, iy)


@wp.func
def goal_position(model: Model, height: wp.array3d(dtype=float), e: int, cell: wp.vec2i) -> wp.vec3:
    """A goal rides one sphere radius above the top of the column it is attached to."""
    top = model.column_rest_top + height[e, cell[1], cell[0]]
    return wp.vec3(
        column_center(model, cell[0]), column_center(model, cell[1]), top + model.sphere_radius
    )


@wp.func
def respawns(model: Model, e: int) -> bool:
    """Whether environment ``e`` respawns resolved spheres: where ``e * respawn_fraction``
    passes a whole number on the way to ``e + 1`` (all of them at 1, every second one at 0.5,
    none at 0, the model's fraction in evaluation mode)."""
    f = model.respawn_fraction
    return int(float(e + 1) * f) > int(float(e) * f)


@wp.func
def assigned_goal(
    model: Model,
    height: wp.array3d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    e: int,
    j: int,
) -> wp.vec3:
    return goal_position(model, height, e, goal_cell[e, j % model.num_goals])


@wp.func
def try_spawn(
    model: Model,
    rng: wp.array(dtype=wp.uint32),
    e: int,
    j: int,
    height: wp.array3d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    velocity: wp.array2d(dtype=wp.vec3),
    angular_velocity: wp.array2d(dtype=wp.vec3),
    goal_distance: wp.array2d(dtype=float),
) -> int:
    """Places sphere ``j`` on a free random cell, at rest, just above the local column tops.

    A cell is free when no active sphere overlaps it and the sphere's own goal is more than
    two goal radii away. Returns 1 on success; after ``spawn_tries`` misses returns 0 and the
    caller tries again on the next tick.
    """
    r = model.sphere_radius
    goal = assigned_goal(model, height, goal_cell, e, j)
    for _ in range(model.spawn_tries):
        cell = random_spawn_cell(model, rng, e)
        x = column_center(model, cell[0])
        y = column_center(model, cell[1])
        free = int(1)
        for o in range(model.num_objects):
            if o != j and active[e, o] != 0:
                q = position[e, o]
                if (q[0] - x) * (q[0] - x) + (q[1] - y) * (q[1] - y) < 4.0 * r * r:
                    free = int(0)
        gr = 2.0 * model.goal_radius
        if (goal[0] - x) * (goal[0] - x) + (goal[1] - y) * (goal[1] - y) < gr * gr:
            free = int(0)
        if free != 0:
            reach = int(wp.ceil(r / model.cell_size))
            top = float(-1.0e6)
            g = model.grid_size
            for iy in range(wp.max(cell[1] - reach, 0), wp.min(cell[1] + reach, g - 1) + 1):
                for ix in range(wp.max(cell[0] - reach, 0), wp.min(cell[0] + reach, g - 1) + 1):
                    top = wp.max(top, model.column_rest_top + height[e, iy, ix])
            p = wp.vec3(x, y, top + r + model.spawn_drop_height)
            position[e, j] = p
            velocity[e, j] = wp.vec3(0.0)
            angular_velocity[e, j] = wp.vec3(0.0)
            active[e, j] = 1
            goal_distance[e, j] = wp.length(p - goal)
            return 1
    return 0


@wp.kernel
def reset_episodes(
    model: Model,
    reset_mask: wp.array(dtype=wp.bool),
    rng: wp.array(dtype=wp.uint32),
    approach_gap: wp.array2d(dtype=float),
    sphere_approach_gap: wp.array2d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    active: wp.array2d(dtype=wp.int32),
    spawn_timer: wp.array2d(dtype=wp.int32),
    surface_work: wp.array2d(dtype=float),
    step_count: wp.array(dtype=wp.int32),
    reward: wp.array(dtype=float),
    terminated: wp.array(dtype=wp.bool),
    truncated: wp.array(dtype=wp.bool),
    episode_goals: wp.array(dtype=wp.int32),
    episode_out_of_bounds: wp.array(dtype=wp.int32),
):
    """Starts a new episode where ``reset_mask`` is set: random goals, spheres queued to spawn
    ``respawn_ticks`` apart (the actuator family draws its own start first). Launch dim:
    [num_envs]."""
    e = wp.tid()
    if not reset_mask[e]:
        return
    for k in range(model.num_agents):
        approach_gap[e, k] = -1.0
    # goals on distinct cells, at least two cells apart where the tries allow
    for i in range(model.num_goals):
        cell = random_spawn_cell(model, rng, e)
        for _ in range(model.spawn_tries):
            clash = int(0)
            for o in range(i):
                other = goal_cell[e, o]
                if wp.abs(other[0] - cell[0]) < 2 and wp.abs(other[1] - cell[1]) < 2:
                    clash = int(1)
            if clash == 0:
                break
            cell = random_spawn_cell(model, rng, e)
        goal_cell[e, i] = cell
    for j in range(model.num_objects):
        active[e, j] = 0
        spawn_timer[e, j] = j * model.respawn_ticks
        sphere_approach_gap[e, j] = -1.0
        surface_work[e, j] = 0.0
    step_count[e] = 0
    reward[e] = 0.0
    terminated[e] = False
    truncated[e] = False
    episode_goals[e] = 0
    episode_out_of_bounds[e] = 0


@wp.kernel
def spawn_due(
    model: Model,
    reset_mask: wp.array(dtype=wp.bool),
    rng: wp.array(dtype=wp.uint32),
    height: wp.array3d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    active: wp.array2d(dtype=wp.int32),
    spawn_timer: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    velocity: wp.array2d(dtype=wp.vec3),
    angular_velocity: wp.array2d(dtype=wp.vec3),
    goal_distance: wp.array2d(dtype=float),
):
    """Spawns the spheres whose timer is zero, where ``reset_mask`` is set (after a reset, so the
    first observation already holds them). Launch dim: [num_envs]."""
    e = wp.tid()
    if not reset_mask[e]:
        return
    for j in range(model.num_objects):
        if active[e, j] == 0 and spawn_timer[e, j] == 0:
            try_spawn(
                model,
                rng,
                e,
                j,
                height,
                goal_cell,
                active,
                position,
                velocity,
                angular_velocity,
                goal_distance,
            )


@wp.func
def cell_distance(model: Model, a: wp.vec2, p: wp.vec3) -> float:
    """Distance from a wavelet centre ``a`` [cells] to a sphere centre ``p`` [m] in the
    wavelets' cell coordinates (column i sits at x = i), the short way round a wrapping grid."""
    g = float(model.grid_size)
    dx = (p[0] + model.half_platform) / model.cell_size - 0.5 - a[0]
    dy = (p[1] + model.half_platform) / model.cell_size - 0.5 - a[1]
    if model.wrap_edges != 0:
        dx = dx - g * wp.floor(dx / g + 0.5)
        dy = dy - g * wp.floor(dy / g + 0.5)
    return wp.sqrt(dx * dx + dy * dy)


@wp.func
def approach_gap_of(
    model: Model,
    e: int,
    k: int,
    agent_position: wp.array2d(dtype=wp.vec2),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
) -> float:
    """Distance of wavelet ``k`` to its nearest active sphere beyond ``approach_radius``
    [cells]; -1 with no sphere in play."""
    nearest = float(-1.0)
    for j in range(model.num_objects):
        if active[e, j] != 0:
            d = cell_distance(model, agent_position[e, k], position[e, j])
            if nearest < 0.0 or d < nearest:
                nearest = d
    if nearest < 0.0:
        return -1.0
    return wp.max(nearest - model.approach_radius, 0.0)


@wp.func
def sphere_approach_gap_of(
    model: Model,
    e: int,
    j: int,
    agent_position: wp.array2d(dtype=wp.vec2),
    position: wp.array2d(dtype=wp.vec3),
) -> float:
    """Distance of sphere ``j`` to its nearest wavelet beyond ``approach_radius`` [cells]."""
    nearest = cell_distance(model, agent_position[e, 0], position[e, j])
    for k in range(1, model.num_agents):
        nearest = wp.min(nearest, cell_distance(model, agent_position[e, k], position[e, j]))
    return wp.max(nearest - model.approach_radius, 0.0)


@wp.kernel
def begin_decision(reward: wp.array(dtype=float)):
    """Clears the reward accumulated over the action repeat. Launch dim: [num_envs]."""
    reward[wp.tid()] = 0.0


@wp.kernel
def tick_events(
    model: Model,
    rng: wp.array(dtype=wp.uint32),
    height: wp.array3d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    active: wp.array2d(dtype=wp.int32),
    spawn_timer: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    velocity: wp.array2d(dtype=wp.vec3),
    angular_velocity: wp.array2d(dtype=wp.vec3),
    goal_distance: wp.array2d(dtype=float),
    agent_position: wp.array2d(dtype=wp.vec2),
    approach_gap: wp.array2d(dtype=float),
    sphere_approach_gap: wp.array2d(dtype=float),
    reward: wp.array(dtype=float),
    episode_goals: wp.array(dtype=wp.int32),
    episode_out_of_bounds: wp.array(dtype=wp.int32),
):
    """Goals, out-of-bounds, respawns and the reward of one physics tick. Launch dim: [num_envs].

    Per active sphere: the goal bonus when within ``goal_radius`` of its goal, else the
    out-of-bounds penalty when it left the box, else the shaping terms (distance improvement,
    potential, slow-ball penalty, velocity alignment). Per wavelet, with ``approach_scale``:
    how far it closed on its nearest sphere (:func:`approach_gap_of`) since the last tick,
    unless a sphere spawned or was resolved on this one. Per sphere in play on this tick and
    the last, with ``sphere_approach_scale``: how far its nearest wavelet closed on it
    (:func:`sphere_approach_gap_of`). The tick's team reward is
    ``(time_penalty + sum) / reward_normalizer``.
    """
    e = wp.tid()
    total = float(0.0)
    changed = int(0)  # a sphere spawned or was resolved on this tick
    for j in range(model.num_objects):
        if active[e, j] != 0:
            p = position[e, j]
            v = velocity[e, j]
            goal = assigned_goal(model, height, goal_cell, e, j)
            to_goal = goal - p
            d = wp.length(to_goal)
            lim = model.out_of_bounds_xy
            resolved = int(0)
            if d <= model.goal_radius:
                total += model.goal_reward
                episode_goals[e] = episode_goals[e] + 1
                resolved = int(1)
            elif (
                wp.abs(p[0]) > lim
                or wp.abs(p[1]) > lim
                or p[2] < 0.0
                or p[2] > model.out_of_bounds_z
            ):
                total += model.out_of_bounds_penalty
                episode_out_of_bounds[e] = episode_out_of_bounds[e] + 1
                resolved = int(1)
            else:
                previous = goal_distance[e, j]
                clip = model.distance_clip
                total += model.distance_scale * wp.clamp(previous - d, -clip, clip)
                total += model.potential_scale * (previous - model.potential_gamma * d)
                speed = wp.length(v)
                if speed < model.slow_speed:
                    total += model.slow_penalty
                if speed > 1.0e-6 and d > 1.0e-6:
                    total += model.alignment_scale * wp.dot(v, to_goal) / (speed * d)
                goal_distance[e, j] = d
            if resolved != 0:
                changed = int(1)
                active[e, j] = 0
                if respawns(model, e):
                    spawn_timer[e, j] = model.respawn_ticks
                else:
                    spawn_timer[e, j] = -1
        else:
            if spawn_timer[e, j] > 0:
                spawn_timer[e, j] = spawn_timer[e, j] - 1
            if spawn_timer[e, j] == 0:
                try_spawn(
                    model,
                    rng,
                    e,
                    j,
                    height,
                    goal_cell,
                    active,
                    position,
                    velocity,
                    angular_velocity,
                    goal_distance,
                )
                changed = changed + active[e, j]
    if model.approach_scale != 0.0:
        for k in range(model.num_agents):
            gap = approach_gap_of(model, e, k, agent_position, active, position)
            previous = approach_gap[e, k]
            if changed == 0 and previous >= 0.0 and gap >= 0.0:
                total += model.approach_scale * (previous - gap)
            approach_gap[e, k] = gap
    if model.sphere_approach_scale != 0.0:
        for j in range(model.num_objects):
            gap = float(-1.0)
            if active[e, j] != 0:
                gap = sphere_approach_gap_of(model, e, j, agent_position, position)
                previous = sphere_approach_gap[e, j]
                if previous >= 0.0:
                    total += model.sphere_approach_scale * (previous - gap)
            sphere_approach_gap[e, j] = gap
    reward[e] = reward[e] + (model.time_penalty + total) / model.reward_normalizer


@wp.kernel
def end_decision(
    model: Model,
    active: wp.array2d(dtype=wp.int32),
    spawn_timer: wp.array2d(dtype=wp.int32),
    step_count: wp.array(dtype=wp.int32),
    terminated: wp.array(dtype=wp.bool),
    truncated: wp.array(dtype=wp.bool),
):
    """Counts the decision; sets ``truncated`` at the step limit and, where nothing respawns
    (:func:`respawns`), ``terminated`` once every sphere is resolved. Launch dim: [num_envs]."""
    e = wp.tid()
    count = step_count[e] + 1
    step_count[e] = count
    truncated[e] = count >= model.max_episode_steps
    if not respawns(model, e):
        done = bool(True)
        for j in range(model.num_objects):
            if active[e, j] != 0 or spawn_timer[e, j] != -1:
                done = False
        terminated[e] = done
