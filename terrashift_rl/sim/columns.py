"""Column geometry: where each column's top is and how fast it moves, the smooth surface
between column centres, and the closest point of a sphere's centre on an ellipsoid, a box or
the smooth surface (the contacts' geometry, which :mod:`terrashift_rl.sim.physics` turns into
impulses, and the heightmap and camera sample)."""

from __future__ import annotations

import warp as wp

from terrashift_rl.sim.types import Model

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.func
def column_top(
    model: Model,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    e: int,
    iy: int,
    ix: int,
    frac: float,
) -> float:
    """Height of a column's top [m] at fraction ``frac`` of the current tick."""
    hp = height_prev[e, iy, ix]
    return model.column_rest_top + hp + frac * (height[e, iy, ix] - hp)


@wp.func
def column_speed(
    model: Model,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    e: int,
    iy: int,
    ix: int,
) -> float:
    """Vertical velocity of a column over the current tick [m/s]."""
    return (height[e, iy, ix] - height_prev[e, iy, ix]) / model.tick_dt


@wp.func
def column_center(model: Model, i: int) -> float:
    """Horizontal coordinate of column index ``i``'s centre [m].

    Measured from the middle of the grid, so mirrored columns lie at exactly opposite
    coordinates and a mirrored scene is simulated as the exact mirror image."""
    return (float(i) - 0.5 * float(model.grid_size - 1)) * model.cell_size


@wp.func
def grid_bracket(model: Model, coordinate: float) -> wp.vec4:
    """The two column centres around ``coordinate`` [m] along one axis, clamped to the
    outermost ones: (index a, index b - index a = +-1, weight of a, weight of b).

    Computed on the positive side from ``|coordinate|`` and mirrored back, so a mirrored
    coordinate gives exactly the mirrored columns and the same weights.
    """
    last = float(model.grid_size - 1)
    u = wp.min(wp.abs(coordinate) / model.cell_size + 0.5 * last, last)  # in column indices
    lower = wp.min(wp.floor(u), last - 1.0)
    weight_b = u - lower
    index_a = lower
    direction = float(1.0)
    if coordinate < 0.0:
        index_a = last - lower
        direction = -1.0
    return wp.vec4(index_a, direction, 1.0 - weight_b, weight_b)


@wp.func
def smooth_surface(
    model: Model,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    e: int,
    x: float,
    y: float,
    frac: float,
) -> wp.vec4:
    """Bilinear surface through the column tops: (z, dz/dx, dz/dy, dz/dt) at (x, y).

    Between the outermost column centres and the platform edge the surface is flat. The four
    corners are summed in an order that a mirror image or the transpose only permutes within
    its pairs, so mirrored scenes see exactly mirrored surfaces.
    """
    bx = grid_bracket(model, x)
    by = grid_bracket(model, y)
    ia = int(bx[0])
    ib = int(bx[0] + bx[1])
    ja = int(by[0])
    jb = int(by[0] + by[1])
    zaa = column_top(model, height_prev, height, e, ja, ia, frac)
    zba = column_top(model, height_prev, height, e, ja, ib, frac)
    zab = column_top(model, height_prev, height, e, jb, ia, frac)
    zbb = column_top(model, height_prev, height, e, jb, ib, frac)
    saa = column_speed(model, height_prev, height, e, ja, ia)
    sba = column_speed(model, height_prev, height, e, ja, ib)
    sab = column_speed(model, height_prev, height, e, jb, ia)
    sbb = column_speed(model, height_prev, height, e, jb, ib)
    waa = bx[2] * by[2]
    wba = bx[3] * by[2]
    wab = bx[2] * by[3]
    wbb = bx[3] * by[3]
    z = (waa * zaa + wbb * zbb) + (wba * zba + wab * zab)
    speed = (waa * saa + wbb * sbb) + (wba * sba + wab * sab)
    # the surface is flat beyond the outermost centres
    half_span = 0.5 * float(model.grid_size - 1) * model.cell_size
    dzdx = float(0.0)
    dzdy = float(0.0)
    if wp.abs(x) < half_span:
        dzdx = bx[1] * (by[2] * (zba - zaa) + by[3] * (zbb - zab)) / model.cell_size
    if wp.abs(y) < half_span:
        dzdy = by[1] * (bx[2] * (zab - zaa) + bx[3] * (zbb - zba)) / model.cell_size
    return wp.vec4(z, dzdx, dzdy, speed)


@wp.func
def ellipse_closest(a: float, b: float, px: float, py: float) -> wp.vec2:
    """Closest point to (px, py) on the ellipse x^2/a^2 + y^2/b^2 = 1 (fixed-point iteration
    on the ellipse's evolute; accurate to float precision after four iterations)."""
    ax = wp.abs(px)
    ay = wp.abs(py)
    tx = float(0.70710678)
    ty = float(0.70710678)
    for _ in range(4):
        x = a * tx
        y = b * ty
        ex = (a * a - b * b) * tx * tx * tx / a
        ey = (b * b - a * a) * ty * ty * ty / b
        rx = x - ex
        ry = y - ey
        qx = ax - ex
        qy = ay - ey
        rr = wp.sqrt(rx * rx + ry * ry)
        qq = wp.max(wp.sqrt(qx * qx + qy * qy), 1.0e-12)
        tx = wp.clamp((qx * rr / qq + ex) / a, 0.0, 1.0)
        ty = wp.clamp((qy * rr / qq + ey) / b, 0.0, 1.0)
        t = wp.max(wp.sqrt(tx * tx + ty * ty), 1.0e-12)
        tx = tx / t
        ty = ty / t
    return wp.vec2(wp.sign(px) * a * tx, wp.sign(py) * b * ty)


@wp.func
def ellipsoid_contact(model: Model, p: wp.vec3, cx: float, cy: float, top: float) -> wp.vec4:
    """Outward normal (xyz) and signed distance (w) from a spheroid column to point ``p``."""
    a = model.column_half_width
    c = model.column_half_height
    d = p - wp.vec3(cx, cy, top - c)
    rho = wp.sqrt(d[0] * d[0] + d[1] * d[1])
    q = ellipse_closest(a, c, rho, d[2])
    nr = q[0] / (a * a)
    nz = q[1] / (c * c)
    nl = wp.max(wp.sqrt(nr * nr + nz * nz), 1.0e-12)
    nr = nr / nl
    nz = nz / nl
    dist = wp.sqrt((rho - q[0]) * (rho - q[0]) + (d[2] - q[1]) * (d[2] - q[1]))
    if (rho * rho) / (a * a) + (d[2] * d[2]) / (c * c) < 1.0:
        dist = -dist
    n = wp.vec3(0.0, 0.0, nz)
    if rho > 1.0e-9:
        n = wp.vec3(nr * d[0] / rho, nr * d[1] / rho, nz)
    return wp.vec4(n[0], n[1], n[2], dist)


@wp.func
def box_contact(model: Model, p: wp.vec3, cx: float, cy: float, top: float) -> wp.vec4:
    """Outward normal (xyz) and signed distance (w) from a box column to point ``p``.

    A box spans one cell horizontally and reaches down to the platform.
    """
    a = model.column_half_width
    lo = wp.vec3(cx - a, cy - a, 0.0)
    hi = wp.vec3(cx + a, cy + a, top)
    q = wp.vec3(
        wp.clamp(p[0], lo[0], hi[0]), wp.clamp(p[1], lo[1], hi[1]), wp.clamp(p[2], lo[2], hi[2])
    )
    diff = p - q
    dist = wp.length(diff)
    if dist > 1.0e-9:
        n = diff / dist
        return wp.vec4(n[0], n[1], n[2], dist)
    # centre inside the box: leave through the nearest of the top and side faces
    depth = hi[2] - p[2]
    n = wp.vec3(0.0, 0.0, 1.0)
    if p[0] - lo[0] < depth:
        depth = p[0] - lo[0]
        n = wp.vec3(-1.0, 0.0, 0.0)
    if hi[0] - p[0] < depth:
        depth = hi[0] - p[0]
        n = wp.vec3(1.0, 0.0, 0.0)
    if p[1] - lo[1] < depth:
        depth = p[1] - lo[1]
        n = wp.vec3(0.0, -1.0, 0.0)
    if hi[1] - p[1] < depth:
        depth = hi[1] - p[1]
        n = wp.vec3(0.0, 1.0, 0.0)
    return wp.vec4(n[0], n[1], n[2], -depth)


@wp.func
def surface_distance_squared(
    model: Model,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    e: int,
    p: wp.vec3,
    u: float,
    v: float,
    frac: float,
) -> float:
    d = p - wp.vec3(u, v, smooth_surface(model, height_prev, height, e, u, v, frac)[0])
    return wp.dot(d, d)


@wp.func
def smooth_contact(
    model: Model,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    e: int,
    p: wp.vec3,
    frac: float,
) -> wp.spatial_vector:
    """Closest point of the smooth surface to ``p``. Returns (normal xyz, signed distance,
    surface vertical speed, unused).

    The penalty force is conservative only if the distance is the true (global) distance, which
    is continuous even where the closest point jumps across a valley. A 5 x 5 sample of the
    sphere's footprint picks the basin; projections onto the tangent plane, with backtracking,
    refine it. The normal points from the closest point to the centre.
    """
    half = model.half_platform
    r = model.sphere_radius
    u = wp.clamp(p[0], -half, half)
    v = wp.clamp(p[1], -half, half)
    best = surface_distance_squared(model, height_prev, height, e, p, u, v, frac)
    for a in range(-2, 3):
        for b in range(-2, 3):
            cu = wp.clamp(p[0] + 0.5 * r * float(a), -half, half)
            cv = wp.clamp(p[1] + 0.5 * r * float(b), -half, half)
            d2 = surface_distance_squared(model, height_prev, height, e, p, cu, cv, frac)
            if d2 < best:
                best = d2
                u = cu
                v = cv
    for _ in range(6):
        s = smooth_surface(model, height_prev, height, e, u, v, frac)
        n = wp.normalize(wp.vec3(-s[1], -s[2], 1.0))
        proj = p - wp.dot(p - wp.vec3(u, v, s[0]), n) * n
        du = wp.clamp(proj[0], -half, half) - u
        dv = wp.clamp(proj[1], -half, half) - v
        step = float(1.0)
        for _ in range(4):
            d2 = surface_distance_squared(
                model, height_prev, height, e, p, u + step * du, v + step * dv, frac
            )
            if d2 < best:
                best = d2
                u = u + step * du
                v = v + step * dv
                break
            step = 0.5 * step
    s = smooth_surface(model, height_prev, height, e, u, v, frac)
    diff = p - wp.vec3(u, v, s[0])
    dist = wp.sqrt(best)
    n = diff / wp.max(dist, 1.0e-12)
    below = smooth_surface(model, height_prev, height, e, u, v, frac)[0]
    if wp.abs(p[0]) <= half and wp.abs(p[1]) <= half:
        below = smooth_surface(model, height_prev, height, e, p[0], p[1], frac)[0]
    if p[2] < below:  # centre under the surface: push it back out
        dist = -dist
        n = -n
    return wp.spatial_vector(n[0], n[1], n[2], dist, s[3], 0.0)
