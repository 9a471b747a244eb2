"""Sphere physics against closed-form results, through scripted scenes."""

import math

import numpy as np
import pytest
import torch
import warp as wp

from terrashift_rl.sim import (
    COLUMN_SHAPES,
    ScriptedScene,
    Simulator,
    TerraShiftConfig,
    columns,
    physics,
)
from terrashift_rl.sim.types import Model, build_model

RADIUS = 0.075
REST_TOP = 0.12


def scene(shape: str, *, objects: int = 1, num_envs: int = 1, **overrides) -> ScriptedScene:
    config = TerraShiftConfig(column_shape=shape, num_objects=objects, num_goals=1, **overrides)
    return ScriptedScene(config, num_envs=num_envs)


def corner(cfg: TerraShiftConfig, ix: int, iy: int) -> tuple[float, float]:
    """(x, y) [m] of the corner shared by columns ix, ix + 1 and rows iy, iy + 1: a hollow
    between four ellipsoids."""
    return (ix + 1) * cfg.cell_size - 0.5, (iy + 1) * cfg.cell_size - 0.5


def total_energy(sc: ScriptedScene) -> float:
    """Kinetic (translation + rotation) plus gravitational energy of every sphere [J]."""
    cfg = sc.config
    m, inertia = cfg.sphere_mass, 0.4 * cfg.sphere_mass * cfg.sphere_radius**2
    v, w, p = sc.sphere_velocity, sc.sphere_angular_velocity, sc.sphere_position
    kinetic = 0.5 * m * (v**2).sum() + 0.5 * inertia * (w**2).sum()
    return (kinetic + m * cfg.gravity * p[..., 2].sum()).item()


@wp.kernel
def _smooth_surface_at(
    model: Model,
    height_prev: wp.array3d(dtype=float),
    height: wp.array3d(dtype=float),
    points: wp.array(dtype=wp.vec2),
    frac: float,
    out: wp.array(dtype=wp.vec4),
):
    i = wp.tid()
    out[i] = columns.smooth_surface(model, height_prev, height, 0, points[i][0], points[i][1], frac)


def reference_smooth_surface(cfg, height_prev, height, x, y, frac) -> np.ndarray:
    """(z, dz/dx, dz/dy, dz/dt) of the bilinear surface through the column tops, flat beyond
    the outermost column centres, in float64."""
    g, cell = cfg.grid_size, cfg.cell_size
    tops = cfg.column_rest_top + height_prev + frac * (height - height_prev)
    speeds = (height - height_prev) * cfg.physics_hz
    u = (x + 0.5 * cfg.platform_size) / cell - 0.5
    v = (y + 0.5 * cfg.platform_size) / cell - 0.5
    uc, vc = min(max(u, 0.0), g - 1.0), min(max(v, 0.0), g - 1.0)
    i, j = min(math.floor(uc), g - 2), min(math.floor(vc), g - 2)
    tu, tv = uc - i, vc - j

    def bilinear(f):
        return (1 - tv) * ((1 - tu) * f[j, i] + tu * f[j, i + 1]) + tv * (
            (1 - tu) * f[j + 1, i] + tu * f[j + 1, i + 1]
        )

    dzdx = (1 - tv) * (tops[j, i + 1] - tops[j, i]) + tv * (tops[j + 1, i + 1] - tops[j + 1, i])
    dzdy = (1 - tu) * (tops[j + 1, i] - tops[j, i]) + tu * (tops[j + 1, i + 1] - tops[j, i + 1])
    inside_x, inside_y = 0.0 < u < g - 1.0, 0.0 < v < g - 1.0
    return np.array(
        [bilinear(tops), dzdx / cell * inside_x, dzdy / cell * inside_y, bilinear(speeds)]
    )


SURFACE_TOL = 2e-5
"""Absolute tolerance on the smooth surface's height [m], slopes and speed [m/s]: float32
rounding of a bilinear interpolation, slopes divided by a cell of a few centimetres."""


@pytest.mark.parametrize("grid_size", [2, 3, 15, 30])
def test_smooth_surface_matches_bilinear_reference(grid_size):
    cfg = TerraShiftConfig(grid_size=grid_size, num_objects=1, num_goals=1, spawn_margin=0)
    rng = np.random.default_rng(0)
    height_prev, height = rng.uniform(-0.05, 0.05, (2, 1, grid_size, grid_size))
    # beyond the platform edge too, where the surface is flat
    points = rng.uniform(-0.6, 0.6, (500, 2))
    frac = 0.3
    out = wp.zeros(len(points), dtype=wp.vec4, device="cpu")
    wp.launch(
        _smooth_surface_at,
        dim=len(points),
        inputs=[
            build_model(cfg),
            wp.array(height_prev, dtype=float, device="cpu"),
            wp.array(height, dtype=float, device="cpu"),
            wp.array(points, dtype=wp.vec2, device="cpu"),
            frac,
            out,
        ],
        device="cpu",
    )
    points32 = points.astype(np.float32).astype(np.float64)  # what the kernel saw
    expected = np.stack(
        [reference_smooth_surface(cfg, height_prev[0], height[0], x, y, frac) for x, y in points32]
    )
    np.testing.assert_allclose(out.numpy(), expected, atol=SURFACE_TOL, rtol=0)


@wp.kernel
def _combine_column_contacts(
    model: Model,
    velocity: wp.vec3,
    angular_velocity: wp.vec3,
    normals: wp.array(dtype=wp.vec3),
    overlaps: wp.array(dtype=float),
    column_speeds: wp.array(dtype=float),
    out: wp.array(dtype=wp.spatial_vector),
):
    impulses = physics.new_column_impulses()
    for i in range(normals.shape[0]):
        surface_velocity = wp.vec3(0.0, 0.0, column_speeds[i])
        impulses = physics.add_column_contact(
            model, impulses, velocity, angular_velocity, normals[i], overlaps[i], surface_velocity
        )
    out[0] = physics.combined_velocity_change(model, impulses)


def reference_column_contacts(model, v, w, normals, overlaps, column_speeds) -> np.ndarray:
    """Velocity change (linear, angular) of a sphere from its column contacts, in float64, with
    the friction factor's least squares written out contact by contact."""
    m, inertia, r = model.sphere_mass, model.sphere_inertia, model.sphere_radius
    k, c, dt, mu = (
        model.contact_stiffness,
        model.column_contact_damping,
        model.substep_dt,
        model.friction,
    )
    normal, approach, share = np.zeros(3), np.zeros(3), 0.0
    contacts = []  # (normal, arm, slip, friction impulse, normal impulse)
    for n, overlap, speed in zip(normals, overlaps, column_speeds, strict=True):
        arm = -r * n
        rel = v + np.cross(w, arm) - np.array([0.0, 0.0, speed])
        normal_speed = rel @ n
        force = k * overlap - c * normal_speed
        if force <= 0.0:
            continue
        normal += n * force * dt
        if normal_speed < 0.0:
            approach += n * (-c * normal_speed * dt)
            share += c * dt / m
        slip = rel - normal_speed * n
        stopping = np.linalg.norm(slip) / (1.0 / m + r * r / inertia)
        magnitude = min(stopping, mu * force * dt)
        jt = -magnitude * slip / np.linalg.norm(slip)
        contacts.append((n, arm, slip, jt, force * dt))
    normal_dv = (normal - (1.0 - 1.0 / max(share, 1.0)) * approach) / m
    dv = sum(jt for *_, jt, _ in contacts) / m
    dw = sum(np.cross(arm, jt) for _, arm, _, jt, _ in contacts) / inertia
    along = curvature = work = 0.0
    cone = math.inf
    for n, arm, slip, jt, jn in contacts:
        change = dv + np.cross(dw, arm)
        left = slip + normal_dv - (normal_dv @ n) * n  # slip after the normal impulses
        along += left @ change
        curvature += change @ change
        work += jt @ left
        cone = min(cone, mu * jn / np.linalg.norm(jt))
    energy = m * dv @ dv + inertia * dw @ dw
    scale = np.clip(-along / curvature, 0.0, max(min(cone, -2.0 * work / energy), 0.0))
    return np.concatenate([normal_dv + scale * dv, scale * dw])


def combine_column_contacts(model, v, w, normals, overlaps, column_speeds) -> np.ndarray:
    out = wp.zeros(1, dtype=wp.spatial_vector, device="cpu")
    wp.launch(
        _combine_column_contacts,
        dim=1,
        inputs=[
            model,
            wp.vec3(*v),
            wp.vec3(*w),
            wp.array(normals, dtype=wp.vec3, device="cpu"),
            wp.array(overlaps, dtype=float, device="cpu"),
            wp.array(column_speeds, dtype=float, device="cpu"),
            out,
        ],
        device="cpu",
    )
    return out.numpy()[0].astype(np.float64)


COMBINE_TOL = 1e-5
"""Absolute tolerance on a substep's velocity change [m/s, rad/s]: float32 rounding of sums
of a few impulses."""


def tilted_normals(tilt: float, count: int, turn: float = 0.0) -> np.ndarray:
    """``count`` unit normals tilted ``tilt`` [rad] from vertical, evenly around the z axis."""
    angles = turn + 2 * np.pi * np.arange(count) / count
    return np.stack(
        [
            np.sin(tilt) * np.cos(angles),
            np.sin(tilt) * np.sin(angles),
            np.full(count, np.cos(tilt)),
        ],
        axis=-1,
    )


@pytest.mark.parametrize("restitution", [0.05, 0.3, 0.9])
def test_column_contacts_combine_as_reference(restitution):
    model = build_model(TerraShiftConfig(restitution=restitution))
    rng = np.random.default_rng(0)
    cases = [
        # a sphere in a hollow, lifted by its four columns, spinning
        (np.array([0.0, 0.0, -0.2]), np.array([1.0, -2.0, 0.5]), tilted_normals(0.8, 4), 1.8),
        # a sphere wedged against five columns, sliding across them
        (np.array([0.6, -0.3, -0.1]), np.array([0.0, 3.0, -1.0]), tilted_normals(1.2, 5, 0.3), 0.0),
    ]
    for v, w, normals, speed in cases:
        overlaps = rng.uniform(0.0, 0.003, len(normals))
        speeds = np.full(len(normals), speed)
        np.testing.assert_allclose(
            combine_column_contacts(model, v, w, normals, overlaps, speeds),
            reference_column_contacts(model, v, w, normals, overlaps, speeds),
            atol=COMBINE_TOL,
            rtol=0,
        )


def test_single_column_contact_is_that_contacts_own_impulse():
    model = build_model(TerraShiftConfig())
    m, inertia, r = model.sphere_mass, model.sphere_inertia, model.sphere_radius
    n = tilted_normals(0.4, 1, 0.7)[0]
    overlap = 0.001
    for v in (np.array([0.05, 0.02, -0.1]), np.array([1.5, -1.0, -0.6])):  # sticks, slides
        rel = v
        force = model.contact_stiffness * overlap - model.column_contact_damping * (rel @ n)
        jn = force * model.substep_dt
        slip = rel - (rel @ n) * n
        magnitude = min(np.linalg.norm(slip) / (1 / m + r * r / inertia), model.friction * jn)
        jt = -magnitude * slip / np.linalg.norm(slip)
        expected = np.concatenate([(n * jn + jt) / m, np.cross(-r * n, jt) / inertia])
        got = combine_column_contacts(model, v, np.zeros(3), n[None], [overlap], [0.0])
        np.testing.assert_allclose(got, expected, atol=COMBINE_TOL, rtol=0)


@pytest.mark.parametrize("restitution", [0.05, 0.3, 0.9])
@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_sphere_at_rest_on_flat_field_stays_put(shape, restitution):
    sc = scene(shape, restitution=restitution)
    # a stable resting place: a column top for boxes and the smooth surface, the hollow
    # between four domes for ellipsoids
    xy = sc.config.cell_size / 2 if shape == "ellipsoid" else 0.0
    sc.place_spheres(torch.tensor([[xy, xy, REST_TOP + RADIUS + 0.002]]))
    sc.step(60)  # settle for 1 s
    start = sc.sphere_position[0, 0]
    sc.step(600)  # 10 s
    drift = (sc.sphere_position[0, 0] - start).norm().item()
    assert drift < 1e-3, f"{shape}: drifted {drift * 1e3:.3f} mm in 10 s"
    assert sc.sphere_velocity.norm() < 1e-3


@pytest.mark.parametrize("restitution", [0.05, 0.3, 0.9])
def test_sphere_on_four_box_corners_settles(restitution):
    # on the corner shared by four box tops the sphere touches all four at one point: four
    # dashpots in parallel, which at low restitution together stop more than the approach
    sc = scene("box", restitution=restitution)
    x, y = corner(sc.config, 7, 7)
    sc.place_spheres(torch.tensor([[x, y, REST_TOP + RADIUS + 0.002]]))
    energy = [total_energy(sc)]
    for _ in range(60):  # settle for 1 s
        sc.step(1)
        energy.append(total_energy(sc))
    start = sc.sphere_position[0, 0]
    sc.step(600)  # 10 s
    drift = (sc.sphere_position[0, 0] - start).norm().item()
    assert max(energy) <= energy[0] + 1e-4
    assert drift < 1e-3, f"drifted {drift * 1e3:.3f} mm in 10 s"
    assert sc.sphere_velocity.norm() < 1e-3


@pytest.mark.parametrize("slope", [0.05, 0.1])
def test_sphere_rolls_down_a_slope_at_five_sevenths_g_sin_theta(slope):
    sc = scene("smooth")
    cfg = sc.config
    centres = (torch.arange(cfg.grid_size) + 0.5) * cfg.cell_size - 0.5
    sc.set_column_heights((-slope * centres).expand(cfg.grid_size, -1))  # falls along +x
    sc.step(1)
    theta = math.atan(slope)
    x0 = -0.3
    z0 = REST_TOP + slope * -x0 + RADIUS / math.cos(theta)
    sc.place_spheres(torch.tensor([[x0, 0.0, z0]]))
    sc.step(6)  # let the contact settle
    v0, t0 = sc.sphere_velocity[0, 0], sc.time
    sc.step(30)
    v1, t1 = sc.sphere_velocity[0, 0], sc.time
    along = torch.tensor([math.cos(theta), 0.0, -math.sin(theta)])
    acceleration = ((v1 - v0) @ along).item() / (t1 - t0)
    expected = 5.0 / 7.0 * cfg.gravity * math.sin(theta)
    assert acceleration == pytest.approx(expected, rel=0.10)
    # rolling without slipping: spin about +y equals speed over radius
    speed = (v1 @ along).item()
    assert sc.sphere_angular_velocity[0, 0, 1].item() == pytest.approx(speed / RADIUS, rel=0.05)


@pytest.mark.parametrize("restitution", [0.3, 0.6, 0.9])
def test_bounce_matches_restitution(restitution):
    # no gravity, so the collision is the pure 1-D problem restitution is defined by
    sc = scene("box", restitution=restitution, gravity=0.0)
    impact = 1.0
    sc.place_spheres(
        torch.tensor([[0.0, 0.0, REST_TOP + RADIUS + 0.01]]),
        velocities=torch.tensor([[0.0, 0.0, -impact]]),
    )
    sc.step(15)  # 0.25 s: the contact lasts about 30 ms
    rebound = sc.sphere_velocity[0, 0, 2].item()
    assert rebound == pytest.approx(restitution * impact, rel=0.10)


def test_head_on_collision_conserves_momentum():
    velocities = torch.tensor([[1.0, 0.0, 0.0], [-0.4, 0.0, 0.0]])
    ratios = []
    # where in a substep the contact begins shifts the outcome of one collision by a few
    # percent (docs/physics.md); the restitution holds on average over that phase
    for offset in (0.0, 0.001, 0.002, 0.003):
        sc = scene("box", objects=2, gravity=0.0, linear_damping=0.0)
        positions = torch.tensor([[-0.1, 0.0, 0.35], [0.1 + offset, 0.0, 0.35]])
        sc.place_spheres(positions, velocities=velocities)
        sc.step(20)
        after = sc.sphere_velocity[0]
        torch.testing.assert_close(after.sum(0), velocities.sum(0), atol=1e-5, rtol=0)
        ratios.append(-(after[0, 0] - after[1, 0]) / (velocities[0, 0] - velocities[1, 0]))
    assert torch.stack(ratios).mean().item() == pytest.approx(sc.config.restitution, rel=0.10)


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_no_tunnelling_through_columns_at_their_fastest_motion(shape):
    sc = scene(shape)
    hmax = sc.config.max_column_height
    xy = sc.config.cell_size / 2 if shape == "ellipsoid" else 0.0
    sc.set_column_heights(-hmax)
    sc.step(1)
    sc.place_spheres(torch.tensor([[xy, xy, REST_TOP - hmax + RADIUS + 0.001]]))
    sc.step(30)
    lowest_gap = math.inf
    for tick in range(60):
        # the columns swing through their whole travel in a single tick
        sc.set_column_heights(hmax if tick % 2 == 0 else -hmax)
        sc.step(1)
        top = REST_TOP + sc.column_heights.max().item()
        lowest_gap = min(lowest_gap, sc.sphere_position[0, 0, 2].item() - top)
    assert lowest_gap > 0.0, "the sphere centre went below the column tops"


def test_rising_column_throws_the_sphere():
    sc = scene("box")
    hmax = sc.config.max_column_height
    sc.set_column_heights(-hmax)
    sc.step(1)
    sc.place_spheres(torch.tensor([[0.0, 0.0, REST_TOP - hmax + RADIUS + 0.001]]))
    sc.step(30)
    sc.set_column_heights(hmax)
    sc.step(1)
    column_speed = 2 * hmax * sc.config.physics_hz
    assert sc.sphere_velocity[0, 0, 2].item() > 0.5 * column_speed


@pytest.mark.parametrize("restitution", [0.05, 0.3, 0.9])
@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_energy_never_grows_on_a_static_field(shape, restitution):
    generator = torch.Generator().manual_seed(0)
    sc = scene(shape, objects=4, restitution=restitution)
    cfg = sc.config
    heights = (torch.rand(cfg.grid_size, cfg.grid_size, generator=generator) * 2 - 1) * 0.05
    sc.set_column_heights(heights)
    sc.step(1)
    positions = torch.tensor(
        [[-0.2, -0.2, 0.30], [0.2, -0.2, 0.32], [-0.2, 0.2, 0.34], [0.05, 0.05, 0.36]]
    )
    velocities = (torch.rand(4, 3, generator=generator) * 2 - 1) * 0.5
    spins = (torch.rand(4, 3, generator=generator) * 2 - 1) * 5.0
    sc.place_spheres(positions, velocities=velocities, angular_velocities=spins)
    energy = [total_energy(sc)]
    for _ in range(180):
        sc.step(1)
        energy.append(total_energy(sc))
    energy = torch.tensor(energy)
    # compressed contact springs hold some energy for a few milliseconds and give it back, so
    # kinetic plus gravitational energy may rise between ticks, but never above the start
    assert energy.max() <= energy[0] + 1e-4
    assert energy[-1] < energy[0]


# --- moving columns and the order of contacts ----------------------------------------------

# A 3 x 3 patch of columns around the platform's centre column (7, 7) of the 15 x 15 grid
PATCH = slice(6, 9)
# The hollow inside the patch, where all four supporting columns rise, and one on its edge,
# where two of the four rise
PATCH_HOLLOWS = {"centre": (7, 7), "edge": (8, 7)}
# Refining the step 16-fold must move the peak of a throw by less than this fraction of it
THROW_CONVERGENCE = 0.05


def throw_height(column_speed: float, hollow: str, *, substeps: int) -> float:
    """How high [m] a sphere resting in one of the ``PATCH_HOLLOWS`` flies when the patch rises
    at ``column_speed`` [m/s] for one tick: its peak height minus its resting height."""
    sc = scene("ellipsoid", substeps=substeps)
    cfg = sc.config
    x, y = corner(cfg, *PATCH_HOLLOWS[hollow])
    sc.place_spheres(torch.tensor([[x, y, REST_TOP + RADIUS + 0.002]]))
    sc.step(60)  # settle
    rest = sc.sphere_position[0, 0, 2].item()
    heights = torch.zeros(cfg.grid_size, cfg.grid_size)
    heights[PATCH, PATCH] = column_speed / cfg.physics_hz
    sc.set_column_heights(heights)
    peak = rest
    for _ in range(45):  # 0.75 s: past the top of the highest throw
        sc.step(1)
        peak = max(peak, sc.sphere_position[0, 0, 2].item())
    return peak - rest


@pytest.mark.parametrize("hollow", sorted(PATCH_HOLLOWS))
@pytest.mark.parametrize("column_speed", [1.8, 3.6])
def test_throw_by_a_rising_patch_converges_at_the_default_step(column_speed, hollow):
    default = TerraShiftConfig().substeps
    coarse = throw_height(column_speed, hollow, substeps=default)
    fine = throw_height(column_speed, hollow, substeps=16 * default)
    error = coarse / fine - 1.0
    assert abs(error) < THROW_CONVERGENCE, (
        f"{column_speed} m/s, {hollow}: {coarse:.4f} m at {default} substeps, {fine:.4f} m at "
        f"{16 * default} ({error:+.1%})"
    )


# Lateral speed of a sphere lifted by columns symmetric around it
SYMMETRIC_LATERAL_SPEED = 1e-3  # m/s


@pytest.mark.parametrize("restitution", [0.05, 0.3, 0.9])
@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_symmetric_lift_goes_straight_up(shape, restitution):
    speeds = [0.6, 1.8, 3.6]  # m/s, one scene each
    sc = scene(shape, num_envs=len(speeds), restitution=restitution)
    cfg = sc.config
    x, y = corner(cfg, 7, 7)
    sc.place_spheres(torch.tensor([[x, y, REST_TOP + RADIUS + 0.002]]))
    sc.step(60)  # settle
    heights = torch.zeros(len(speeds), cfg.grid_size, cfg.grid_size)
    for env, speed in enumerate(speeds):
        heights[env, 7:9, 7:9] = speed / cfg.physics_hz  # the four columns around the sphere
    sc.set_column_heights(heights)
    lateral = torch.zeros(len(speeds))
    for _ in range(30):
        sc.step(1)
        lateral = torch.maximum(lateral, sc.sphere_velocity[:, 0, :2].norm(dim=-1))
    assert lateral.max() < SYMMETRIC_LATERAL_SPEED, (
        f"lateral speeds {lateral.tolist()} m/s at column speeds {speeds} m/s"
    )


def mirror_images(vectors: torch.Tensor, *, axial: bool = False) -> torch.Tensor:
    """A scene's vectors [..., 3] and their images under x -> -x, y -> -y and the transpose
    x <-> y, stacked along a new leading dimension. Angular velocities are ``axial``: a
    reflection maps them to minus their reflected image."""
    flip_x = vectors * torch.tensor([-1.0, 1.0, 1.0])
    flip_y = vectors * torch.tensor([1.0, -1.0, 1.0])
    transpose = vectors[..., [1, 0, 2]]
    images = torch.stack([vectors, flip_x, flip_y, transpose])
    if axial:
        images[1:] = -images[1:]
    return images


def mirror_heights(heights: torch.Tensor) -> torch.Tensor:
    """A height field [G(y), G(x)] and its images, in the order of :func:`mirror_images`."""
    return torch.stack([heights, heights.flip(-1), heights.flip(-2), heights.T])


# Mirrored scenes must stay mirror images of each other to this distance over 1 s
MIRROR_TOLERANCE = 1e-4  # m


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_mirrored_scenes_give_mirrored_trajectories(shape):
    generator = torch.Generator().manual_seed(0)
    sc = scene(shape, objects=2, num_envs=4)
    cfg = sc.config
    # a random field that rises and falls once a second (columns at up to 0.2 m/s), two spheres
    # rolling over it into each other
    field = (torch.rand(cfg.grid_size, cfg.grid_size, generator=generator) * 2 - 1) * 0.03
    positions = torch.tensor([[-0.2, 0.03, 0.25], [0.2, -0.02, 0.25]])
    velocities = torch.tensor([[0.5, 0.0, 0.0], [-0.5, 0.05, 0.0]])
    spins = (torch.rand(2, 3, generator=generator) * 2 - 1) * 2.0
    sc.set_column_heights(mirror_heights(field))
    sc.step(1)
    sc.place_spheres(
        mirror_images(positions),
        velocities=mirror_images(velocities),
        angular_velocities=mirror_images(spins, axial=True),
    )
    worst = 0.0
    for tick in range(60):
        sc.set_column_heights(mirror_heights(field * math.cos(2 * math.pi * tick * cfg.tick_dt)))
        sc.step(1)
        # each image mapped back (every reflection here is its own inverse)
        images = mirror_images(sc.sphere_position)
        back = torch.stack([images[i, i] for i in range(4)])
        worst = max(worst, (back - back[0]).norm(dim=-1).max().item())
    assert worst < MIRROR_TOLERANCE, f"{shape}: mirrored trajectories {worst * 1e3:.4f} mm apart"


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
@pytest.mark.parametrize("substeps", [8, 5])
def test_fused_substeps_compute_what_a_launch_per_substep_computes(shape, substeps):
    """A tick's substeps in one launch (a thread per environment) and in a launch each (a
    thread per sphere) give the same bits, in episodes long enough for spheres to meet."""
    config = TerraShiftConfig(column_shape=shape, substeps=substeps)
    generator = torch.Generator().manual_seed(0)
    actions = torch.rand(24, 8, config.num_agents, 6, generator=generator) * 2 - 1
    states = []
    for fuse_substeps in (True, False):
        sim = Simulator(config, num_envs=8, seed=1, fuse_substeps=fuse_substeps)
        sim.reset()
        for action in actions:
            sim.step(action)
        states.append(sim.state_dict())
    fused, unfused = states
    assert fused["sphere_active"].sum() > 8
    for name, value in fused.items():
        torch.testing.assert_close(value, unfused[name], rtol=0, atol=0, msg=name)
