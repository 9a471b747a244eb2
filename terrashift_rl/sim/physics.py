"""Physics stage: sphere contacts with the columns and with each other, and integration.

Contact model (docs/physics.md has the derivation and the stable ranges):

* Normal: a penalty spring-dashpot, ``f_n = max(0, k * overlap - c * v_n)``, with ``c`` chosen
  so a collision ends with the configured restitution. Columns are kinematic: their vertical
  velocity enters ``v_n``, so a rising column lifts or throws a sphere. Where the actuator
  family slides the surface in plane, the sliding's part tangent to a contact enters its slip,
  and friction drags the sphere along (:func:`sphere_kernels`).
* Tangential: Coulomb friction as a velocity-level impulse at the contact point. It removes the
  slip of the contact point up to ``mu * f_n * dt``, acting on both linear and angular velocity,
  so a sphere that does not slip *rolls* (5/7 g sin(theta) down a slope).
* Sphere pairs use the state at the start of the substep, so both partners compute the same
  impulse with opposite signs and momentum is conserved exactly. The column contacts of one
  sphere are then all computed from the same velocities and combined (Jacobi iteration): no
  contact goes first, so the result does not depend on the order in which columns are visited
  and a mirrored scene gives the mirrored motion. Combining scales the velocity-level parts
  (dashpots and friction) so that together they neither overshoot nor fall short; see
  :func:`combined_velocity_change`.
* Semi-implicit Euler: velocities first, then positions with the new velocities.
"""

from __future__ import annotations

import functools

import warp as wp

from terrashift_rl.sim.columns import (
    box_contact,
    column_center,
    column_speed,
    column_top,
    ellipsoid_contact,
    grid_bracket,
    smooth_contact,
)
from terrashift_rl.sim.types import SHAPE_BOX, SHAPE_ELLIPSOID, Model

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it


@wp.func
def tangential(velocity: wp.vec2, n: wp.vec3) -> wp.vec3:
    """The part of an in-plane surface velocity (x, y) [m/s] tangent to a contact of normal
    ``n``: a surface that slides along itself never pushes along its normal."""
    u = wp.vec3(velocity[0], velocity[1], 0.0)
    return u - wp.dot(u, n) * n


@wp.func
def smooth_flow(
    model: Model, flow: wp.array3d(dtype=wp.vec2), e: int, x: float, y: float
) -> wp.vec2:
    """Bilinear interpolation at (x, y) [m] of the columns' in-plane surface velocities,
    constant beyond the outermost column centres (as ``columns.smooth_surface``)."""
    bx = grid_bracket(model, x)
    by = grid_bracket(model, y)
    ia = int(bx[0])
    ib = int(bx[0] + bx[1])
    ja = int(by[0])
    jb = int(by[0] + by[1])
    return (bx[2] * by[2] * flow[e, ja, ia] + bx[3] * by[3] * flow[e, jb, ib]) + (
        bx[3] * by[2] * flow[e, ja, ib] + bx[2] * by[3] * flow[e, jb, ia]
    )


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


@wp.struct
class ColumnImpulses:
    """The column contacts of one sphere in one substep, each computed from the same velocities
    as if it were the sphere's only contact, summed; and what it takes to combine them."""

    normal: wp.vec3
    """Sum of the normal (spring and dashpot) impulses [N s]."""
    approach_damping: wp.vec3
    """Sum of the dashpot impulses of the approaching contacts [N s]."""
    damping_share: float
    """Sum over the approaching contacts of the fraction of their approach the dashpot stops."""
    friction: wp.vec3
    """Sum of the friction impulses [N s]."""
    friction_moment: wp.vec3
    """Sum of the friction impulses' moments about the sphere's centre [N m s]."""
    friction_work: float
    """Sum of friction impulse . slip [J]: the first-order change of kinetic energy (<= 0)."""
    friction_cone: float
    """Largest factor on every friction impulse that keeps each within mu * normal impulse."""
    contacts: float
    """Number of contacts with friction."""
    normals: wp.vec3
    """Sum of their normals."""
    normal_products: wp.mat33
    """Sum of the outer products of their normals with themselves."""
    slips: wp.vec3
    """Sum of their slip velocities [m/s]."""
    normal_cross_slips: wp.vec3
    """Sum of their normals crossed with their slip velocities [m/s]."""
    normal_power: float
    """Sum of the normal impulses dotted with their surfaces' velocities [J]."""
    approach_power: float
    """The same of the approaching contacts' dashpot impulses [J]."""
    friction_power: float
    """Sum of the friction impulses dotted with their surfaces' velocities [J]."""


@wp.func
def new_column_impulses() -> ColumnImpulses:
    impulses = ColumnImpulses()
    impulses.friction_cone = 1.0e30
    return impulses


@wp.func
def add_column_contact(
    model: Model,
    impulses: ColumnImpulses,
    v: wp.vec3,
    w: wp.vec3,
    n: wp.vec3,
    overlap: float,
    surface_velocity: wp.vec3,
) -> ColumnImpulses:
    """Adds one sphere-column contact's impulses, computed from the velocities ``v``, ``w``."""
    r = model.sphere_radius
    dt = model.substep_dt
    arm = -r * n
    rel = v + wp.cross(w, arm) - surface_velocity
    normal_speed = wp.dot(rel, n)
    damping = -model.column_contact_damping * normal_speed
    force = model.contact_stiffness * overlap + damping
    if force <= 0.0:
        return impulses
    jn = force * dt
    impulses.normal = impulses.normal + n * jn
    surface_normal_speed = wp.dot(surface_velocity, n)
    impulses.normal_power = impulses.normal_power + jn * surface_normal_speed
    # an approaching contact's force is never clipped, so its dashpot part can be scaled later
    if normal_speed < 0.0:
        impulses.approach_damping = impulses.approach_damping + n * (damping * dt)
        impulses.approach_power = impulses.approach_power + damping * dt * surface_normal_speed
        impulses.damping_share = (
            impulses.damping_share + model.column_contact_damping * dt / model.sphere_mass
        )
    slip = rel - normal_speed * n
    jt = friction_impulse(model, slip, 1.0 / model.sphere_mass + r * r / model.sphere_inertia, jn)
    impulses.friction = impulses.friction + jt
    impulses.friction_moment = impulses.friction_moment + wp.cross(arm, jt)
    impulses.friction_work = impulses.friction_work + wp.dot(jt, slip)
    impulses.friction_power = impulses.friction_power + wp.dot(jt, surface_velocity)
    magnitude = wp.length(jt)
    if magnitude > 0.0:
        impulses.friction_cone = wp.min(impulses.friction_cone, model.friction * jn / magnitude)
    impulses.contacts = impulses.contacts + 1.0
    impulses.normals = impulses.normals + n
    impulses.normal_products = impulses.normal_products + wp.outer(n, n)
    impulses.slips = impulses.slips + slip
    impulses.normal_cross_slips = impulses.normal_cross_slips + wp.cross(n, slip)
    return impulses


@wp.func
def combined_velocity_change(model: Model, impulses: ColumnImpulses) -> wp.spatial_vector:
    """Velocity changes (linear xyz, angular xyz) from a sphere's column contacts together.

    Springs add up as they are. The dashpots of several approaching contacts that would
    together stop more than the whole approach are scaled down to stop just it. The friction
    impulses, each the one that would stop its own contact's slip (capped by Coulomb), are
    summed and the sum is scaled by the factor that best stops all the slips at once: an exact
    line search along it (least squares over the contacts' slips), which neither undershoots
    where contacts share a direction of motion nor overshoots where they cross. The factor
    stays within every contact's friction cone and where kinetic energy cannot grow; for a
    single contact it is one, which is that contact's own friction.
    """
    m = model.sphere_mass
    inertia = model.sphere_inertia
    r = model.sphere_radius
    damping_scale = 1.0 / wp.max(impulses.damping_share, 1.0)
    normal_dv = (impulses.normal - (1.0 - damping_scale) * impulses.approach_damping) / m
    dv = impulses.friction / m
    dw = impulses.friction_moment / inertia
    # The factor minimises the sum over the contacts of |s_i + f c_i|^2: s_i the slip left
    # after the normal impulses (which already stop much of it where normals are tilted
    # against each other), c_i = dv - r dw x n_i the contact point's velocity change per unit
    # factor. Its tangential part should cancel the slip; its normal part, which pushes the
    # sphere into or off its other contacts, is a cost. The sums of s_i . c_i and |c_i|^2
    # follow from the contacts' sums of n, n n^T, slip and n x slip.
    products = impulses.normal_products
    along = (
        wp.dot(impulses.slips, dv)
        - r * wp.dot(dw, impulses.normal_cross_slips)
        + impulses.contacts * wp.dot(normal_dv, dv)
        - r * wp.dot(normal_dv, wp.cross(dw, impulses.normals))
        - wp.dot(normal_dv, products * dv)
    )
    curvature = (
        impulses.contacts * (wp.dot(dv, dv) + r * r * wp.dot(dw, dw))
        - 2.0 * r * wp.dot(impulses.normals, wp.cross(dv, dw))
        - r * r * wp.dot(dw, products * dw)
    )
    scale = float(0.0)
    if curvature > 0.0:
        # kinetic energy changes by scale * work + scale^2 * energy / 2 after the normal impulses
        work = impulses.friction_work + wp.dot(impulses.friction, normal_dv)
        energy = m * wp.dot(dv, dv) + inertia * wp.dot(dw, dw)
        limit = wp.min(impulses.friction_cone, -2.0 * work / energy)
        scale = wp.clamp(-along / curvature, 0.0, wp.max(limit, 0.0))
    dv = normal_dv + scale * dv
    dw = scale * dw
    return wp.spatial_vector(dv[0], dv[1], dv[2], dw[0], dw[1], dw[2])


@wp.func
def column_work(
    model: Model, impulses: ColumnImpulses, velocity_change: wp.spatial_vector
) -> float:
    """Work [J] the columns' surfaces do on a sphere in one substep through the impulses that
    :func:`combined_velocity_change` made of ``impulses`` (its result ``velocity_change``):
    each contact's impulse dotted with its surface's velocity. The scale of the dashpots
    follows from the impulses; that of the friction from the velocity change it made."""
    m = model.sphere_mass
    inertia = model.sphere_inertia
    r = model.sphere_radius
    damping_scale = 1.0 / wp.max(impulses.damping_share, 1.0)
    normal = impulses.normal - (1.0 - damping_scale) * impulses.approach_damping
    friction_dv = wp.vec3(velocity_change[0], velocity_change[1], velocity_change[2]) * m - normal
    friction_dw = wp.vec3(velocity_change[3], velocity_change[4], velocity_change[5]) * inertia
    # the friction impulses applied are scale * their sum, and their moment scale * its sum
    along = wp.dot(friction_dv, impulses.friction) + wp.dot(
        friction_dw, impulses.friction_moment
    ) / (r * r)
    norm = wp.dot(impulses.friction, impulses.friction) + wp.dot(
        impulses.friction_moment, impulses.friction_moment
    ) / (r * r)
    scale = float(0.0)
    if norm > 0.0:
        scale = along / norm
    return (
        impulses.normal_power
        - (1.0 - damping_scale) * impulses.approach_power
        + scale * impulses.friction_power
    )


CONTACT_MAX_REGISTERS = 128
"""Registers a GPU thread of the sphere kernels may use. Unbounded they take 180-250, so that
a multiprocessor (64 K registers) holds 8 warps of them; at 128 it holds 16, twice the threads
to hide latency with, for a few spills to the L1 cache."""


@functools.cache
def sphere_kernels(surface_flow: bool, surface_work: bool) -> tuple[wp.Kernel, wp.Kernel]:
    """The sphere kernels, :func:`substep` and :func:`tick_substeps`, for a family that slides
    the surface in plane (``surface_flow``) or not, counting the surface's work on the spheres
    (``surface_work``) or not.

    With ``surface_flow`` every contact's surface velocity adds the part of the column's
    in-plane velocity (``flow``, the data's ``surface_velocity`` [m/s], [num_envs, G(y),
    G(x)], vec2) that is tangent to the contact, as a belt moves along its own surface; the
    smooth surface takes the bilinear interpolation of the columns' velocities under the
    sphere's centre. The choice
    is compiled in: without it the kernels never read ``flow`` (it may be empty).

    With ``surface_work`` each sphere's ``work`` [J], [num_envs, M], grows by the work its
    column contacts did on it in a substep, where that is positive (:func:`column_work`): the
    energy an actuator spends that cannot take energy back. Without it the kernels never read
    ``work``.
    """

    @wp.func
    def advance_sphere(
        model: Model,
        frac: float,
        height_prev: wp.array3d(dtype=float),
        height: wp.array3d(dtype=float),
        flow: wp.array3d(dtype=wp.vec2),
        work: wp.array2d(dtype=float),
        active: wp.array2d(dtype=wp.int32),
        position_in: wp.array2d(dtype=wp.vec3),
        velocity_in: wp.array2d(dtype=wp.vec3),
        angular_velocity_in: wp.array2d(dtype=wp.vec3),
        position_out: wp.array2d(dtype=wp.vec3),
        velocity_out: wp.array2d(dtype=wp.vec3),
        angular_velocity_out: wp.array2d(dtype=wp.vec3),
        e: int,
        j: int,
    ):
        """Advances sphere ``j`` of environment ``e`` by one substep, from the ``_in`` state of
        every sphere to its own ``_out`` state.

        ``frac`` is the fraction of the tick reached in the middle of this substep, (s + 1/2) /
        substeps; column tops are interpolated to it. A contact's impulse over the substep is
        then that of the columns' mean position over it, so a column that starts or stops with
        the tick is not felt a whole substep early or late.
        """
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
            force = model.contact_stiffness * overlap - model.sphere_contact_damping * wp.dot(
                rel, n
            )
            if force <= 0.0:
                continue
            jn = force * dt
            slip = rel - wp.dot(rel, n) * n
            inv = 2.0 * (1.0 / m + r * r / inertia)
            impulse = n * jn + friction_impulse(model, slip, inv, jn)
            v = v + impulse / m
            w = w + wp.cross(-r * n, impulse) / inertia

        v = v + wp.vec3(0.0, 0.0, -model.gravity * dt)

        # column contacts, all from the same velocities: the result does not depend on the order in
        # which they are visited
        impulses = new_column_impulses()
        half = model.half_platform
        if model.column_shape == SHAPE_BOX or model.column_shape == SHAPE_ELLIPSOID:
            g = model.grid_size
            i0 = int(wp.floor((p[0] - r + half) / model.cell_size))
            i1 = int(wp.floor((p[0] + r + half) / model.cell_size))
            k0 = int(wp.floor((p[1] - r + half) / model.cell_size))
            k1 = int(wp.floor((p[1] + r + half) / model.cell_size))
            if i1 >= 0 and i0 < g and k1 >= 0 and k0 < g:
                # The columns under the sphere are visited row by row, as nested loops would, but
                # the exact contact, the costly part, has a loop of its own whose every pass takes
                # the next column that the cheap test keeps: the threads of a GPU warp then share
                # as many passes as the most such columns any one of them has, not one at every
                # column where any of them needs it.
                i0 = wp.max(i0, 0)
                i1 = wp.min(i1, g - 1)
                k1 = wp.min(k1, g - 1)
                ix = i0
                iy = wp.max(k0, 0)
                while iy <= k1:
                    found = int(0)
                    column_x = int(0)
                    column_y = int(0)
                    top = float(0.0)
                    while found == 0 and iy <= k1:
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
                        if not (reach <= 0.0 or top < p[2] - wp.sqrt(reach)):
                            found = 1
                            column_x = ix
                            column_y = iy
                        ix += 1
                        if ix > i1:
                            ix = i0
                            iy += 1
                    if found == 0:
                        break
                    cx = column_center(model, column_x)
                    cy = column_center(model, column_y)
                    nd = wp.vec4()
                    if model.column_shape == SHAPE_BOX:
                        nd = box_contact(model, p, cx, cy, top)
                    else:
                        nd = ellipsoid_contact(model, p, cx, cy, top)
                    overlap = r - nd[3]
                    if overlap > 0.0:
                        n = wp.vec3(nd[0], nd[1], nd[2])
                        surface_velocity = wp.vec3(
                            0.0,
                            0.0,
                            column_speed(model, height_prev, height, e, column_y, column_x),
                        )
                        if wp.static(surface_flow):
                            surface_velocity = surface_velocity + tangential(
                                flow[e, column_y, column_x], n
                            )
                        impulses = add_column_contact(
                            model, impulses, v, w, n, overlap, surface_velocity
                        )
        elif wp.abs(p[0]) < half + r and wp.abs(p[1]) < half + r:
            sc = smooth_contact(model, height_prev, height, e, p, frac)
            overlap = r - sc[3]
            if overlap > 0.0:
                n = wp.vec3(sc[0], sc[1], sc[2])
                surface_velocity = wp.vec3(0.0, 0.0, sc[4])
                if wp.static(surface_flow):
                    surface_velocity = surface_velocity + tangential(
                        smooth_flow(model, flow, e, p[0], p[1]), n
                    )
                impulses = add_column_contact(model, impulses, v, w, n, overlap, surface_velocity)
        dvw = combined_velocity_change(model, impulses)
        if wp.static(surface_work):
            work[e, j] = work[e, j] + wp.max(column_work(model, impulses, dvw), 0.0)
        v = v + wp.vec3(dvw[0], dvw[1], dvw[2])
        w = w + wp.vec3(dvw[3], dvw[4], dvw[5])

        v = v / (1.0 + model.linear_damping * dt)
        w = w / (1.0 + model.angular_damping * dt)
        position_out[e, j] = p + v * dt
        velocity_out[e, j] = v
        angular_velocity_out[e, j] = w

    @wp.kernel(
        cuda_max_registers=CONTACT_MAX_REGISTERS,
        module="unique",
        module_options={"enable_backward": False},
    )
    def substep(
        model: Model,
        frac: float,
        height_prev: wp.array3d(dtype=float),
        height: wp.array3d(dtype=float),
        flow: wp.array3d(dtype=wp.vec2),
        work: wp.array2d(dtype=float),
        active: wp.array2d(dtype=wp.int32),
        position_in: wp.array2d(dtype=wp.vec3),
        velocity_in: wp.array2d(dtype=wp.vec3),
        angular_velocity_in: wp.array2d(dtype=wp.vec3),
        position_out: wp.array2d(dtype=wp.vec3),
        velocity_out: wp.array2d(dtype=wp.vec3),
        angular_velocity_out: wp.array2d(dtype=wp.vec3),
    ):
        """Advances every sphere by one substep (:func:`advance_sphere`). Launch dim:
        [num_envs, M]."""
        e, j = wp.tid()
        advance_sphere(
            model,
            frac,
            height_prev,
            height,
            flow,
            work,
            active,
            position_in,
            velocity_in,
            angular_velocity_in,
            position_out,
            velocity_out,
            angular_velocity_out,
            e,
            j,
        )

    @wp.kernel(
        cuda_max_registers=CONTACT_MAX_REGISTERS,
        module="unique",
        module_options={"enable_backward": False},
    )
    def tick_substeps(
        model: Model,
        height_prev: wp.array3d(dtype=float),
        height: wp.array3d(dtype=float),
        flow: wp.array3d(dtype=wp.vec2),
        work: wp.array2d(dtype=float),
        active: wp.array2d(dtype=wp.int32),
        position: wp.array2d(dtype=wp.vec3),
        velocity: wp.array2d(dtype=wp.vec3),
        angular_velocity: wp.array2d(dtype=wp.vec3),
        position_next: wp.array2d(dtype=wp.vec3),
        velocity_next: wp.array2d(dtype=wp.vec3),
        angular_velocity_next: wp.array2d(dtype=wp.vec3),
    ):
        """Advances every sphere of an environment through all substeps of one tick, as many
        launches of :func:`substep` would. Launch dim: [num_envs].

        One thread per environment, so that a substep can follow the previous one without a
        launch in between: every sphere's next state goes to the ``_next`` arrays, and only once
        all of them are there do they become the current state.
        """
        e = wp.tid()
        for s in range(model.substeps):
            frac = (float(s) + 0.5) / float(model.substeps)
            for j in range(model.num_objects):
                advance_sphere(
                    model,
                    frac,
                    height_prev,
                    height,
                    flow,
                    work,
                    active,
                    position,
                    velocity,
                    angular_velocity,
                    position_next,
                    velocity_next,
                    angular_velocity_next,
                    e,
                    j,
                )
            for j in range(model.num_objects):
                position[e, j] = position_next[e, j]
                velocity[e, j] = velocity_next[e, j]
                angular_velocity[e, j] = angular_velocity_next[e, j]

    return substep, tick_substeps
