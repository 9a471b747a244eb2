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

Three launches draw it: the terrain under every pixel, two columns of pixels per thread; then
each goal's region and then each sphere over it, a thread per pixel column of the object's
box, so that only the pixels about an object test it. The threads of one box walk its rows
together, so that the pixels they write at a time lie side by side in one row.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from terrashift_rl.sim.columns import column_center, column_top, smooth_surface
from terrashift_rl.sim.config import TerraShiftConfig
from terrashift_rl.sim.observations import MISS
from terrashift_rl.sim.types import SHAPE_BOX, SHAPE_ELLIPSOID, Data, Model

# nothing differentiates through it; on CUDA, divisions and square roots may be approximate
# (a few units in the last place): no pixel's grey level or placement notices
wp.set_module_options({"enable_backward": False, "fast_math": True})

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


@wp.struct
class CameraModel:
    """Constants of the camera derived from the scene's :class:`Model` once on the host
    (:func:`build_camera_model`), so that no pixel divides."""

    step: float
    """Distance between neighbouring pixels' centres [m]."""
    to_step: float
    """1 / step [1/m]."""
    step_in_cells: float
    """step / cell_size."""
    to_dome: float
    """1 / column_half_width^2 [1/m^2]: scales a dome's footprint to the unit disc."""
    shade_gain: float
    """Grey level per metre of surface height [1/m]."""
    shade_offset: float
    """Grey level of a surface at height 0 before the clamp to [TERRAIN_LOW, TERRAIN_HIGH]."""


def build_camera_model(model: Model) -> CameraModel:
    """The camera's constants for ``model``; the pixel step is computed in float32 as the
    heightmap's lattice is."""
    camera_model = CameraModel()
    half, sides = np.float32(model.half_platform), np.float32(model.camera_resolution - 1)
    camera_model.step = float(np.float32(2.0) * half / sides)
    camera_model.to_step = 1.0 / camera_model.step
    camera_model.step_in_cells = camera_model.step / model.cell_size
    camera_model.to_dome = 1.0 / model.column_half_width**2
    lowest = model.column_rest_top - model.max_column_height
    gain = (TERRAIN_HIGH - TERRAIN_LOW) / (2.0 * model.max_column_height)
    camera_model.shade_gain = gain
    camera_model.shade_offset = TERRAIN_LOW - gain * lowest
    return camera_model


@wp.func
def pixel_coordinate(model: Model, camera_model: CameraModel, i: int) -> float:
    """Coordinate [m] of pixel row (or column) ``i``'s centre along y (or x)."""
    return -model.half_platform + float(i) * camera_model.step


@wp.func
def pixel_cell(model: Model, camera_model: CameraModel, i: int) -> int:
    """Column index (along the same axis) under pixel row (or column) ``i``."""
    return wp.min(int(float(i) * camera_model.step_in_cells), model.grid_size - 1)


@wp.func
def pixels_within(model: Model, camera_model: CameraModel, centre: float, reach: float) -> wp.vec2i:
    """First and last pixel rows (or columns) within ``reach`` [m] of ``centre`` [m], widened
    to whole pixels and clamped to the image."""
    lo = int(wp.floor((centre - reach + model.half_platform) * camera_model.to_step))
    hi = int(wp.ceil((centre + reach + model.half_platform) * camera_model.to_step))
    return wp.vec2i(wp.max(lo, 0), wp.min(hi, model.camera_resolution - 1))


@wp.func
def chord_rows(
    model: Model, camera_model: CameraModel, x: float, centre: wp.vec2, reach: float
) -> wp.vec2i:
    """First and last pixel rows where the pixel column at ``x`` [m] may fall within
    ``reach`` [m] of ``centre`` [m]; none (first > last) where the disc does not reach x."""
    chord2 = reach * reach - (x - centre[0]) * (x - centre[0])
    rows = wp.vec2i(model.camera_resolution, -1)
    if chord2 >= 0.0:
        rows = pixels_within(model, camera_model, centre[1], wp.sqrt(chord2))
    return rows


@wp.func
def overlap(a: wp.vec2i, b: wp.vec2i) -> bool:
    """Whether the row ranges ``a`` and ``b`` (first, last) share a row."""
    return a[0] <= b[1] and b[0] <= a[1]


@wp.func
def column_surface(
    model: Model,
    camera_model: CameraModel,
    height: wp.array3d(dtype=float),
    e: int,
    top: float,
    dx: float,
    dy: float,
    x: float,
    y: float,
) -> float:
    """Height [m] of the columns' surface at (x, y) [m] (``surface_height``'s surface), MISS
    on the platform: ``top`` [m] is the top of the column under (x, y) and (dx, dy) [m] the
    offset from that column's centre."""
    z = float(MISS)
    if model.column_shape == SHAPE_BOX:
        z = top
    elif model.column_shape == SHAPE_ELLIPSOID:
        rho2 = (dx * dx + dy * dy) * camera_model.to_dome
        if rho2 <= 1.0 + 1.0e-5:  # as surface_height: the platform edge grazes the domes
            z = top - model.column_half_height * (1.0 - wp.sqrt(wp.max(1.0 - rho2, 0.0)))
    else:
        z = smooth_surface(model, height, height, e, x, y, 1.0)[0]
    return z


@wp.func
def pixel_surface(
    model: Model,
    camera_model: CameraModel,
    height: wp.array3d(dtype=float),
    e: int,
    cx: int,
    cy: int,
) -> float:
    """Height [m] of the columns' surface at pixel (cx, cy) as ``draw_terrain`` shades it,
    MISS on the platform."""
    ix = pixel_cell(model, camera_model, cx)
    iy = pixel_cell(model, camera_model, cy)
    x = pixel_coordinate(model, camera_model, cx)
    y = pixel_coordinate(model, camera_model, cy)
    top = column_top(model, height, height, e, iy, ix, 1.0)
    dx = x - column_center(model, ix)
    dy = y - column_center(model, iy)
    return column_surface(model, camera_model, height, e, top, dx, dy, x, y)


@wp.func
def terrain_level(camera_model: CameraModel, z: float) -> float:
    """Grey level of the columns' surface at height z [m]; the platform (MISS) is 0."""
    level = float(0.0)
    if z != MISS:
        level = camera_model.shade_gain * z + camera_model.shade_offset
        level = wp.clamp(level, TERRAIN_LOW, TERRAIN_HIGH)
    return level


@wp.func
def goal_centre(model: Model, cell: wp.vec2i) -> wp.vec2:
    """Horizontal position [m] of the centre of goal column ``cell``."""
    return wp.vec2(column_center(model, cell[0]), column_center(model, cell[1]))


@wp.func
def goal_distance2(model: Model, cell: wp.vec2i, x: float, y: float) -> float:
    """Squared horizontal distance [m^2] from (x, y) to the centre of goal column ``cell``."""
    centre = goal_centre(model, cell)
    dx = x - centre[0]
    dy = y - centre[1]
    return dx * dx + dy * dy


@wp.func
def nearest_goal(
    model: Model, goal_cell: wp.array2d(dtype=wp.vec2i), e: int, x: float, y: float
) -> int:
    """The goal whose column's centre is nearest (x, y) and closer than ``goal_radius``, the
    lower index on a tie; -1 if none."""
    nearest = int(-1)
    nearest_d2 = model.goal_radius * model.goal_radius
    for c in range(model.num_goals):
        d2 = goal_distance2(model, goal_cell[e, c], x, y)
        if d2 < nearest_d2:
            nearest = c
            nearest_d2 = d2
    return nearest


@wp.func
def sphere_top(model: Model, p: wp.vec3, x: float, y: float) -> float:
    """Height [m] of the top of the sphere centred at ``p`` over (x, y); MISS where it does
    not reach over (x, y)."""
    r2 = model.sphere_radius * model.sphere_radius
    d2 = (p[0] - x) * (p[0] - x) + (p[1] - y) * (p[1] - y)
    top = float(MISS)
    if d2 <= r2:
        top = p[2] + wp.sqrt(r2 - d2)
    return top


@wp.func
def front_sphere(
    model: Model,
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    e: int,
    x: float,
    y: float,
    surface: float,
) -> int:
    """The active sphere a vertical ray at (x, y) meets first, above the columns' surface at
    height ``surface`` [m] there, the lower index on a tie; -1 if none."""
    top = surface
    front = int(-1)
    for j in range(model.num_objects):
        if active[e, j] != 0:
            z = sphere_top(model, position[e, j], x, y)
            if z > top:
                top = z
                front = j
    return front


@wp.kernel
def draw_terrain(
    model: Model,
    camera_model: CameraModel,
    height: wp.array3d(dtype=float),
    camera: wp.array4d(dtype=float),
):
    """Shades every pixel by the columns' surface under it or the platform, two lattice
    columns of pixels per thread, one in the left half and one in the right: what depends on
    y alone is computed once for both, what depends on x once per thread, and a column's top
    is read once for all its pixels.

    Launch dim: [num_envs, ceil(C / 2)] as (env, column = x in the left half).
    """
    e, cx = wp.tid()
    c = model.camera_resolution
    cx_right = cx + (c + 1) / 2
    x = pixel_coordinate(model, camera_model, cx)
    x_right = pixel_coordinate(model, camera_model, cx_right)
    ix = pixel_cell(model, camera_model, cx)
    ix_right = pixel_cell(model, camera_model, cx_right)
    dx = x - column_center(model, ix)
    dx_right = x_right - column_center(model, ix_right)
    iy_read = int(-1)
    top = float(0.0)
    top_right = float(0.0)
    yc = float(0.0)
    for cy in range(c):
        y = pixel_coordinate(model, camera_model, cy)
        iy = pixel_cell(model, camera_model, cy)
        if iy != iy_read:  # the columns under these pixels and their centres' y
            iy_read = iy
            top = column_top(model, height, height, e, iy, ix, 1.0)
            top_right = column_top(model, height, height, e, iy, ix_right, 1.0)
            yc = column_center(model, iy)
        z = column_surface(model, camera_model, height, e, top, dx, y - yc, x, y)
        camera[e, 0, cy, cx] = terrain_level(camera_model, z)
        if cx_right < c:
            z = column_surface(
                model, camera_model, height, e, top_right, dx_right, y - yc, x_right, y
            )
            camera[e, 0, cy, cx_right] = terrain_level(camera_model, z)


@wp.kernel
def draw_goals(
    model: Model,
    camera_model: CameraModel,
    goal_cell: wp.array2d(dtype=wp.vec2i),
    camera: wp.array4d(dtype=float),
):
    """Paints each goal's region over the terrain where that goal is the nearest, a column of
    the pixels around one goal per thread; the goals are compared only where another goal's
    region may reach the same pixels of the column. The box's threads walk all its rows in
    step, each writing only those within its column's chord.

    Launch dim: [num_envs, G, box] as (env, goal, column of the goal's box of pixels); ``box``
    is at least the number of pixel columns within ``goal_radius`` of a point.
    """
    e, c, k = wp.tid()
    cell = goal_cell[e, c]
    centre = goal_centre(model, cell)
    reach = model.goal_radius
    cx = pixels_within(model, camera_model, centre[0], reach)[0] + k
    x = pixel_coordinate(model, camera_model, cx)
    rows = chord_rows(model, camera_model, x, centre, reach)
    if cx >= model.camera_resolution or rows[0] > rows[1]:
        return
    shared = bool(False)
    for other in range(model.num_goals):
        other_centre = goal_centre(model, goal_cell[e, other])
        if other != c and overlap(rows, chord_rows(model, camera_model, x, other_centre, reach)):
            shared = True
    level = marker_level(model.num_goals, c, 0)
    box = pixels_within(model, camera_model, centre[1], reach)
    for cy in range(box[0], box[1] + 1):  # the box's rows, the same in each of its threads
        if cy >= rows[0] and cy <= rows[1]:
            y = pixel_coordinate(model, camera_model, cy)
            nearest = bool(False)
            if shared:
                nearest = nearest_goal(model, goal_cell, e, x, y) == c
            else:
                nearest = goal_distance2(model, cell, x, y) < reach * reach
            if nearest:
                camera[e, 0, cy, cx] = level


@wp.kernel
def draw_spheres(
    model: Model,
    camera_model: CameraModel,
    height: wp.array3d(dtype=float),
    active: wp.array2d(dtype=wp.int32),
    position: wp.array2d(dtype=wp.vec3),
    camera: wp.array4d(dtype=float),
):
    """Draws each active sphere where it is the first thing a ray from above meets, a column
    of the pixels around one sphere per thread; the spheres are compared only where another
    sphere may reach the same pixels of the column. The box's threads walk all its rows in
    step, each writing only those within its column's chord.

    Launch dim: [num_envs, M, box] as (env, sphere, column of the sphere's box of pixels);
    ``box`` is at least the number of pixel columns within ``sphere_radius`` of a point.
    """
    e, j, k = wp.tid()
    if active[e, j] == 0:
        return
    p = position[e, j]
    reach = model.sphere_radius
    cx = pixels_within(model, camera_model, p[0], reach)[0] + k
    x = pixel_coordinate(model, camera_model, cx)
    rows = chord_rows(model, camera_model, x, wp.vec2(p[0], p[1]), reach)
    if cx >= model.camera_resolution or rows[0] > rows[1]:
        return
    shared = bool(False)
    for other in range(model.num_objects):
        q = position[e, other]
        reaches = overlap(rows, chord_rows(model, camera_model, x, wp.vec2(q[0], q[1]), reach))
        if other != j and active[e, other] != 0 and reaches:
            shared = True
    level = marker_level(model.num_goals, j % model.num_goals, 1)
    box = pixels_within(model, camera_model, p[1], reach)
    for cy in range(box[0], box[1] + 1):  # the box's rows, the same in each of its threads
        if cy >= rows[0] and cy <= rows[1]:
            y = pixel_coordinate(model, camera_model, cy)
            surface = pixel_surface(model, camera_model, height, e, cx, cy)
            front = bool(False)
            if shared:
                front = front_sphere(model, active, position, e, x, y, surface) == j
            else:
                front = sphere_top(model, p, x, y) > surface
            if front:
                camera[e, 0, cy, cx] = level


KERNELS = (draw_terrain, draw_goals, draw_spheres)
"""The camera's launches, in order: a profile's camera lines."""


def box_size(config: TerraShiftConfig, reach: float) -> int:
    """Pixel columns a launch gives to the box around a disc of radius ``reach`` [m]: every
    column within ``reach`` of its centre, whatever the float rounding."""
    step = config.platform_size / (config.camera_resolution - 1)
    return min(config.camera_resolution, math.ceil(2.0 * reach / step) + 3)


def render(model: Model, data: Data, config: TerraShiftConfig, num_envs: int) -> None:
    """Launches the camera's stages: the terrain, then the goal regions painted on it, then the
    spheres over both (the module docstring's rules)."""
    camera_model = build_camera_model(model)
    wp.launch(
        draw_terrain,
        dim=(num_envs, (config.camera_resolution + 1) // 2),
        inputs=[model, camera_model, data.column_height, data.camera],
    )
    wp.launch(
        draw_goals,
        dim=(num_envs, config.num_goals, box_size(config, config.goal_radius)),
        inputs=[model, camera_model, data.goal_cell, data.camera],
    )
    wp.launch(
        draw_spheres,
        dim=(num_envs, config.num_objects, box_size(config, config.sphere_radius)),
        inputs=[
            model,
            camera_model,
            data.column_height,
            data.sphere_active,
            data.sphere_position,
            data.camera,
        ],
    )
