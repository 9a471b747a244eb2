"""Reward terms and episode events against hand computations.

Single ticks launch ``events.tick_events`` directly on a posed state (nothing moves); the
sum over the action repeat, termination, truncation and respawns run through ``step``.
"""

import math

import numpy as np
import pytest
import torch

from terrashift_rl.sim import Simulator, TerraShiftConfig

SEED = 0
REWARD_TOL = 1e-5
"""Absolute tolerance on rewards: float32 distances (about 3e-8 m) times distance_scale."""
PARKED = 1000
"""Spawn timer of slots kept empty for a test: far beyond any test's length."""
FAR = torch.tensor([0.0, 0.0, 0.3])
"""A place in the air above the platform centre, in bounds and far from every goal used."""


def make_sim(*, num_envs: int = 1, **overrides) -> Simulator:
    settings = {"num_objects": 3, "num_goals": 3, "action_repeat": 1, **overrides}
    return Simulator(TerraShiftConfig(**settings), num_envs=num_envs, seed=SEED)


def goal_xyz(cfg: TerraShiftConfig, ix: int, iy: int, height: float = 0.0) -> torch.Tensor:
    """A goal rides one sphere radius above the top of its column (ix, iy)."""
    half = 0.5 * cfg.platform_size
    return torch.tensor(
        [
            (ix + 0.5) * cfg.cell_size - half,
            (iy + 0.5) * cfg.cell_size - half,
            cfg.column_rest_top + height + cfg.sphere_radius,
        ]
    )


def pose(sim: Simulator, spheres: list[dict], *, goal_cells=((2, 3), (11, 4), (5, 12))) -> None:
    """Flat columns, goals on ``goal_cells`` and the given spheres in slots 0, 1, ... of every
    environment; each sphere is a dict with ``position`` and optional ``velocity`` and
    ``previous`` (distance to its goal at the last tick). Other slots stay empty."""
    cfg = sim.config
    for name in ("column_height", "column_height_prev", "reward"):
        sim.view(name).zero_()
    sim.view("goal_cell").copy_(torch.tensor(goal_cells[: cfg.num_goals], dtype=torch.int32))
    active, timer = sim.view("sphere_active"), sim.view("spawn_timer")
    active.zero_()
    timer.fill_(PARKED)
    for j, sphere in enumerate(spheres):
        position = torch.as_tensor(sphere["position"], dtype=torch.float32)
        sim.view("sphere_position")[:, j] = position
        sim.view("sphere_velocity")[:, j] = torch.as_tensor(
            sphere.get("velocity", [0.0, 0.0, 0.0]), dtype=torch.float32
        )
        sim.view("sphere_angular_velocity")[:, j] = 0.0
        goal = goal_xyz(cfg, *goal_cells[j % cfg.num_goals])
        previous = sphere.get("previous", (position - goal).norm().item())
        sim.view("goal_distance")[:, j] = previous
        active[:, j] = 1
        timer[:, j] = 0


def tick(sim: Simulator) -> float:
    """One physics tick of goals, out-of-bounds, respawns and reward; returns env 0's reward."""
    sim.view("reward").zero_()
    sim.events_tick()
    return sim.view("reward")[0].item()


def team(cfg: TerraShiftConfig, *object_terms: float) -> float:
    return (cfg.time_penalty + sum(object_terms)) / cfg.reward_normalizer


def moving(speed: float = 0.5) -> list[float]:
    """Straight up, fast enough to escape the slow penalty (alignment is off by default)."""
    return [0.0, 0.0, speed]


# --- terms of one tick --------------------------------------------------------------------


def test_time_penalty_alone_without_active_spheres():
    sim = make_sim(time_penalty=-0.3, reward_normalizer=2.5)
    pose(sim, [])
    assert tick(sim) == pytest.approx(-0.3 / 2.5, abs=REWARD_TOL)
    assert not sim.view("sphere_active").any()


@pytest.mark.parametrize("respawn", [True, False])
def test_goal_pays_once_and_resolves_the_sphere(respawn):
    sim = make_sim(respawn=respawn)
    cfg = sim.config
    goal = goal_xyz(cfg, 2, 3)
    # 9 cm from the goal (inside the 10 cm radius), slow, and with a large distance gain that
    # must not be paid on top of the bonus
    pose(sim, [{"position": goal + torch.tensor([0.0, 0.06, 0.0671]), "previous": 0.5}])
    assert tick(sim) == pytest.approx(team(cfg, cfg.goal_reward), abs=REWARD_TOL)
    assert sim.view("sphere_active")[0, 0] == 0
    assert sim.view("episode_goals")[0] == 1
    assert sim.view("episode_out_of_bounds")[0] == 0
    assert sim.view("spawn_timer")[0, 0] == (cfg.respawn_ticks if respawn else -1)
    # the next tick pays only the time penalty: the bonus is paid once
    assert tick(sim) == pytest.approx(team(cfg), abs=REWARD_TOL)
    assert sim.view("episode_goals")[0] == 1
    assert sim.view("spawn_timer")[0, 0] == (cfg.respawn_ticks - 1 if respawn else -1)


def test_sphere_just_outside_the_goal_radius_is_not_resolved():
    sim = make_sim()
    cfg = sim.config
    goal = goal_xyz(cfg, 2, 3)
    pose(sim, [{"position": goal + torch.tensor([0.0, 0.06, 0.0805])}])  # 10.04 cm away
    assert tick(sim) == pytest.approx(team(cfg, cfg.slow_penalty), abs=REWARD_TOL)
    assert sim.view("sphere_active")[0, 0] == 1
    assert sim.view("episode_goals")[0] == 0


@pytest.mark.parametrize("height", [-0.06, 0.06])
def test_goal_rides_its_column(height):
    sim = make_sim()
    cfg = sim.config
    # the sphere sits where the goal is when the column is raised; lowering it puts the goal
    # 12 cm below the sphere
    pose(sim, [{"position": goal_xyz(cfg, 2, 3, height=0.06), "velocity": moving()}])
    sim.view("column_height")[0, 3, 2] = height
    reached = height > 0
    tick(sim)
    assert sim.view("episode_goals")[0] == int(reached)
    assert sim.view("sphere_active")[0, 0] == int(not reached)


@pytest.mark.parametrize(
    "offset",
    [(0.495, 0.0, 0.0), (-0.495, 0.0, 0.0), (0.0, 0.495, 0.0), (0.0, -0.495, 0.0)],
    ids=["+x", "-x", "+y", "-y"],
)
@pytest.mark.parametrize("respawn", [True, False])
def test_out_of_bounds_sideways_is_penalised_once(offset, respawn):
    sim = make_sim(respawn=respawn)
    cfg = sim.config
    position = torch.tensor(offset) + torch.tensor([0.0, 0.0, 0.3])
    pose(sim, [{"position": position, "velocity": moving(), "previous": 0.0}])
    assert tick(sim) == pytest.approx(team(cfg, cfg.out_of_bounds_penalty), abs=REWARD_TOL)
    assert sim.view("sphere_active")[0, 0] == 0
    assert sim.view("episode_out_of_bounds")[0] == 1
    assert sim.view("episode_goals")[0] == 0
    assert sim.view("spawn_timer")[0, 0] == (cfg.respawn_ticks if respawn else -1)
    assert tick(sim) == pytest.approx(team(cfg), abs=REWARD_TOL)
    assert sim.view("episode_out_of_bounds")[0] == 1


@pytest.mark.parametrize(("z", "out"), [(-0.01, True), (0.41, True), (0.005, False), (0.39, False)])
def test_out_of_bounds_below_the_platform_and_above_the_ceiling(z, out):
    sim = make_sim()
    cfg = sim.config
    pose(sim, [{"position": [0.1, -0.1, z], "velocity": moving()}])
    expected = cfg.out_of_bounds_penalty if out else 0.0
    assert tick(sim) == pytest.approx(team(cfg, expected), abs=REWARD_TOL)
    assert sim.view("episode_out_of_bounds")[0] == int(out)
    assert sim.view("sphere_active")[0, 0] == int(not out)


@pytest.mark.parametrize("xy", [(0.485, 0.0), (-0.485, 0.3), (0.2, 0.485), (-0.3, -0.485)])
def test_inside_the_bounds_is_not_out(xy):
    sim = make_sim()
    cfg = sim.config
    pose(sim, [{"position": [*xy, 0.3], "velocity": moving()}])
    assert tick(sim) == pytest.approx(team(cfg), abs=REWARD_TOL)
    assert sim.view("sphere_active")[0, 0] == 1


@pytest.mark.parametrize(("gain", "paid"), [(0.01, 0.01), (0.5, 0.02), (-0.5, -0.02), (0.0, 0.0)])
def test_distance_improvement_is_scaled_and_clipped(gain, paid):
    sim = make_sim(distance_clip=0.02)
    cfg = sim.config
    goal = goal_xyz(cfg, 2, 3)
    position = FAR
    distance = (position - goal).norm().item()
    pose(sim, [{"position": position, "velocity": moving(), "previous": distance + gain}])
    assert tick(sim) == pytest.approx(team(cfg, cfg.distance_scale * paid), abs=REWARD_TOL)
    # the tick's distance becomes the next tick's reference
    assert sim.view("goal_distance")[0, 0].item() == pytest.approx(distance, abs=1e-6)
    assert tick(sim) == pytest.approx(team(cfg), abs=REWARD_TOL)


@pytest.mark.parametrize(
    ("speed", "slow"), [(0.0, True), (0.05, True), (0.099, True), (0.101, False), (0.5, False)]
)
def test_slow_penalty_below_the_slow_speed(speed, slow):
    sim = make_sim()
    cfg = sim.config
    direction = torch.tensor([3.0, -4.0, 12.0]) / 13.0
    pose(sim, [{"position": FAR, "velocity": speed * direction}])
    expected = cfg.slow_penalty if slow else 0.0
    assert tick(sim) == pytest.approx(team(cfg, expected), abs=REWARD_TOL)


def test_potential_shaping():
    sim = make_sim(potential_scale=0.5, potential_gamma=0.9, distance_scale=0.0)
    cfg = sim.config
    distance = (FAR - goal_xyz(cfg, 2, 3)).norm().item()
    previous = distance + 0.03
    pose(sim, [{"position": FAR, "velocity": moving(), "previous": previous}])
    expected = 0.5 * (previous - 0.9 * distance)
    assert tick(sim) == pytest.approx(team(cfg, expected), abs=REWARD_TOL)


@pytest.mark.parametrize("degrees", [0.0, 60.0, 90.0, 135.0, 180.0])
def test_velocity_alignment_is_the_cosine_to_the_goal(degrees):
    sim = make_sim(alignment_scale=0.7, distance_scale=0.0)
    cfg = sim.config
    to_goal = goal_xyz(cfg, 2, 3) - FAR
    along = to_goal / to_goal.norm()
    across = torch.linalg.cross(along, torch.tensor([0.0, 0.0, 1.0]))
    across = across / across.norm()
    angle = math.radians(degrees)
    velocity = 0.4 * (math.cos(angle) * along + math.sin(angle) * across)
    pose(sim, [{"position": FAR, "velocity": velocity}])
    assert tick(sim) == pytest.approx(team(cfg, 0.7 * math.cos(angle)), abs=REWARD_TOL)


def test_velocity_alignment_is_zero_at_rest():
    sim = make_sim(alignment_scale=0.7, slow_penalty=0.0)
    cfg = sim.config
    pose(sim, [{"position": FAR}])
    assert tick(sim) == pytest.approx(team(cfg), abs=REWARD_TOL)


def test_team_reward_sums_the_objects_and_divides_by_the_normalizer():
    sim = make_sim(num_envs=2, num_objects=4, num_goals=3, reward_normalizer=2.5)
    cfg = sim.config
    goal_0 = goal_xyz(cfg, 2, 3)
    distance_1 = (FAR - goal_xyz(cfg, 11, 4)).norm().item()
    pose(
        sim,
        [
            {"position": goal_0},  # goal
            {"position": FAR, "velocity": moving(), "previous": distance_1 + 0.004},  # +0.4
            {"position": [0.0, 0.6, 0.3]},  # out of bounds
            {"position": [0.2, 0.2, 0.3]},  # slow, and shares goal 0 (slot 3 mod 3 goals)
        ],
    )
    expected = team(
        cfg,
        cfg.goal_reward,
        cfg.distance_scale * 0.004,
        cfg.out_of_bounds_penalty,
        cfg.slow_penalty,
    )
    tick(sim)
    np.testing.assert_allclose(sim.view("reward").numpy(), [expected] * 2, atol=REWARD_TOL)
    np.testing.assert_array_equal(sim.view("sphere_active").numpy(), [[0, 1, 0, 1]] * 2)
    np.testing.assert_array_equal(sim.view("episode_goals").numpy(), [1, 1])
    np.testing.assert_array_equal(sim.view("episode_out_of_bounds").numpy(), [1, 1])


def cell_of(cfg: TerraShiftConfig, xy: torch.Tensor) -> torch.Tensor:
    """A point of the platform [m] in the wavelets' cell coordinates (column i at x = i)."""
    return (xy + 0.5 * cfg.platform_size) / cfg.cell_size - 0.5


def above_cell(cfg: TerraShiftConfig, cx: float, cy: float) -> torch.Tensor:
    """The point 0.3 m above cell coordinates (cx, cy) [m], as ``cell_of`` inverts."""
    xy = (torch.tensor([cx, cy]) + 0.5) * cfg.cell_size - 0.5 * cfg.platform_size
    return torch.tensor([*xy.tolist(), 0.3])


def approach_sim(
    *, gaps: list[float], cells: list[tuple[float, float]], per_sphere: bool = False, **overrides
):
    """A scene whose reward is one approach term alone at scale 0.3 (per wavelet, or with
    ``per_sphere`` per sphere), wavelets at ``cells`` and the term's gaps (one per wavelet or
    per sphere slot) known from the last tick."""
    term = "sphere_approach" if per_sphere else "approach"
    settings = {f"{term}_scale": 0.3, "distance_scale": 0.0, "slow_penalty": 0.0}
    sim = make_sim(num_agents=len(cells), **{**settings, **overrides})
    sim.view("agent_position").copy_(torch.tensor(cells))
    sim.view(f"{term}_gap").copy_(torch.tensor(gaps))
    return sim


def test_approach_pays_the_closing_on_the_nearest_sphere_beyond_the_radius():
    cfg = TerraShiftConfig()
    torch.testing.assert_close(cell_of(cfg, FAR[:2]), torch.tensor([7.0, 7.0]))
    cells = [
        (1.0, 7.0),  # 6 cells left of the first sphere: gap 3.5, 0.4 closer than last tick
        (7.0, 10.0),  # 2 cells above the second: inside the radius, gap 0, was 0.2
        (12.0, 8.0),  # 5 cells right of the second: gap 2.5, not known last tick
    ]
    sim = approach_sim(gaps=[3.9, 0.2, -1.0], cells=cells)
    pose(sim, [{"position": FAR}, {"position": above_cell(cfg, 7.0, 8.0)}])
    expected = team(cfg, 0.3 * (3.9 - 3.5) + 0.3 * (0.2 - 0.0))
    assert tick(sim) == pytest.approx(expected, abs=REWARD_TOL)
    np.testing.assert_allclose(sim.view("approach_gap")[0].numpy(), [3.5, 0.0, 2.5], atol=1e-5)


@pytest.mark.parametrize(("wrap", "gap"), [(True, 1.0), (False, 14.0)])
def test_approach_measures_the_short_way_round_a_wrapping_grid(wrap, gap):
    cfg = TerraShiftConfig()
    sphere = above_cell(cfg, 0.0, 7.0)  # a wavelet at x = 14 is one cell away, the short way
    sim = approach_sim(gaps=[gap + 0.25], cells=[(14.0, 7.0)], approach_radius=0.0, wrap_edges=wrap)
    pose(sim, [{"position": sphere}])
    assert tick(sim) == pytest.approx(team(cfg, 0.3 * 0.25), abs=REWARD_TOL)
    assert sim.view("approach_gap")[0, 0].item() == pytest.approx(gap, abs=1e-5)


def test_approach_pays_nothing_on_a_tick_that_resolves_a_sphere():
    cfg = TerraShiftConfig()
    sim = approach_sim(gaps=[9.0], cells=[(1.0, 7.0)])
    pose(sim, [{"position": FAR}, {"position": goal_xyz(cfg, 11, 4)}])  # the second scores
    assert tick(sim) == pytest.approx(team(cfg, cfg.goal_reward), abs=REWARD_TOL)
    assert sim.view("approach_gap")[0, 0].item() == pytest.approx(3.5, abs=1e-5)


def test_approach_is_unknown_without_spheres_and_after_a_reset():
    sim = approach_sim(gaps=[2.0], cells=[(1.0, 7.0)])
    pose(sim, [])
    assert tick(sim) == pytest.approx(team(sim.config), abs=REWARD_TOL)
    assert sim.view("approach_gap")[0, 0].item() == -1.0
    sim.view("approach_gap").fill_(2.0)
    sim.reset()
    assert sim.view("approach_gap").eq(-1.0).all()


def test_sphere_approach_pays_each_spheres_nearest_wavelet_closing_on_it():
    cfg = TerraShiftConfig()
    cells = [
        (7.0, 1.0),  # 6 cells below the first sphere (7, 7), 7 from the second
        (7.0, 12.0),  # 4 cells above the second sphere (7, 8), 5 from the first
    ]
    # first sphere: nearest wavelet 5 cells away, gap 2.5, 0.5 closer than last tick;
    # second: nearest 4 cells away, gap 1.5, 0.25 farther; third: spawns on this tick
    sim = approach_sim(gaps=[3.0, 1.25, -1.0], cells=cells, per_sphere=True)
    pose(sim, [{"position": FAR}, {"position": above_cell(cfg, 7.0, 8.0)}])
    sim.view("spawn_timer")[0, 2] = 1  # the third sphere enters play on this tick
    expected = team(cfg, 0.3 * (3.0 - 2.5) + 0.3 * (1.25 - 1.5))
    assert tick(sim) == pytest.approx(expected, abs=REWARD_TOL)
    assert sim.view("sphere_active")[0, 2].item() == 1
    gaps = sim.view("sphere_approach_gap")[0]
    np.testing.assert_allclose(gaps[:2].numpy(), [2.5, 1.5], atol=1e-5)
    assert gaps[2].item() >= 0.0  # known from now on


def test_sphere_approach_pays_a_wavelet_for_leaving_the_team_for_a_lone_sphere():
    # two wavelets at one sphere and a second sphere far from both: the per-wavelet term would
    # charge the wavelet that moves off towards the lone sphere, the per-sphere term pays it
    cfg = TerraShiftConfig()
    spheres = [{"position": FAR}, {"position": above_cell(cfg, 1.0, 1.0)}]
    cells = [(7.0, 7.0), (7.0, 7.0)]
    rewards = {}
    for cell in ((7.0, 7.0), (4.0, 4.0)):  # the second wavelet stays, or moves 3 cells diagonally
        sim = approach_sim(gaps=[-1.0, -1.0, -1.0], cells=cells, per_sphere=True)
        pose(sim, spheres)
        tick(sim)
        sim.view("agent_position")[0, 1] = torch.tensor(cell)
        rewards[cell] = tick(sim)
    left_alone = 6.0 * 2**0.5 - 2.5
    closer = 3.0 * 2**0.5 - 2.5
    assert rewards[(7.0, 7.0)] == pytest.approx(team(cfg), abs=REWARD_TOL)
    assert rewards[(4.0, 4.0)] == pytest.approx(team(cfg, 0.3 * (left_alone - closer)), abs=1e-4)


def test_sphere_approach_pays_nothing_for_a_sphere_resolved_and_forgets_it():
    cfg = TerraShiftConfig()
    sim = approach_sim(gaps=[9.0, 9.0, -1.0], cells=[(1.0, 7.0)], per_sphere=True)
    pose(sim, [{"position": FAR}, {"position": goal_xyz(cfg, 11, 4)}])  # the second scores
    expected = team(cfg, 0.3 * (9.0 - 3.5) + cfg.goal_reward)
    assert tick(sim) == pytest.approx(expected, abs=REWARD_TOL)
    np.testing.assert_allclose(sim.view("sphere_approach_gap")[0].numpy(), [3.5, -1, -1], atol=1e-5)
    sim.view("sphere_approach_gap").fill_(2.0)
    sim.reset()
    assert sim.view("sphere_approach_gap").eq(-1.0).all()


def test_approach_sums_over_a_decision_to_the_gap_it_closed():
    # a wavelet driven towards a still sphere for several decisions: each decision's reward is
    # the scale times the gap closed over it, measured from the positions alone
    sim = make_sim(
        action_repeat=2,
        approach_scale=0.5,
        approach_radius=1.0,
        distance_scale=0.0,
        slow_penalty=0.0,
        time_penalty=0.0,
        gravity=0.0,
        num_agents=1,
    )
    cfg = sim.config
    sim.reset()
    make_inert(sim)
    sim.view("agent_position").copy_(torch.tensor([[[2.0, 7.0]]]))
    pose(sim, [{"position": FAR}])
    sphere = cell_of(cfg, FAR[:2])
    action = torch.zeros(sim.action_shape)
    action[..., 0] = 1.0  # accelerate along +x, towards the sphere

    def gap() -> float:
        offset = sphere - sim.view("agent_position")[0, 0]
        return max(offset.norm().item() - 1.0, 0.0)

    sim.step(action)  # the first tick only learns the gap
    for _ in range(6):
        before = gap()
        sim.step(action)
        closed = before - gap()
        assert sim.view("reward")[0].item() == pytest.approx(
            0.5 * closed / cfg.reward_normalizer, abs=REWARD_TOL
        )
    assert closed > 0.05  # the wavelet moves fast enough to matter


# --- whole decisions ----------------------------------------------------------------------


def make_inert(sim: Simulator) -> None:
    """Flat, still columns: zero amplitudes and rates, so zero actions keep the field flat."""
    for name in ("agent_amplitude", "agent_velocity", "agent_angular_velocity"):
        sim.view(name).zero_()
    sim.view("column_height").zero_()
    sim.view("column_height_prev").zero_()


def test_reward_is_summed_over_the_action_repeat():
    # no gravity and no damping: the sphere flies in a straight line, clear of the columns
    sim = make_sim(action_repeat=3, gravity=0.0, linear_damping=0.0)
    cfg = sim.config
    sim.reset()
    make_inert(sim)
    start, velocity = torch.tensor([-0.2, 0.1, 0.3]), torch.tensor([-0.3, -0.8, 0.0])
    pose(sim, [{"position": start, "velocity": velocity}])
    goal = goal_xyz(cfg, 2, 3)

    def distance_after(ticks: int) -> float:
        return (start + ticks * cfg.tick_dt * velocity - goal).norm().item()

    zero = torch.zeros(sim.action_shape)
    for decision in range(2):
        sim.step(zero)
        first = decision * cfg.action_repeat
        expected = sum(
            team(cfg, cfg.distance_scale * (distance_after(t) - distance_after(t + 1)))
            for t in range(first, first + cfg.action_repeat)
        )
        assert sim.view("reward")[0].item() == pytest.approx(expected, abs=REWARD_TOL)
        assert sim.view("goal_distance")[0, 0].item() == pytest.approx(
            distance_after(first + cfg.action_repeat), abs=1e-6
        )
    assert expected > 0.5  # the sphere closes on its goal fast enough to matter


def test_evaluation_terminates_once_every_sphere_is_resolved():
    sim = make_sim(respawn=False, num_objects=2, num_goals=2, gravity=0.0)
    cfg = sim.config
    sim.reset()
    make_inert(sim)
    zero = torch.zeros(sim.action_shape)
    active, timer = sim.view("sphere_active"), sim.view("spawn_timer")
    assert active[0].tolist() == [1, 0] and timer[0, 1] == cfg.respawn_ticks
    # sphere 0 reaches its goal at once; sphere 1 is still waiting to spawn
    cell = sim.view("goal_cell")[0, 0].tolist()
    sim.view("sphere_position")[0, 0] = goal_xyz(cfg, *cell)
    sim.view("sphere_velocity")[0, 0] = 0.0
    sim.step(zero)
    assert active[0, 0] == 0 and timer[0, 0] == -1
    assert sim.view("episode_goals")[0] == 1
    assert not sim.view("terminated")[0]
    # sphere 1 spawns respawn_ticks after the reset, then leaves over the edge
    for _ in range(cfg.respawn_ticks - 1):
        assert not sim.view("terminated")[0]
        sim.step(zero)
    assert active[0, 1] == 1
    assert not sim.view("terminated")[0]
    sim.view("sphere_position")[0, 1] = torch.tensor([0.6, 0.0, 0.3])
    sim.step(zero)
    assert active[0].tolist() == [0, 0] and timer[0].tolist() == [-1, -1]
    assert sim.view("episode_out_of_bounds")[0] == 1
    assert sim.view("terminated")[0]
    assert not sim.view("truncated")[0]
    # nothing respawns in evaluation: the episode stays over
    for _ in range(cfg.respawn_ticks + 1):
        sim.step(zero)
        assert sim.view("terminated")[0] and not active[0].any()


def test_training_never_terminates_and_truncates_at_the_step_limit():
    sim = make_sim(num_objects=1, num_goals=1, max_episode_steps=5, gravity=0.0)
    cfg = sim.config
    sim.reset()
    make_inert(sim)
    zero = torch.zeros(sim.action_shape)
    # every sphere resolved: in evaluation this would end the episode, in training it must not
    sim.view("sphere_position")[0, 0] = goal_xyz(cfg, *sim.view("goal_cell")[0, 0].tolist())
    for step in range(1, cfg.max_episode_steps + 1):
        sim.step(zero)
        assert sim.view("step_count")[0] == step
        assert not sim.view("terminated")[0]
        assert bool(sim.view("truncated")[0]) == (step == cfg.max_episode_steps)
    assert sim.view("episode_goals")[0] == 1
    sim.reset()
    assert not sim.view("truncated")[0] and sim.view("step_count")[0] == 0
    assert sim.view("episode_goals")[0] == 0


@pytest.mark.parametrize(
    ("fraction", "respawning"),
    [(1.0, [1, 1, 1, 1, 1]), (0.5, [0, 1, 0, 1, 0]), (0.4, [0, 0, 1, 0, 1]), (0.0, [0] * 5)],
)
def test_respawn_fraction_picks_the_environments_that_respawn(fraction, respawning):
    sim = make_sim(num_envs=5, num_objects=1, num_goals=1, respawn_fraction=fraction, gravity=0.0)
    sim.reset()
    make_inert(sim)
    zero = torch.zeros(sim.action_shape)
    for e in range(sim.num_envs):  # every sphere on its goal: resolved on the first tick
        sim.view("sphere_position")[e, 0] = goal_xyz(sim.config, *sim.view("goal_cell")[e, 0])
    sim.step(zero)
    assert sim.view("episode_goals").tolist() == [1] * 5
    timer = sim.view("spawn_timer")[:, 0].tolist()
    assert timer == [sim.config.respawn_ticks if r else -1 for r in respawning]
    # the others run as in evaluation mode: their episodes end with their last sphere
    assert sim.view("terminated").tolist() == [not r for r in respawning]


@pytest.mark.parametrize("action_repeat", [1, 2])
def test_resolved_sphere_respawns_after_the_respawn_delay(action_repeat):
    sim = make_sim(
        num_objects=1, num_goals=1, action_repeat=action_repeat, respawn_delay=0.1, gravity=0.0
    )
    cfg = sim.config
    assert cfg.respawn_ticks == 6
    sim.reset()
    make_inert(sim)
    zero = torch.zeros(sim.action_shape)
    cell = sim.view("goal_cell")[0, 0].tolist()
    goal = goal_xyz(cfg, *cell)
    sim.view("sphere_position")[0, 0] = goal  # resolved on the first tick
    ticks = 0
    history = []
    while ticks < cfg.respawn_ticks + 1:
        sim.step(zero)
        ticks += cfg.action_repeat
        history.append((ticks, int(sim.view("sphere_active")[0, 0])))
    # inactive while fewer than respawn_ticks ticks have passed since the event (tick 1)
    for after, active in history:
        assert active == int(after - 1 >= cfg.respawn_ticks), history
    # respawned at rest above the columns, away from its goal, with a fresh goal distance
    position = sim.view("sphere_position")[0, 0]
    assert (position[:2] - goal[:2]).norm() >= 2 * cfg.goal_radius - 1e-6
    assert position[2] > cfg.column_rest_top + cfg.sphere_radius
    assert sim.view("goal_distance")[0, 0].item() == pytest.approx(
        (position - goal).norm().item(), abs=1e-6
    )
    assert sim.view("episode_goals")[0] == 1
