"""Physics stage: sphere contacts with the columns and with each other, and integration.

Contact model (docs/physics.md has the derivation and the stable ranges):

* Normal: a penalty spring-dashpot, ``f_n = max(0, k * overlap - c * v_n)``, with ``c`` chosen
  so a collision ends with the configured restitution. Columns are kinematic: their vertical
  velocity enters ``v_n``, so a rising column lifts or throws a sphere.
* Tangential: Coulomb friction as a velocity-level impulse at the contact point. It removes the
  slip of the contact point up to ``mu * f_n * dt``, acting on both linear and angular velocity,
  so a sphere that does not slip *rolls* (5/7 g sin(theta) down a slope).
* Sphere pairs use the state at the start of the substep, so both partners compute the same
  impulse with opposite signs and momentum is conserved exactly. Column contacts of one sphere
  are then resolved one after another (Gauss-Seidel), which keeps stacked contacts stable.
* Semi-implicit Euler: velocities first, then positions with the new velocities.
"""

from __future__ import annotations

import warp as wp

from terrashift_rl.sim.types import SHAPE_BOX, SHAPE_ELLIPSOID, Model


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
    """Horizontal coordinate of column index ``i``'s centre [m]."""
    return (float(i) + 0.5) * model.cell_size - model.half_platform


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

    Between the outermost column centres and the platform edge the surface is flat.
    """
    gmax = float(model.grid_size - 1)
    u = (x + model.half_platform) / model.cell_size - 0.5
    v = (y + model.half_platform) / model.cell_size - 0.5
    uc = wp.clamp(u, 0.0, gmax)
    vc = wp.clamp(v, 0.0, gmax)
    i0 = wp.min(int(wp.floor(uc)), model.grid_size - 2)
    j0 = wp.min(int(wp.floor(vc)), model.grid_size - 2)
    tu = uc - float(i0)
    tv = vc - float(j0)
    z00 = column_top(model, height_prev, height, e, j0, i0, frac)
    z10 = column_top(model, height_prev, height, e, j0, i0 + 1, frac)
    z01 = column_top(model, height_prev, height, e, j0 + 1, i0, frac)
    z11 = column_top(model, height_prev, height, e, j0 + 1, i0 + 1, frac)
    s00 = column_speed(model, height_prev, height, e, j0, i0)
    s10 = column_speed(model, height_prev, height, e, j0, i0 + 1)
    s01 = column_speed(model, height_prev, height, e, j0 + 1, i0)
    s11 = column_speed(model, height_prev, height, e, j0 + 1, i0 + 1)
    z = (1.0 - tv) * ((1.0 - tu) * z00 + tu * z10) + tv * ((1.0 - tu) * z01 + tu * z11)
    speed = (1.0 - tv) * ((1.0 - tu) * s00 + tu * s10) + tv * ((1.0 - tu) * s01 + tu * s11)
    dzdx = float(0.0)
    dzdy = float(0.0)
    if u > 0.0 and u < gmax:
        dzdx = ((1.0 - tv) * (z10 - z00) + tv * (z11 - z01)) / model.cell_size
    if v > 0.0 and v < gmax:
        dzdy = ((1.0 - tu) * (z01 - z00) + tu * (z11 - z10)) / model.cell_size
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


@wp.func
def friction_impulse(
    model: Model, slip: wp.vec3, inverse_mass: float, normal_impulse: float
) -> wp.vec3:
    """Impulse that stops ``slip`` (tangential contact-point velocity), capped by Coulomb's
    law. ``inverse_mass`` is the contact point's tangential inverse effective mass."""
    speed = wp.length(slip)
    if speed < 1.0e-9:
        return wp.vec3(0.0)
    magnitude = wp.min(speed / inverse_mass, model.friction * normal_impulse)
    return -magnitude / speed * slip


@wp.func
def column_contact_impulse(
    model: Model, v: wp.vec3, w: wp.vec3, n: wp.vec3, overlap: float, surface_velocity: wp.vec3
) -> wp.spatial_vector:
    """Velocity changes (linear xyz, angular xyz) from one sphere-column contact."""
    r = model.sphere_radius
    dt = model.substep_dt
    arm = -r * n
    rel = v + wp.cross(w, arm) - surface_velocity
    force = model.contact_stiffness * overlap - model.column_contact_damping * wp.dot(rel, n)
    if force <= 0.0:
        return wp.spatial_vector()
    jn = force * dt
    dv = n * (jn / model.sphere_mass)
    slip = rel - wp.dot(rel, n) * n
    inv = 1.0 / model.sphere_mass + r * r / model.sphere_inertia
    jt = friction_impulse(model, slip, inv, jn)
    dv = dv + jt / model.sphere_mass
    dw = wp.cross(arm, jt) / model.sphere_inertia
    return wp.spatial_vector(dv[0], dv[1], dv[2], dw[0], dw[1], dw[2])


@wp.func
def apply_impulse(v: wp.vec3, dvw: wp.spatial_vector) -> wp.vec3:
    return v + wp.vec3(dvw[0], dvw[1], dvw[2])


@wp.func
def apply_angular(w: wp.vec3, dvw: wp.spatial_vector) -> wp.vec3:
    return w + wp.vec3(dvw[3], dvw[4], dvw[5])


@wp.kernel
def substep(
    model: Model,
    frac: float,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    active: wp.array2d(dtype=wp.int32),
    position_in: wp.array2d(dtype=wp.vec3),
    velocity_in: wp.array2d(dtype=wp.vec3),
    angular_velocity_in: wp.array2d(dtype=wp.vec3),
    position_out: wp.array2d(dtype=wp.vec3),
    velocity_out: wp.array2d(dtype=wp.vec3),
    angular_velocity_out: wp.array2d(dtype=wp.vec3),
):
    """Advances every sphere by one substep. Launch dim: [num_envs, M].

    ``frac`` is the fraction of the tick reached at the end of this substep; column tops are
    interpolated to it.
    """
    e, j = wp.tid()
    p = position_in[e, j]
    v = velocity_in[e, j]
    w = angular_velocity_in[e, j]
    if active[e, j] == 0:
        position_out[e, j] = p
        velocity_out[e, j] = v
        angular_velocity_out[e, j] = w
        return
    dt = model.substep_dt
    r = model.sphere_radius
    m = model.sphere_mass
    inertia = model.sphere_inertia

    # sphere pairs, from the start-of-substep state of both partners
    v_start = v
    w_start = w
    for o in range(model.num_objects):
        if o == j or active[e, o] == 0:
            continue
        d = p - position_in[e, o]
        dist = wp.length(d)
        overlap = 2.0 * r - dist
        if overlap <= 0.0 or dist < 1.0e-9:
            continue
        n = d / dist
        rel = (v_start + wp.cross(w_start, -r * n)) - (
            velocity_in[e, o] + wp.cross(angular_velocity_in[e, o], r * n)
        )
        force = model.contact_stiffness * overlap - model.sphere_contact_damping * wp.dot(rel, n)
        if force <= 0.0:
            continue
        jn = force * dt
        slip = rel - wp.dot(rel, n) * n
        inv = 2.0 * (1.0 / m + r * r / inertia)
        impulse = n * jn + friction_impulse(model, slip, inv, jn)
        v = v + impulse / m
        w = w + wp.cross(-r * n, impulse) / inertia

    v = v + wp.vec3(0.0, 0.0, -model.gravity * dt)

    half = model.half_platform
    if model.column_shape == SHAPE_BOX or model.column_shape == SHAPE_ELLIPSOID:
        g = model.grid_size
        i0 = int(wp.floor((p[0] - r + half) / model.cell_size))
        i1 = int(wp.floor((p[0] + r + half) / model.cell_size))
        k0 = int(wp.floor((p[1] - r + half) / model.cell_size))
        k1 = int(wp.floor((p[1] + r + half) / model.cell_size))
        if i1 >= 0 and i0 < g and k1 >= 0 and k0 < g:
            for iy in range(wp.max(k0, 0), wp.min(k1, g - 1) + 1):
                for ix in range(wp.max(i0, 0), wp.min(i1, g - 1) + 1):
                    top = column_top(model, height_prev, height, e, iy, ix, frac)
                    cx = column_center(model, ix)
                    cy = column_center(model, iy)
                    # cheap rejection: the column lies inside the prism over its cell, and the
                    # sphere's underside above the cell is no lower than at the cell's nearest
                    # point to the centre
                    a = model.column_half_width
                    gx = wp.max(wp.abs(p[0] - cx) - a, 0.0)
                    gy = wp.max(wp.abs(p[1] - cy) - a, 0.0)
                    reach = r * r - gx * gx - gy * gy
                    if reach <= 0.0 or top < p[2] - wp.sqrt(reach):
                        continue
                    nd = wp.vec4()
                    if model.column_shape == SHAPE_BOX:
                        nd = box_contact(model, p, cx, cy, top)
                    else:
                        nd = ellipsoid_contact(model, p, cx, cy, top)
                    overlap = r - nd[3]
                    if overlap > 0.0:
                        surface_velocity = wp.vec3(
                            0.0, 0.0, column_speed(model, height_prev, height, e, iy, ix)
                        )
                        dvw = column_contact_impulse(
                            model, v, w, wp.vec3(nd[0], nd[1], nd[2]), overlap, surface_velocity
                        )
                        v = apply_impulse(v, dvw)
                        w = apply_angular(w, dvw)
    elif wp.abs(p[0]) < half + r and wp.abs(p[1]) < half + r:
        sc = smooth_contact(model, height_prev, height, e, p, frac)
        overlap = r - sc[3]
        if overlap > 0.0:
            dvw = column_contact_impulse(
                model, v, w, wp.vec3(sc[0], sc[1], sc[2]), overlap, wp.vec3(0.0, 0.0, sc[4])
            )
            v = apply_impulse(v, dvw)
            w = apply_angular(w, dvw)

    v = v / (1.0 + model.linear_damping * dt)
    w = w / (1.0 + model.angular_damping * dt)
    position_out[e, j] = p + v * dt
    velocity_out[e, j] = v
    angular_velocity_out[e, j] = w
