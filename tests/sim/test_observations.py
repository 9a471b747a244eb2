"""Observation stage against a NumPy reference: heightmap rays, object and agent features."""

import math

import numpy as np
import pytest
import torch

from terrashift_rl.sim import COLUMN_SHAPES, Simulator, TerraShiftConfig

SEED = 0
HEIGHTMAP_TOL = 2e-5
"""Absolute tolerance on heightmap values in [-1, 1]: float32 rounding of a ray's height,
amplified near the rim of a dome or a sphere where the surface is steep (4e-6 seen)."""
FEATURE_TOL = 1e-6
"""Absolute tolerance on normalised features: float32 rounding of one division."""


def make_sim(*, num_envs: int = 2, **overrides) -> Simulator:
    config = TerraShiftConfig(**{"num_objects": 3, "num_goals": 2, **overrides})
    return Simulator(config, num_envs=num_envs, seed=SEED)


# --- NumPy reference ----------------------------------------------------------------------


def lattice(cfg: TerraShiftConfig) -> np.ndarray:
    """Ray coordinates [m] along one axis, computed in float32 as the kernel does, so the
    reference casts exactly the same rays."""
    half = np.float32(0.5 * cfg.platform_size)
    step = np.float32(2.0) * half / np.float32(cfg.heightmap_resolution - 1)
    return (-half + np.arange(cfg.heightmap_resolution, dtype=np.float32) * step).astype(np.float64)


def column_centres(cfg: TerraShiftConfig) -> np.ndarray:
    return (np.arange(cfg.grid_size) + 0.5) * cfg.cell_size - 0.5 * cfg.platform_size


def normalised(z, cfg: TerraShiftConfig):
    h = cfg.heightmap_max_height
    return 2.0 * np.clip(z, 0.0, h) / h - 1.0


def column_surface(cfg: TerraShiftConfig, heights: np.ndarray, x: float, y: float) -> float:
    """Height [m] where a vertical ray at (x, y) meets the columns; -inf on a miss."""
    g, cell, half = cfg.grid_size, cfg.cell_size, 0.5 * cfg.platform_size
    tops = cfg.column_rest_top + heights
    ix = min(max(math.floor((x + half) / cell), 0), g - 1)
    iy = min(max(math.floor((y + half) / cell), 0), g - 1)
    if cfg.column_shape == "box":
        return tops[iy, ix]
    if cfg.column_shape == "ellipsoid":
        a = 0.5 * cell
        c = 0.5 * cfg.column_aspect * cell
        centres = column_centres(cfg)
        rho2 = (x - centres[ix]) ** 2 + (y - centres[iy]) ** 2
        if rho2 > a * a:
            return -math.inf
        return tops[iy, ix] - c * (1.0 - math.sqrt(1.0 - rho2 / (a * a)))
    # smooth: bilinear through the tops at the column centres, flat beyond the outer ones
    u = min(max((x + half) / cell - 0.5, 0.0), g - 1.0)
    v = min(max((y + half) / cell - 0.5, 0.0), g - 1.0)
    i0, j0 = min(math.floor(u), g - 2), min(math.floor(v), g - 2)
    tu, tv = u - i0, v - j0
    return (1 - tv) * ((1 - tu) * tops[j0, i0] + tu * tops[j0, i0 + 1]) + tv * (
        (1 - tu) * tops[j0 + 1, i0] + tu * tops[j0 + 1, i0 + 1]
    )


def reference_heightmap(
    cfg: TerraShiftConfig, heights: np.ndarray, positions: np.ndarray, active: np.ndarray
) -> np.ndarray:
    """Heightmap [R(y), R(x)] of one environment: the top surface of columns and active
    spheres under each ray, mapped to [-1, 1]; -1 where a ray hits nothing."""
    coords = lattice(cfg)
    r = cfg.sphere_radius
    out = np.empty((len(coords), len(coords)))
    for ry, y in enumerate(coords):
        for rx, x in enumerate(coords):
            z = column_surface(cfg, heights, x, y)
            for (px, py, pz), on in zip(positions, active, strict=True):
                d2 = (px - x) ** 2 + (py - y) ** 2
                if on and d2 <= r * r:
                    z = max(z, pz + math.sqrt(r * r - d2))
            out[ry, rx] = -1.0 if z == -math.inf else normalised(z, cfg)
    return out


def reference_agent_features(cfg: TerraShiftConfig, sim: Simulator, env: int) -> np.ndarray:
    def state(name):
        return sim.view(name)[env].double().numpy()

    p, v, s = state("agent_position"), state("agent_velocity"), state("agent_sigma")
    span = cfg.sigma_max - cfg.sigma_min
    return np.column_stack(
        [
            2 * p[:, 0] / cfg.grid_size - 1,
            2 * p[:, 1] / cfg.grid_size - 1,
            state("agent_angle") / math.pi - 1,
            state("agent_amplitude") / cfg.max_amplitude,
            2 * (s[:, 0] - cfg.sigma_min) / span - 1,
            2 * (s[:, 1] - cfg.sigma_min) / span - 1,
            v[:, 0] / cfg.max_velocity,
            v[:, 1] / cfg.max_velocity,
            state("agent_angular_velocity") / cfg.max_angular_velocity,
        ]
    )


def reference_object_features(cfg: TerraShiftConfig, sim: Simulator, env: int) -> np.ndarray:
    half = 0.5 * cfg.platform_size
    heights = sim.view("column_height")[env].double().numpy()
    goal_cell = sim.view("goal_cell")[env].numpy()
    centres = column_centres(cfg)
    vmax = cfg.max_object_speed
    rows = []
    for j in range(cfg.num_objects):
        if not sim.view("sphere_active")[env, j]:
            rows.append(np.zeros(9))
            continue
        p = sim.view("sphere_position")[env, j].double().numpy()
        v = sim.view("sphere_velocity")[env, j].double().numpy()
        gx, gy = goal_cell[j % cfg.num_goals]
        goal_z = cfg.column_rest_top + heights[gy, gx] + cfg.sphere_radius
        rows.append(
            [
                p[0] / half,
                p[1] / half,
                normalised(p[2], cfg),
                centres[gx] / half,
                centres[gy] / half,
                normalised(goal_z, cfg),
                *(np.clip(v, -vmax, vmax) / vmax),
            ]
        )
    return np.asarray(rows, dtype=np.float64)


def assert_observation_matches_state(sim: Simulator, env: int) -> None:
    """Every observation of ``env`` equals the reference computed from its current state."""
    cfg = sim.config
    expected = reference_heightmap(
        cfg,
        sim.view("column_height")[env].double().numpy(),
        sim.view("sphere_position")[env].double().numpy(),
        sim.view("sphere_active")[env].numpy(),
    )
    np.testing.assert_allclose(sim.view("heightmap")[env, 0].numpy(), expected, atol=HEIGHTMAP_TOL)
    np.testing.assert_allclose(
        sim.view("object_features")[env].numpy(),
        reference_object_features(cfg, sim, env),
        atol=FEATURE_TOL,
    )
    np.testing.assert_array_equal(
        sim.view("object_mask")[env].numpy(), sim.view("sphere_active")[env].numpy() != 0
    )
    np.testing.assert_allclose(
        sim.view("agent_features")[env].numpy(),
        reference_agent_features(cfg, sim, env),
        atol=FEATURE_TOL,
    )


def pose_scene(sim: Simulator, rng: np.random.Generator) -> None:
    """Random column heights and a few spheres: one above the tallest column tops, one sunk
    between them, one above the heightmap's range, and one inactive slot."""
    cfg = sim.config
    n, g = sim.num_envs, cfg.grid_size
    heights = torch.as_tensor(
        rng.uniform(-cfg.max_column_height, cfg.max_column_height, (n, g, g)), dtype=torch.float32
    )
    sim.view("column_height").copy_(heights)
    sim.view("column_height_prev").copy_(heights)
    xy = rng.uniform(-0.4, 0.4, (n, 4, 2))
    z = np.broadcast_to([0.22, 0.13, 0.37, 0.25], (n, 4))
    positions = np.concatenate([xy, z[..., None]], axis=-1)
    sim.view("sphere_position").copy_(torch.as_tensor(positions, dtype=torch.float32))
    sim.view("sphere_velocity").copy_(
        torch.as_tensor(rng.uniform(-2.0, 2.0, (n, 4, 3)), dtype=torch.float32)
    )
    sim.view("sphere_active").copy_(torch.tensor([1, 1, 1, 0]).expand(n, 4))


# --- heightmap ----------------------------------------------------------------------------


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_heightmap_matches_ray_cast_reference(shape):
    sim = make_sim(column_shape=shape, num_objects=4)
    pose_scene(sim, np.random.default_rng(SEED))
    sim.observe()
    cfg = sim.config
    heightmap = sim.view("heightmap")
    for env in range(sim.num_envs):
        expected = reference_heightmap(
            cfg,
            sim.view("column_height")[env].double().numpy(),
            sim.view("sphere_position")[env].double().numpy(),
            sim.view("sphere_active")[env].numpy(),
        )
        np.testing.assert_allclose(heightmap[env, 0].numpy(), expected, atol=HEIGHTMAP_TOL)
    # the scene exercises what it is meant to: spheres on the map, the clip at the top, and
    # (for domes) rays that fall between the columns
    values = heightmap.numpy()
    assert (values == 1.0).any()
    assert (values > normalised(cfg.column_rest_top + cfg.max_column_height, cfg)).any()
    if shape == "ellipsoid":
        assert (values == -1.0).any()
    else:
        assert (values > -1.0).all()


def test_inactive_sphere_is_invisible_and_active_one_is_seen():
    sim = make_sim(column_shape="box", num_objects=2, num_goals=1)
    cfg = sim.config
    sim.view("column_height").zero_()
    sim.view("sphere_position").copy_(torch.tensor([[0.2, -0.1, 0.3], [-0.2, 0.1, 0.3]]))
    sim.view("sphere_active").copy_(torch.tensor([1, 0]))
    sim.observe()
    coords = lattice(cfg)
    heightmap = sim.view("heightmap")[0, 0]
    # the ray nearest each sphere's centre: rows are y, columns are x
    ry, rx = np.abs(coords + 0.1).argmin(), np.abs(coords - 0.2).argmin()
    d2 = (coords[rx] - 0.2) ** 2 + (coords[ry] + 0.1) ** 2
    top = 0.3 + math.sqrt(cfg.sphere_radius**2 - d2)
    assert heightmap[ry, rx].item() == pytest.approx(normalised(top, cfg), abs=HEIGHTMAP_TOL)
    ry, rx = np.abs(coords - 0.1).argmin(), np.abs(coords + 0.2).argmin()
    assert heightmap[ry, rx].item() == pytest.approx(
        normalised(cfg.column_rest_top, cfg), abs=HEIGHTMAP_TOL
    )


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_raised_column_appears_at_its_row_and_column(shape):
    # the original transposed the heightmap against the column grid: here row = y, col = x
    sim = make_sim(column_shape=shape, num_envs=1)
    cfg = sim.config
    sim.view("sphere_active").zero_()
    heights = torch.full((cfg.grid_size, cfg.grid_size), -cfg.max_column_height)
    iy, ix = 3, 10
    heights[iy, ix] = cfg.max_column_height
    sim.view("column_height").copy_(heights)
    sim.observe()
    heightmap = sim.view("heightmap")[0, 0].numpy()
    low = normalised(cfg.column_rest_top - cfg.max_column_height, cfg)
    raised = np.argwhere(heightmap > low + 0.05)
    assert len(raised) > 0
    cell = np.floor((lattice(cfg) + 0.5) / cfg.cell_size).clip(0, cfg.grid_size - 1)
    # every raised ray lies over (or, for the smooth surface, next to) the raised column
    reach = 1 if shape == "smooth" else 0
    assert (np.abs(cell[raised[:, 0]] - iy) <= reach).all(), raised
    assert (np.abs(cell[raised[:, 1]] - ix) <= reach).all(), raised
    # and the peak sits on the raised column
    ry, rx = np.unravel_index(heightmap.argmax(), heightmap.shape)
    assert (cell[ry], cell[rx]) == (iy, ix)
    assert sim.view("column_height")[0, iy, ix] > sim.view("column_height")[0, ix, iy]


# --- features -----------------------------------------------------------------------------


def test_agent_features_are_normalised_state():
    sim = make_sim(num_envs=2, num_agents=5)
    cfg = sim.config
    rng = np.random.default_rng(SEED)
    n, k = sim.num_envs, cfg.num_agents
    values = {
        "agent_position": rng.uniform(0.0, cfg.grid_size, (n, k, 2)),
        "agent_velocity": rng.uniform(-cfg.max_velocity, cfg.max_velocity, (n, k, 2)),
        "agent_angle": rng.uniform(0.0, 2 * math.pi, (n, k)),
        "agent_angular_velocity": rng.uniform(
            -cfg.max_angular_velocity, cfg.max_angular_velocity, (n, k)
        ),
        "agent_amplitude": rng.uniform(-cfg.max_amplitude, cfg.max_amplitude, (n, k)),
        "agent_sigma": rng.uniform(cfg.sigma_min, cfg.sigma_max, (n, k, 2)),
    }
    for name, value in values.items():
        sim.view(name).copy_(torch.as_tensor(value, dtype=torch.float32))
    sim.observe()
    features = sim.view("agent_features").numpy()
    for env in range(n):
        np.testing.assert_allclose(
            features[env], reference_agent_features(cfg, sim, env), atol=FEATURE_TOL
        )
    assert (np.abs(features) <= 1.0 + FEATURE_TOL).all()


def test_agent_features_at_the_ends_of_their_ranges():
    sim = make_sim(num_envs=1, num_agents=2)
    cfg = sim.config
    sim.view("agent_position").copy_(torch.tensor([[[0.0, 0.0], [7.5, 7.5]]]))
    sim.view("agent_velocity").copy_(torch.tensor([[[-1.0, 1.0], [0.5, 0.0]]]) * cfg.max_velocity)
    sim.view("agent_angle").copy_(torch.tensor([[0.0, math.pi]]))
    sim.view("agent_angular_velocity").copy_(torch.tensor([[-1.0, 0.0]]) * cfg.max_angular_velocity)
    sim.view("agent_amplitude").copy_(torch.tensor([[1.0, -0.5]]) * cfg.max_amplitude)
    sim.view("agent_sigma").copy_(
        torch.tensor(
            [[[cfg.sigma_min, cfg.sigma_max], [0.5 * (cfg.sigma_min + cfg.sigma_max)] * 2]]
        )
    )
    sim.observe()
    expected = [
        [-1.0, -1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0],
        [0.0, 0.0, 0.0, -0.5, 0.0, 0.0, 0.5, 0.0, 0.0],
    ]
    np.testing.assert_allclose(sim.view("agent_features")[0].numpy(), expected, atol=FEATURE_TOL)


def test_object_features_are_normalised_and_zero_where_inactive():
    # four slots, two goals: slots 2 and 3 share the goals of slots 0 and 1
    sim = make_sim(num_envs=2, num_objects=4, num_goals=2)
    cfg = sim.config
    rng = np.random.default_rng(SEED)
    pose_scene(sim, rng)
    sim.view("sphere_active").copy_(torch.tensor([[1, 0, 1, 1], [0, 1, 1, 0]]))
    sim.view("goal_cell").copy_(torch.tensor([[[3, 11], [12, 5]], [[2, 2], [9, 4]]]))
    sim.view("object_features").fill_(7.0)  # stale values must not survive in empty slots
    sim.view("object_mask").fill_(True)
    sim.observe()
    features = sim.view("object_features").numpy()
    for env in range(sim.num_envs):
        np.testing.assert_allclose(
            features[env], reference_object_features(cfg, sim, env), atol=FEATURE_TOL
        )
    np.testing.assert_array_equal(
        sim.view("object_mask").numpy(), [[True, False, True, True], [False, True, True, False]]
    )
    assert (features[0, 1] == 0).all() and (features[1, [0, 3]] == 0).all()
    # velocities of +-2 m/s saturate at +-1; goal features follow goal j mod num_goals
    assert (np.abs(features[..., 6:]) <= 1.0).all()
    assert (np.abs(features[..., 6:]) == 1.0).any()
    goal_1 = [(12.5 / 15 - 0.5) / 0.5, (5.5 / 15 - 0.5) / 0.5]  # cell (ix, iy) = (12, 5)
    np.testing.assert_allclose(features[0, 3, 3:5], goal_1, atol=FEATURE_TOL)
    np.testing.assert_allclose(features[0, 2, 3:6], features[0, 0, 3:6], atol=0.0)


def test_object_goal_height_rides_its_column():
    sim = make_sim(num_envs=1, num_objects=1, num_goals=1)
    cfg = sim.config
    sim.view("sphere_active").fill_(1)
    sim.view("sphere_position").copy_(torch.tensor([[[0.1, 0.2, 0.25]]]))
    sim.view("goal_cell").copy_(torch.tensor([[[6, 9]]]))
    zs = []
    for h in (-cfg.max_column_height, 0.0, cfg.max_column_height):
        sim.view("column_height").zero_()
        sim.view("column_height")[0, 9, 6] = h
        sim.observe()
        zs.append(sim.view("object_features")[0, 0, 5].item())
        expected = normalised(cfg.column_rest_top + h + cfg.sphere_radius, cfg)
        assert zs[-1] == pytest.approx(expected, abs=FEATURE_TOL)
    assert zs[0] < zs[1] < zs[2]


# --- observations after resets ------------------------------------------------------------


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_first_observation_after_reset_describes_the_new_episode(shape):
    sim = make_sim(num_envs=2, column_shape=shape)
    sim.reset()
    heightmap = sim.view("heightmap")
    for env in range(sim.num_envs):
        assert not torch.all(heightmap[env] == -1.0)
        assert not torch.all(heightmap[env] == 0.0)
        assert sim.view("object_mask")[env, 0]  # slot 0 spawns with the reset
        assert not sim.view("object_mask")[env, 1:].any()  # the others are staggered
        p = sim.view("sphere_position")[env, 0]
        np.testing.assert_allclose(
            sim.view("object_features")[env, 0, :2].numpy(), (p[:2] / 0.5).numpy(), atol=1e-6
        )
        assert_observation_matches_state(sim, env)
    # the agent features of a fresh episode are not the zeros of an unobserved state
    assert sim.view("agent_features").abs().sum() > 0
    # and the first step keeps them consistent
    sim.step(torch.zeros(sim.action_shape))
    for env in range(sim.num_envs):
        assert_observation_matches_state(sim, env)


def test_partial_reset_refreshes_only_the_reset_envs():
    sim = make_sim(num_envs=3)
    sim.reset()
    rng = np.random.default_rng(SEED)
    for _ in range(20):
        sim.step(torch.as_tensor(rng.uniform(-1, 1, sim.action_shape), dtype=torch.float32))
    names = ("heightmap", "object_features", "object_mask", "agent_features", "agent_position")
    before = {name: sim.view(name).clone() for name in names}
    mask = torch.tensor([True, False, True])
    sim.reset(mask)
    for name, old in before.items():
        new = sim.view(name)
        torch.testing.assert_close(new[~mask], old[~mask], rtol=0.0, atol=0.0, msg=name)
        assert not torch.equal(new[mask], old[mask]), name
    np.testing.assert_array_equal(sim.view("step_count").numpy(), [0, 20, 0])
    for env in range(sim.num_envs):
        assert_observation_matches_state(sim, env)
    for env in (0, 2):
        assert sim.view("object_mask")[env, 0] and not sim.view("object_mask")[env, 1:].any()


# --- scene sizes --------------------------------------------------------------------------


def test_the_large_scene_observes_eight_spheres_and_every_agent():
    """45 x 45 columns, 24 agents, 8 spheres and goals: every one of the 8 object slots comes
    into play and every observation still equals the reference."""
    sim = Simulator(TerraShiftConfig.preset("large"), num_envs=2, seed=SEED)
    sim.reset()
    seen = torch.zeros(2, 8, dtype=torch.bool)
    for _ in range(60):  # the spawns are staggered by respawn_delay: 8 x 0.2 s < 60 decisions
        sim.step(torch.zeros(2, 24, 6))
        seen |= sim.view("object_mask")
    assert sim.view("object_features").shape == (2, 8, 9)
    assert sim.view("agent_features").shape == (2, 24, 9)
    assert seen.all()
    for env in range(sim.num_envs):
        assert_observation_matches_state(sim, env)
