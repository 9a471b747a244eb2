"""Camera stage: an orthographic overhead greyscale image of every scene.

The image ``camera`` [num_envs, 1, C, C] samples the same kind of lattice as the heightmap,
C x C points spanning the platform edge to edge, rows along +y and columns along +x, so a
camera and a heightmap of one resolution are aligned pixel for pixel. Each pixel is the first
thing a vertical ray from above meets:

- an active sphere wherever its top is above the columns' surface under the pixel (spheres
  hide each other the same way, the higher one in front; a sphere in a hollow between taller
  columns is hidden where they rise above it);
- otherwise the goal region of the nearest goal closer than ``goal_radius`` (horizontal
  distance from its column's centre), painted on the surface: only spheres hide a goal;
- otherwise the columns' surface, shaded by height, or the platform between the columns.

Grey levels (:func:`camera_levels`): the platform is 0; a column top runs from
``TERRAIN_LOW`` at its lowest (``column_rest_top - max_column_height``) to ``TERRAIN_HIGH``
at its highest, linearly in height; goals and spheres take the 2G levels spaced evenly over
[``MARKER_LOW``, 1], G = ``num_goals`` colour pairs in order goal 0, sphere 0, goal 1, sphere 1
and so on. Sphere j belongs to goal ``j mod num_goals``, so a sphere is one level step
brighter than its own goal, and every level tells apart what it shows.
"""

from __future__ import annotations

import warp as wp

from terrashift_rl.sim.columns import column_center
from terrashift_rl.sim.observations import MISS, surface_height
from terrashift_rl.sim.types import Model

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it

TERRAIN_LOW = 0.05
"""Grey level of the lowest column top (the platform, where no column is hit, is 0)."""
TERRAIN_HIGH = 0.4
"""Grey level of the highest column top."""
MARKER_LOW = 0.5
"""Grey level of goal 0; goals and spheres span [MARKER_LOW, 1], above every column."""


@wp.func
def marker_level(num_goals: int, pair: int, sphere: int) -> float:
    """Grey level of colour pair ``pair``'s goal (``sphere`` 0) or sphere (``sphere`` 1);
    callable from Python too."""
    return MARKER_LOW + (1.0 - MARKER_LOW) * float(2 * pair + sphere) / float(2 * num_goals - 1)


def camera_levels(num_goals: int) -> list[tuple[float, float]]:
    """The (goal, sphere) grey levels of each colour pair, as the camera draws them.

    Example:
        >>> [(round(goal, 3), round(sphere, 3)) for goal, sphere in camera_levels(2)]
        [(0.5, 0.667), (0.833, 1.0)]
    """
    return [
        (marker_level(num_goals, c, 0), marker_level(num_goals, c, 1)) for c in range(num_goals)
    ]


@wp.func
def terrain_level(model: Model, z: float) -> float:
    """Grey level of a column surface at height z [m]."""
    low = model.column_rest_top - model.max_column_height
    fraction = wp.clamp((z - low) / (2.0 * model.max_column_height), 0.0, 1.0)
    return TERRAIN_LOW + (TERRAIN_HIGH - TERRAIN_LOW) * fraction


@wp.func
def nearest_goal(
    model: Model, goal_cell: wp.array2d(dtype=wp.vec2i), e: int, x: float, y: float
) -> int:
    """The goal whose column's centre is nearest (x, y) and closer than ``goal_radius``, the
    lower index on a tie; -1 if none."""
    nearest = int(-1)
    nearest_d2 = model.goal_radius * model.goal_radius
    for c in range(model.num_goals):
        cell = goal_cell[e, c]
        dx = x - column_center(model, cell[0])
        dy = y - column_center(model, cell[1])
        d2 = dx * dx + dy * dy
        if d2 < nearest_d2:
            nearest = c
            nearest_d2 = d2
    return nearest


@wp.func
def front_sphere(
    model: Model,
    height: wp.array3d(dtype=float),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    e: int,
    x: float,
    y: float,
) -> int:
    """The active sphere a vertical ray at (x, y) meets first, above the columns' surface, the
    lower index on a tie; -1 if none."""
    top = surface_height(model, height, e, x, y)
    front = int(-1)
    r2 = model.sphere_radius * model.sphere_radius
    for j in range(model.num_objects):
        if active[e, j] != 0:
            p = position[e, j]
            d2 = (p[0] - x) * (p[0] - x) + (p[1] - y) * (p[1] - y)
            if d2 <= r2:
                sphere_top = p[2] + wp.sqrt(r2 - d2)
                if sphere_top > top:
                    top = sphere_top
                    front = j
    return front


@wp.func
def rows_within(model: Model, centre: float, reach: float) -> wp.vec2i:
    """First and last lattice rows (or columns) within ``reach`` [m] of ``centre`` [m],
    widened to whole rows and clamped to the image."""
    step = 2.0 * model.half_platform / float(model.camera_resolution - 1)
    lo = int(wp.floor((centre - reach + model.half_platform) / step))
    hi = int(wp.ceil((centre + reach + model.half_platform) / step))
    return wp.vec2i(wp.max(lo, 0), wp.min(hi, model.camera_resolution - 1))


@wp.kernel
def render_camera(
    model: Model,
    height: wp.array3d(dtype=float),
    goal_cell: wp.array2d(dtype=wp.vec2i),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    camera: wp.array4d(dtype=float),
):
    """Draws the overhead image (the module docstring's rules), a lattice column of pixels per
    thread as the heightmap's rays are cast: the columns' surface first, then the goal regions
    and the spheres that reach over the thread's column, each over its own rows only (most
    reach over none), where it is what a ray from above meets first.

    Launch dim: [num_envs, C] as (env, column = x).
    """
    e, cx = wp.tid()
    step = 2.0 * model.half_platform / float(model.camera_resolution - 1)
    x = -model.half_platform + float(cx) * step
    for cy in range(model.camera_resolution):
        y = -model.half_platform + float(cy) * step
        top = surface_height(model, height, e, x, y)
        level = float(0.0)
        if top != MISS:
            level = terrain_level(model, top)
        camera[e, 0, cy, cx] = level

    reach = model.goal_radius
    for c in range(model.num_goals):
        cell = goal_cell[e, c]
        if wp.abs(x - column_center(model, cell[0])) < reach:
            rows = rows_within(model, column_center(model, cell[1]), reach)
            for cy in range(rows[0], rows[1] + 1):
                y = -model.half_platform + float(cy) * step
                if nearest_goal(model, goal_cell, e, x, y) == c:
                    camera[e, 0, cy, cx] = marker_level(model.num_goals, c, 0)

    reach = model.sphere_radius
    for j in range(model.num_objects):
        p = position[e, j]
        if active[e, j] != 0 and wp.abs(x - p[0]) <= reach:
            rows = rows_within(model, p[1], reach)
            for cy in range(rows[0], rows[1] + 1):
                y = -model.half_platform + float(cy) * step
                if front_sphere(model, height, active, position, e, x, y) == j:
                    camera[e, 0, cy, cx] = marker_level(model.num_goals, j % model.num_goals, 1)
