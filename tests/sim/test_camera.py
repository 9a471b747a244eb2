"""Overhead camera against a NumPy reference: grey levels, placement, occlusion, settings."""

import math

import numpy as np
import pytest
import torch
from test_observations import column_centres, column_surface, pose_scene

from terrashift_rl.sim import COLUMN_SHAPES, Simulator, TerraShiftConfig
from terrashift_rl.sim.camera import MARKER_LOW, TERRAIN_HIGH, TERRAIN_LOW, camera_levels
from terrashift_rl.sim.config import MAX_CAMERA_RESOLUTION

SEED = 0
LEVEL_TOL = 1e-5
"""Absolute tolerance on a pixel's grey level: float32 rounding of a column's height, of the
terrain shade's division and of the marker levels."""
BOUNDARY_MARGIN = 1e-6
"""Pixels this close [m or m^2] to the edge of a disc or to an occlusion's tie are left out:
float32 and float64 may decide those either way."""


def make_sim(*, num_envs: int = 2, device: str = "cpu", **overrides) -> Simulator:
    config = TerraShiftConfig(
        **{"num_objects": 4, "num_goals": 2, "camera_resolution": 48, **overrides}
    )
    return Simulator(config, num_envs=num_envs, device=device, seed=SEED)


# --- NumPy reference ----------------------------------------------------------------------


def camera_lattice(cfg: TerraShiftConfig) -> np.ndarray:
    """Pixel coordinates [m] along one axis, in float32 as the kernel computes them."""
    half = np.float32(0.5 * cfg.platform_size)
    step = np.float32(2.0) * half / np.float32(cfg.camera_resolution - 1)
    return (-half + np.arange(cfg.camera_resolution, dtype=np.float32) * step).astype(np.float64)


def terrain(cfg: TerraShiftConfig, z: float) -> float:
    if z == -math.inf:
        return 0.0
    low = cfg.column_rest_top - cfg.max_column_height
    fraction = np.clip((z - low) / (2 * cfg.max_column_height), 0.0, 1.0)
    return TERRAIN_LOW + (TERRAIN_HIGH - TERRAIN_LOW) * fraction


def reference_camera(
    cfg: TerraShiftConfig,
    heights: np.ndarray,
    goal_cells: np.ndarray,
    positions: np.ndarray,
    active: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The image [R(y), R(x)] of one environment and, per pixel, how close it is to a decision
    boundary (disc edges, ties between a sphere's top and what is under it, between goals)."""
    coords = camera_lattice(cfg)
    centres = column_centres(cfg)
    levels = camera_levels(cfg.num_goals)
    r2, g2 = cfg.sphere_radius**2, cfg.goal_radius**2
    image = np.empty((len(coords), len(coords)))
    margin = np.full_like(image, np.inf)
    for ry, y in enumerate(coords):
        for rx, x in enumerate(coords):
            top = column_surface(cfg, heights, x, y)
            value = terrain(cfg, top)
            goal_d2 = [(x - centres[gx]) ** 2 + (y - centres[gy]) ** 2 for gx, gy in goal_cells]
            order = np.argsort(goal_d2, kind="stable")
            near = [d for d in goal_d2 if d < g2]
            if near:
                value = levels[order[0]][0]
            closest = [abs(d - g2) for d in goal_d2]
            if len(near) > 1:
                closest.append(goal_d2[order[1]] - goal_d2[order[0]])
            for j, ((px, py, pz), on) in enumerate(zip(positions, active, strict=True)):
                d2 = (px - x) ** 2 + (py - y) ** 2
                if on:
                    closest.append(abs(d2 - r2))
                if on and d2 <= r2:
                    sphere_top = pz + math.sqrt(r2 - d2)
                    closest.append(abs(sphere_top - top))
                    if sphere_top > top:
                        top = sphere_top
                        value = levels[j % cfg.num_goals][1]
            image[ry, rx] = value
            margin[ry, rx] = min(closest)
    return image, margin


def assert_camera_matches_state(sim: Simulator, env: int) -> np.ndarray:
    """The camera of ``env`` equals the reference drawn from its current state; returns it."""

    def state(name):
        return sim.view(name)[env].cpu().numpy()

    expected, margin = reference_camera(
        sim.config,
        state("column_height").astype(np.float64),
        state("goal_cell"),
        state("sphere_position").astype(np.float64),
        state("sphere_active"),
    )
    decided = margin > BOUNDARY_MARGIN
    assert decided.mean() > 0.99  # almost no pixel sits on a boundary
    image = state("camera")[0]
    np.testing.assert_allclose(image[decided], expected[decided], atol=LEVEL_TOL)
    return expected


def pose_scene_with_goals(sim: Simulator, rng: np.random.Generator) -> None:
    """The heightmap test's scene (random columns; spheres on top, sunk between the columns,
    above everything, inactive) and goals on distinct random columns."""
    pose_scene(sim, rng)
    cfg = sim.config
    side = cfg.grid_size - 4
    cells = [rng.choice(side * side, cfg.num_goals, replace=False) for _ in range(sim.num_envs)]
    cells = np.stack([np.stack([index % side, index // side], -1) + 2 for index in cells])
    sim.view("goal_cell").copy_(torch.as_tensor(cells))


def showing(image: np.ndarray, level: float) -> np.ndarray:
    """Where ``image`` shows grey level ``level``."""
    return np.abs(image - level) < LEVEL_TOL


def pixel(sim: Simulator, x: float, y: float) -> tuple[int, int]:
    """(row, column) of the pixel nearest (x, y): rows are y, columns are x."""
    coords = camera_lattice(sim.config)
    return int(np.abs(coords - y).argmin()), int(np.abs(coords - x).argmin())


# --- rendering ----------------------------------------------------------------------------


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_camera_matches_reference(shape):
    sim = make_sim(column_shape=shape)
    pose_scene_with_goals(sim, np.random.default_rng(SEED))
    sim.observe()
    levels = camera_levels(sim.config.num_goals)
    for env in range(sim.num_envs):
        expected = assert_camera_matches_state(sim, env)
        # the scene shows what it is meant to: both goals and the spheres of both pairs
        for goal_level, sphere_level in levels:
            assert (expected == goal_level).any() and (expected == sphere_level).any()
        if shape == "ellipsoid":  # the platform seen between the domes
            assert (expected == 0.0).any()
    image = sim.view("camera")
    assert image.shape == (2, 1, 48, 48) and image.dtype == torch.float32
    assert image.min() >= 0.0 and image.max() <= 1.0


def test_odd_resolution_matches_reference():
    # an odd side splits unevenly into the halves the terrain's threads share (box columns:
    # with domes, the middle of an odd image's edge grazes the outer dome, where float32
    # and float64 part)
    sim = make_sim(column_shape="box", camera_resolution=47)
    pose_scene_with_goals(sim, np.random.default_rng(SEED))
    sim.observe()
    for env in range(sim.num_envs):
        assert_camera_matches_state(sim, env)


def test_levels_tell_goals_spheres_and_pairs_apart():
    levels = camera_levels(4)
    flat = [level for pair in levels for level in pair]
    assert len(set(flat)) == 8
    assert flat == sorted(flat) and flat[0] == MARKER_LOW and flat[-1] == 1.0
    assert TERRAIN_HIGH < MARKER_LOW  # no column is mistaken for a marker
    assert camera_levels(1) == [(MARKER_LOW, 1.0)]


def test_sphere_and_goal_are_drawn_where_they_are_with_their_pair_level():
    sim = make_sim(column_shape="box", num_envs=1, num_objects=3)
    cfg = sim.config
    levels = camera_levels(cfg.num_goals)
    sim.view("column_height").zero_()
    sim.view("goal_cell").copy_(torch.tensor([[[3, 4], [11, 10]]]))  # (ix, iy) of each goal
    rest = cfg.column_rest_top + cfg.sphere_radius
    # sphere 2 belongs to goal 0 (2 mod 2), sphere 1 to goal 1; sphere 0 is not in play
    sim.view("sphere_position").copy_(
        torch.tensor([[[0.0, 0.0, rest], [0.25, -0.3, rest], [-0.2, 0.3, rest]]])
    )
    sim.view("sphere_active").copy_(torch.tensor([[0, 1, 1]]))
    sim.observe()
    image = sim.view("camera")[0, 0]
    centres = column_centres(cfg)
    assert image[pixel(sim, 0.25, -0.3)].item() == pytest.approx(levels[1][1], abs=LEVEL_TOL)
    assert image[pixel(sim, -0.2, 0.3)].item() == pytest.approx(levels[0][1], abs=LEVEL_TOL)
    assert image[pixel(sim, centres[3], centres[4])].item() == pytest.approx(
        levels[0][0], abs=LEVEL_TOL
    )
    assert image[pixel(sim, centres[11], centres[10])].item() == pytest.approx(
        levels[1][0], abs=LEVEL_TOL
    )
    # the inactive sphere is not drawn: flat columns at rest height are mid-grey terrain
    middle = 0.5 * (TERRAIN_LOW + TERRAIN_HIGH)
    assert image[pixel(sim, 0.0, 0.0)].item() == pytest.approx(middle, abs=LEVEL_TOL)
    # each marker is a disc of its radius about its centre
    coords = camera_lattice(cfg)
    rows, cols = np.nonzero(showing(image.numpy(), levels[1][1]))
    distance = np.hypot(coords[cols] - 0.25, coords[rows] + 0.3)
    assert distance.max() <= cfg.sphere_radius
    rows, cols = np.nonzero(showing(image.numpy(), levels[0][0]))
    distance = np.hypot(coords[cols] - centres[3], coords[rows] - centres[4])
    assert distance.max() < cfg.goal_radius and distance.max() > cfg.goal_radius - 0.03


def test_taller_columns_hide_a_sunk_sphere_and_spheres_hide_goals():
    sim = make_sim(column_shape="box", num_envs=1, num_objects=2, num_goals=1)
    cfg = sim.config
    (goal_level, sphere_level), r = camera_levels(1)[0], cfg.sphere_radius
    sim.view("column_height").fill_(cfg.max_column_height)
    surface = cfg.column_rest_top + cfg.max_column_height
    sim.view("goal_cell").copy_(torch.tensor([[[7, 7]]]))
    centre = column_centres(cfg)[7]
    # sphere 0 sits on the goal; sphere 1 is sunk 5 cm under the columns' surface at its
    # centre, so only the disc where its top rises above them shows
    sunk_z = surface - 0.05
    sim.view("sphere_position").copy_(
        torch.tensor([[[centre, centre, surface + r], [-0.25, -0.25, sunk_z]]])
    )
    sim.view("sphere_active").fill_(1)
    sim.observe()
    image = sim.view("camera")[0, 0].numpy()
    coords = camera_lattice(cfg)
    # the goal is seen only around the sphere on it
    rows, cols = np.nonzero(showing(image, goal_level))
    distance = np.hypot(coords[cols] - centre, coords[rows] - centre)
    assert len(rows) > 0 and distance.min() > r
    rows, cols = np.nonzero(showing(image, sphere_level))
    distance = np.hypot(coords[cols] + 0.25, coords[rows] + 0.25)
    sunk = distance < 2 * r
    visible_radius = math.sqrt(r**2 - (surface - sunk_z) ** 2)
    assert sunk.any() and distance[sunk].max() <= visible_radius
    assert image[pixel(sim, -0.25 + 0.9 * r, -0.25)].item() == pytest.approx(
        TERRAIN_HIGH, abs=LEVEL_TOL
    )
    # lowered under the columns' surface, it disappears
    sim.view("sphere_position")[0, 1, 2] = surface - r - 1e-3
    sim.observe()
    image = sim.view("camera")[0, 0].numpy()
    assert image[pixel(sim, -0.25, -0.25)].item() == pytest.approx(TERRAIN_HIGH, abs=LEVEL_TOL)


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_overlapping_goals_and_spheres_match_reference(shape):
    sim = make_sim(column_shape=shape, num_envs=1, num_goals=4)
    cfg = sim.config
    rng = np.random.default_rng(SEED)
    heights = rng.uniform(-cfg.max_column_height, cfg.max_column_height, (1, 15, 15))
    sim.view("column_height").copy_(torch.as_tensor(heights, dtype=torch.float32))
    # three goal regions on neighbouring columns, each overlapping the other two, and one
    # apart
    sim.view("goal_cell").copy_(torch.tensor([[[6, 7], [7, 7], [7, 8], [2, 12]]]))
    # three spheres overlapping one another, each wholly above the one before, and one over
    # the goals
    above, lift = cfg.column_rest_top + cfg.max_column_height + cfg.sphere_radius, 0.16
    positions = [[0.2, -0.2, above], [0.26, -0.2, above + lift], [0.23, -0.15, above + 2 * lift]]
    centres = column_centres(cfg)
    positions.append([centres[7], centres[7], above])
    sim.view("sphere_position").copy_(torch.tensor([positions], dtype=torch.float32))
    sim.view("sphere_active").fill_(1)
    sim.observe()
    expected = assert_camera_matches_state(sim, 0)
    levels = camera_levels(cfg.num_goals)
    # every goal keeps a part of its region and every sphere a part of its disc, but the
    # goals share their overlaps and the lower spheres are partly hidden
    full_goal = np.pi * (cfg.goal_radius / (cfg.platform_size / 47)) ** 2
    for c in range(3):
        assert 0 < showing(expected, levels[c][0]).sum() < 0.8 * full_goal
    full_sphere = np.pi * (cfg.sphere_radius / (cfg.platform_size / 47)) ** 2
    for j in range(2):
        assert 0 < showing(expected, levels[j][1]).sum() < 0.8 * full_sphere
    assert showing(expected, levels[2][1]).sum() > 0.9 * full_sphere


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_objects_at_the_border_are_cut_by_the_image_edge(shape):
    sim = make_sim(column_shape=shape, num_envs=1)
    cfg = sim.config
    half, last = 0.5 * cfg.platform_size, cfg.grid_size - 1
    sim.view("column_height").zero_()
    sim.view("goal_cell").copy_(torch.tensor([[[0, 0], [last, last]]]))  # opposite corners
    z = cfg.column_rest_top + cfg.sphere_radius
    positions = [
        [-half + 0.02, 0.1, z],  # over the left edge
        [half - 0.01, -half + 0.01, z],  # on a corner
        [0.0, half + 0.03, z],  # centre beyond the top edge, a sliver seen
        [half + 0.2, 0.0, z],  # wholly beyond the right edge
    ]
    sim.view("sphere_position").copy_(torch.tensor([positions], dtype=torch.float32))
    sim.view("sphere_active").fill_(1)
    sim.observe()
    expected = assert_camera_matches_state(sim, 0)
    image = sim.view("camera")[0, 0].numpy()
    (goal_0, sphere_0), (goal_1, sphere_1) = camera_levels(cfg.num_goals)
    assert showing(image[:, 0], sphere_0).any()  # the left edge
    assert showing(image[0, :], sphere_1).any() and showing(image[:, -1], sphere_1).any()
    assert showing(image[-1, :], sphere_0).any()  # the top edge (rows run along +y)
    assert showing(image[0, 0], goal_0) and showing(image[-1, -1], goal_1)
    # the sphere beyond the edge draws nothing: sphere 3's level shows only where sphere 1 is
    assert np.array_equal(showing(image, sphere_1), showing(expected, sphere_1))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_camera_follows_the_simulation_through_steps_and_resets(device):
    sim = make_sim(num_envs=2, device=device)  # on CUDA, inside the captured step and reset
    sim.reset()
    first = sim.view("camera").clone()
    assert_camera_matches_state(sim, 0)
    actions = torch.rand(*sim.action_shape, generator=torch.Generator().manual_seed(SEED))
    for _ in range(20):
        sim.step((actions * 2 - 1).to(device))
    assert not torch.equal(sim.view("camera"), first)
    for env in range(sim.num_envs):
        assert_camera_matches_state(sim, env)
    sim.reset(torch.tensor([True, False], device=device))
    assert_camera_matches_state(sim, 0)


def test_camera_off_by_default_renders_nothing():
    sim = Simulator(TerraShiftConfig(), num_envs=2)
    assert sim.view("camera").shape == (2, 1, 0, 0)


# --- settings -----------------------------------------------------------------------------


@pytest.mark.parametrize("value", [-1, 1, MAX_CAMERA_RESOLUTION + 1, 10**6, 32.0, True, "64"])
def test_bad_camera_resolution_is_refused_by_name(value):
    with pytest.raises(ValueError, match=rf"camera_resolution .*\[2, {MAX_CAMERA_RESOLUTION}\]"):
        TerraShiftConfig(camera_resolution=value)


def test_observe_objects_must_be_a_bool():
    with pytest.raises(ValueError, match="observe_objects must be true or false"):
        TerraShiftConfig(observe_objects="no")
