"""Observation stage: heightmap rays, the object sequence and the agent features.

Heightmap rows run along +y and columns along +x, the same layout as the column-height grid
``[G(y), G(x)]``, so row ``i`` / column ``j`` of both refer to the same side of the platform.
"""

from __future__ import annotations

import warp as wp

from terrashift_rl.sim.columns import column_center, column_top, smooth_surface
from terrashift_rl.sim.events import assigned_goal
from terrashift_rl.sim.types import SHAPE_BOX, SHAPE_ELLIPSOID, Model

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it

MISS = wp.constant(-1.0e6)


@wp.func
def normalised_height(model: Model, z: float) -> float:
    """Maps a height in [0, heightmap_max_height] m to [-1, 1] (clipping outside)."""
    h = model.heightmap_max_height
    return 2.0 * wp.clamp(z, 0.0, h) / h - 1.0


@wp.func
def surface_height(
    model: Model, height: wp.array3d(dtype=float), e: int, x: float, y: float
) -> float:
    """Height [m] at which a vertical ray at (x, y) meets the columns' tops, MISS if it falls
    between them onto the platform (ellipsoids leave gaps at the corners of their cells)."""
    g = model.grid_size
    ix = wp.clamp(int(wp.floor((x + model.half_platform) / model.cell_size)), 0, g - 1)
    iy = wp.clamp(int(wp.floor((y + model.half_platform) / model.cell_size)), 0, g - 1)
    z = float(MISS)
    if model.column_shape == SHAPE_BOX:
        z = column_top(model, height, height, e, iy, ix, 1.0)
    elif model.column_shape == SHAPE_ELLIPSOID:
        a = model.column_half_width
        dx = x - column_center(model, ix)
        dy = y - column_center(model, iy)
        rho2 = (dx * dx + dy * dy) / (a * a)
        if rho2 <= 1.0 + 1.0e-5:  # rays on the platform edge graze the outer columns
            top = column_top(model, height, height, e, iy, ix, 1.0)
            z = top - model.column_half_height * (1.0 - wp.sqrt(wp.max(1.0 - rho2, 0.0)))
    else:
        z = smooth_surface(model, height, height, e, x, y, 1.0)[0]
    return z


@wp.kernel
def cast_heightmap(
    model: Model,
    height: wp.array3d(dtype=float),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    heightmap: wp.array4d(dtype=float),
):
    """Casts one vertical ray per lattice point; the lattice spans the platform edge to edge.

    The highest hit of columns and active spheres is recorded; a miss reads as -1.
    Launch dim: [num_envs, R] as (env, column = x): a thread casts the R rays of one lattice
    column, the columns first, then raises the rays that a sphere covers, visiting only the
    spheres that reach over its lattice column (most reach over none).
    """
    e, rx = wp.tid()
    step = 2.0 * model.half_platform / float(model.heightmap_resolution - 1)
    x = -model.half_platform + float(rx) * step
    for ry in range(model.heightmap_resolution):
        y = -model.half_platform + float(ry) * step
        z = surface_height(model, height, e, x, y)
        if z == MISS:
            heightmap[e, 0, ry, rx] = -1.0
        else:
            heightmap[e, 0, ry, rx] = normalised_height(model, z)

    # normalised_height never decreases with the height, so the highest hit can be taken after
    # normalising
    r = model.sphere_radius
    last = model.heightmap_resolution - 1
    for j in range(model.num_objects):
        if active[e, j] != 0:
            p = position[e, j]
            if (p[0] - x) * (p[0] - x) <= r * r:
                # the rows within reach of the sphere, widened to whole rows
                lo = int(wp.floor((p[1] - r + model.half_platform) / step))
                hi = int(wp.ceil((p[1] + r + model.half_platform) / step))
                for ry in range(wp.max(lo, 0), wp.min(hi, last) + 1):
                    y = -model.half_platform + float(ry) * step
                    d2 = (p[0] - x) * (p[0] - x) + (p[1] - y) * (p[1] - y)
                    if d2 <= r * r:
                        top = normalised_height(model, p[2] + wp.sqrt(r * r - d2))
                        heightmap[e, 0, ry, rx] = wp.max(heightmap[e, 0, ry, rx], top)


@wp.kernel
def gather_features(
    model: Model,
    height: wp.array3d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    velocity: wp.array2d(dtype=wp.vec3),
    object_features: wp.array3d(dtype=float),
    object_mask: wp.array2d(dtype=wp.bool),
):
    """Writes the normalised object sequence and its mask (the actuator family writes the
    agent features).

    Objects: [x, y, z, goal x, goal y, goal z, v_x, v_y, v_z]; x and y over the half platform,
    z as the heightmap, velocity clipped to +-max_object_speed and divided by it; zeros where
    the slot is inactive. Launch dim: [num_envs, M].
    """
    e, i = wp.tid()
    half = model.half_platform
    vmax = model.max_object_speed
    on = active[e, i] != 0
    object_mask[e, i] = on
    if on:
        p = position[e, i]
        goal = assigned_goal(model, height, goal_cell, e, i)
        v = velocity[e, i]
        object_features[e, i, 0] = p[0] / half
        object_features[e, i, 1] = p[1] / half
        object_features[e, i, 2] = normalised_height(model, p[2])
        object_features[e, i, 3] = goal[0] / half
        object_features[e, i, 4] = goal[1] / half
        object_features[e, i, 5] = normalised_height(model, goal[2])
        object_features[e, i, 6] = wp.clamp(v[0], -vmax, vmax) / vmax
        object_features[e, i, 7] = wp.clamp(v[1], -vmax, vmax) / vmax
        object_features[e, i, 8] = wp.clamp(v[2], -vmax, vmax) / vmax
    else:
        for f in range(9):
            object_features[e, i, f] = 0.0
