"""Baseline policies: action shapes and ranges, and the heuristic's steering on posed scenes."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.envs.baselines import RandomPolicy, ScriptedHeuristicPolicy, ZeroPolicy
from terrashift_rl.sim import ACTUATORS, TerraShiftConfig
from terrashift_rl.training.evaluation import evaluate

CFG = TerraShiftConfig(max_episode_steps=64)
G = CFG.grid_size
VX, VY, OMEGA, AMP, SX, SY = range(6)


def observation_td(batch: tuple[int, ...], k: int = 8, m: int = 4) -> TensorDict:
    return TensorDict(
        {
            (GROUP, "observation"): torch.zeros(*batch, k, 9),
            "objects": torch.zeros(*batch, m, 9),
            "objects_mask": torch.ones(*batch, m, dtype=torch.bool),
        },
        batch_size=batch,
    )


def cell_to_metres(cell: float, config: TerraShiftConfig = CFG) -> float:
    """Centre of column ``cell`` [m]."""
    return (cell + 0.5) * config.cell_size - 0.5 * config.platform_size


def posed_scene(
    agent_cells: list[tuple[float, float]],
    spheres: list[tuple[float, float] | None],
    goals: list[tuple[float, float]],
    config: TerraShiftConfig,
) -> TensorDict:
    """One environment: wavelets at rest at ``agent_cells`` (amplitude 0, width 1 cell), spheres
    at rest at the given cells (None: empty slot), goals at the given cells."""
    k, m = len(agent_cells), len(spheres)
    agents = torch.zeros(1, k, 9)
    for i, (x, y) in enumerate(agent_cells):
        agents[0, i, 0] = 2 * x / config.grid_size - 1
        agents[0, i, 1] = 2 * y / config.grid_size - 1
    sigma = 2 * (1.0 - config.sigma_min) / (config.sigma_max - config.sigma_min) - 1
    agents[0, :, 4:6] = sigma
    objects = torch.zeros(1, m, 9)
    mask = torch.zeros(1, m, dtype=torch.bool)
    half = 0.5 * config.platform_size
    for j, (sphere, goal) in enumerate(zip(spheres, goals, strict=True)):
        if sphere is None:
            continue
        mask[0, j] = True
        objects[0, j, 0] = cell_to_metres(sphere[0], config) / half
        objects[0, j, 1] = cell_to_metres(sphere[1], config) / half
        objects[0, j, 3] = cell_to_metres(goal[0], config) / half
        objects[0, j, 4] = cell_to_metres(goal[1], config) / half
    return TensorDict(
        {(GROUP, "observation"): agents, "objects": objects, "objects_mask": mask},
        batch_size=[1],
    )


def one_object_config(num_agents: int = 1, num_objects: int = 1) -> TerraShiftConfig:
    return TerraShiftConfig(num_agents=num_agents, num_objects=num_objects, num_goals=1)


@pytest.mark.parametrize("batch", [(3,), (2, 5), ()])
@pytest.mark.parametrize(
    "make", [lambda: RandomPolicy(seed=0), ZeroPolicy, lambda: ScriptedHeuristicPolicy(CFG)]
)
def test_actions_have_the_action_shape_and_range(make, batch):
    td = observation_td(batch)
    td["objects"].uniform_(-0.9, 0.9)
    td[GROUP, "observation"].uniform_(-1, 1)
    action = make()(td)[GROUP, "action"]
    assert action.shape == (*batch, 8, 6)
    assert action.dtype == torch.float32
    assert torch.isfinite(action).all()
    assert action.abs().max() <= 1.0


@pytest.mark.parametrize(
    "make", [lambda: RandomPolicy(seed=0), ZeroPolicy, lambda: ScriptedHeuristicPolicy(CFG)]
)
def test_policies_drive_a_real_environment(make):
    env = TerraShiftEnv(CFG, num_envs=3, seed=0)
    data = env.rollout(5, make())
    assert data[GROUP, "action"].shape == (3, 5, 8, 6)
    assert data[GROUP, "action"].abs().max() <= 1.0
    # a batch of time steps is a batch too
    frames = make()(data.exclude((GROUP, "action")))
    assert frames[GROUP, "action"].shape == (3, 5, 8, 6)


def test_random_policy_is_uniform_and_reproducible():
    td = observation_td((64,))
    a = RandomPolicy(seed=1)(td.clone())[GROUP, "action"]
    b = RandomPolicy(seed=1)(td.clone())[GROUP, "action"]
    c = RandomPolicy(seed=2)(td.clone())[GROUP, "action"]
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    policy = RandomPolicy(seed=1)
    policy(td)
    assert not torch.equal(policy(td)[GROUP, "action"], a)  # the stream advances
    assert a.min() >= -1 and a.max() <= 1
    assert abs(a.mean().item()) < 0.05  # 3072 draws: U[-1, 1] has mean 0, sd 0.58 / sqrt(n)
    assert a.min() < -0.99 and a.max() > 0.99


def test_zero_policy_is_all_zero():
    action = ZeroPolicy()(observation_td((4,)))[GROUP, "action"]
    assert action.shape == (4, 8, 6) and not action.any()


def test_heuristic_goes_behind_the_sphere_away_from_its_goal():
    cfg = one_object_config()
    sphere, goal = (7.0, 7.0), (12.0, 7.0)  # goal along +x: target is 2 cells left, x = 5
    policy = ScriptedHeuristicPolicy(cfg)
    left = policy(posed_scene([(3.0, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    right = policy(posed_scene([(10.0, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert left[VX] > 0.5 and abs(left[VY]) < 1e-5
    assert right[VX] < -0.5 and abs(right[VY]) < 1e-5
    # the same along y, goal along -y: the target is above the sphere (y = 9)
    goal = (7.0, 2.0)
    below = policy(posed_scene([(7.0, 5.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert below[VY] > 0.5 and abs(below[VX]) < 1e-5


def test_heuristic_steers_across_the_wrapped_edge():
    cfg = one_object_config()
    # sphere at cell 3, goal along +x: target at x = 1; from x = 13.5 the short way is +x
    td = posed_scene([(13.5, 7.0)], [(3.0, 7.0)], [(10.0, 7.0)], cfg)
    assert ScriptedHeuristicPolicy(cfg)(td)[GROUP, "action"][0, 0, VX] > 0.5
    unwrapped = cfg.replace(wrap_edges=False)
    assert ScriptedHeuristicPolicy(unwrapped)(td)[GROUP, "action"][0, 0, VX] < -0.5


def test_heuristic_raises_the_bump_only_near_its_target():
    cfg = one_object_config()
    policy = ScriptedHeuristicPolicy(cfg)
    sphere, goal = (7.0, 7.0), (12.0, 7.0)
    at_target = policy(posed_scene([(5.0, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert at_target[AMP] == 1.0  # amplitude 0 -> towards +max_amplitude
    assert abs(at_target[VX]) < 1e-5 and abs(at_target[VY]) < 1e-5  # at rest on its target
    far = posed_scene([(1.0, 12.0)], [sphere], [goal], cfg)
    far[GROUP, "observation"][0, 0, 3] = 0.5  # a half-height bump travelling
    far[GROUP, "observation"][0, 0, 8] = 0.5  # spinning
    far[GROUP, "observation"][0, 0, 4:6] = 1.0  # widest
    action = policy(far)[GROUP, "action"][0, 0]
    assert action[AMP] < 0  # flattened while it travels
    assert action[OMEGA] < 0  # spin towards zero
    assert action[SX] < 0 and action[SY] < 0  # width towards one cell


def test_heuristic_feeds_the_sphere_velocity_forward():
    cfg = one_object_config()
    td = posed_scene([(5.0, 7.0)], [(7.0, 7.0)], [(12.0, 7.0)], cfg)
    td["objects"][0, 0, 6] = 0.3  # rolling towards +x at 0.3 m/s
    assert ScriptedHeuristicPolicy(cfg)(td)[GROUP, "action"][0, 0, VX] > 0.5


def test_heuristic_skips_empty_slots_and_idles_without_spheres():
    cfg = one_object_config(num_agents=2, num_objects=2)
    policy = ScriptedHeuristicPolicy(cfg)
    # slot 0 empty: agent 0 serves the sphere in slot 1 (target x = 5), like agent 1
    td = posed_scene([(3.0, 7.0), (9.0, 7.0)], [None, (7.0, 7.0)], [(0, 0), (12.0, 7.0)], cfg)
    action = policy(td)[GROUP, "action"][0]
    assert action[0, VX] > 0.5 and action[1, VX] < -0.5
    # no sphere at all: stop and flatten
    idle = posed_scene([(3.0, 7.0), (9.0, 7.0)], [None, None], [(0, 0), (0, 0)], cfg)
    idle[GROUP, "observation"][0, :, 6] = 0.5  # moving towards +x
    idle[GROUP, "observation"][0, :, 3] = 0.5  # raised
    action = policy(idle)[GROUP, "action"][0]
    assert (action[:, VX] < 0).all() and (action[:, AMP] < 0).all()


def test_heuristic_with_target_actions_sets_its_set_points():
    cfg = one_object_config().replace(action_mode="target")
    policy = ScriptedHeuristicPolicy(cfg)
    sphere, goal = (7.0, 7.0), (12.0, 7.0)  # target cell x = 5
    far = posed_scene([(1.0, 7.0)], [sphere], [goal], cfg)
    far[GROUP, "observation"][0, 0, 3] = 0.5  # a half-height bump travelling
    far[GROUP, "observation"][0, 0, 6] = 0.5  # already moving towards +x
    far[GROUP, "observation"][0, 0, 8] = 0.5  # spinning
    action = policy(far)[GROUP, "action"][0, 0]
    # full speed towards +x whatever the current velocity, no spin, flat, one cell wide
    assert action[VX] == 1.0 and abs(action[VY]) < 1e-6
    assert action[OMEGA] == 0.0 and action[AMP] == 0.0
    width = cfg.sigma_min + (action[SX] + 1) * 0.5 * (cfg.sigma_max - cfg.sigma_min)
    assert width == pytest.approx(1.0) and action[SY] == action[SX]
    # on its target: at rest, raised to the full amplitude
    at_target = policy(posed_scene([(5.0, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert abs(at_target[VX]) < 1e-5 and at_target[AMP] == 1.0


def test_heuristic_with_shape_actions_accelerates_as_with_deltas_and_sets_its_shape():
    delta_cfg = one_object_config()
    cfg = delta_cfg.replace(action_mode="shape")
    sphere, goal = (7.0, 7.0), (12.0, 7.0)  # target cell x = 5
    for wavelet in ((1.0, 7.0), (5.0, 7.0)):  # travelling, then on its target
        scene = posed_scene([wavelet], [sphere], [goal], cfg)
        scene[GROUP, "observation"][0, 0, 3] = 0.5  # a half-height bump
        scene[GROUP, "observation"][0, 0, 8] = 0.5  # spinning
        action = ScriptedHeuristicPolicy(cfg)(scene.clone())[GROUP, "action"][0, 0]
        delta = ScriptedHeuristicPolicy(delta_cfg)(scene.clone())[GROUP, "action"][0, 0]
        torch.testing.assert_close(action[[VX, VY, OMEGA]], delta[[VX, VY, OMEGA]])
        width = cfg.sigma_min + (action[SX] + 1) * 0.5 * (cfg.sigma_max - cfg.sigma_min)
        assert width == pytest.approx(1.0) and action[SY] == action[SX]
    # the amplitude set points: flat while travelling, the full bump on its target
    assert action[AMP] == 1.0
    travelling = posed_scene([(1.0, 7.0)], [sphere], [goal], cfg)
    assert ScriptedHeuristicPolicy(cfg)(travelling)[GROUP, "action"][0, 0, AMP] == 0.0


def test_heuristic_with_position_actions_aims_where_the_servo_gives_its_velocity():
    cfg = one_object_config().replace(action_mode="position", position_gain=2.0)
    policy = ScriptedHeuristicPolicy(cfg)
    g = cfg.grid_size
    sphere, goal = (7.0, 7.0), (12.0, 7.0)  # target cell x = 5
    # 0.3 cells short of the target: desired velocity 0.3 (the heuristic's gain of 1), which
    # the servo (gain 2) aims at from 0.15 cells ahead, at x = 4.85
    near = policy(posed_scene([(4.7, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert near[VX] == pytest.approx(2 * 4.85 / g - 1, abs=1e-5)
    assert near[VY] == pytest.approx(2 * 7.0 / g - 1, abs=1e-5)
    # far away: full speed (1) the short way round, through the edge: aim 0.5 cells past x = 14
    far = policy(posed_scene([(14.0, 7.0)], [(2.0, 7.0)], [(6.0, 7.0)], cfg))
    assert far[GROUP, "action"][0, 0, VX] == pytest.approx(2 * 14.5 / g - 1, abs=1e-5)
    # the shape dims are deltas, as with delta actions: raise the bump on the target
    at_target = policy(posed_scene([(5.0, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert at_target[VX] == pytest.approx(2 * 5.0 / g - 1, abs=1e-5) and at_target[AMP] == 1.0
    # no sphere: every wavelet stays where it is
    idle = policy(posed_scene([(3.0, 9.0)], [None], [goal], cfg))[GROUP, "action"][0, 0]
    assert idle[VX] == pytest.approx(2 * 3.0 / g - 1, abs=1e-5)
    assert idle[VY] == pytest.approx(2 * 9.0 / g - 1, abs=1e-5)


def test_heuristic_rejects_bad_parameters():
    with pytest.raises(ValueError, match="amplitude"):
        ScriptedHeuristicPolicy(CFG, amplitude=0.0)
    with pytest.raises(ValueError, match="offset"):
        ScriptedHeuristicPolicy(CFG, offset=-1.0)
    with pytest.raises(ValueError, match="clearance"):
        ScriptedHeuristicPolicy(CFG, clearance=1.0)


def family_config(actuator: str, num_agents: int = 1) -> TerraShiftConfig:
    return TerraShiftConfig(actuator=actuator, num_agents=num_agents, num_objects=1, num_goals=1)


def with_angle(td: TensorDict, angle: float) -> TensorDict:
    """Sets every patch's orientation [rad] in a posed scene."""
    td[GROUP, "observation"][..., 2] = angle / math.pi - 1
    return td


def test_flow_heuristic_stands_on_the_sphere_and_turns_its_flow_towards_the_goal():
    cfg = family_config("surface_flow")
    policy = ScriptedHeuristicPolicy(cfg)
    sphere, goal = (7.0, 7.0), (12.0, 7.0)  # the goal along +x: the flow should point at 0 rad
    far = policy(posed_scene([(3.0, 7.0)], [sphere], [goal], cfg))[GROUP, "action"][0, 0]
    assert far[VX] > 0.5 and abs(far[VY]) < 1e-5
    assert far[AMP] == 0.0  # no flow while it travels
    on_it = posed_scene([sphere], [sphere], [goal], cfg)
    left_of_goal = policy(with_angle(on_it.clone(), 0.5 * math.pi))[GROUP, "action"][0, 0]
    right_of_goal = policy(with_angle(on_it.clone(), 1.5 * math.pi))[GROUP, "action"][0, 0]
    assert left_of_goal[OMEGA] < -0.5 < 0.5 < right_of_goal[OMEGA]  # the short way round
    assert left_of_goal[AMP] > 0.5 and abs(left_of_goal[VX]) < 1e-5


def test_flow_heuristic_steers_clear_of_another_sphere_and_stops_short_of_one_ahead():
    """Sphere 0 at (7, 7), its goal along +x at (12, 7); shape actions, so the amplitude
    action is the speed set point. Another sphere in play one diameter and a half ahead,
    a little to the left, halves the flow's speed and turns it away, clockwise; touching
    straight ahead, it stops the flow; behind, or beyond ``clearance`` diameters, it leaves the
    flow as it was, as ``clearance=None`` does wherever it is."""
    cfg = TerraShiftConfig(
        actuator="surface_flow", action_mode="shape", num_agents=1, num_objects=2, num_goals=1
    )
    policy = ScriptedHeuristicPolicy(cfg, clearance=2.0)
    diameter = 2 * cfg.sphere_radius / cfg.cell_size  # [cells]
    sphere, goal = (7.0, 7.0), (12.0, 7.0)

    def action(other: tuple[float, float] | None) -> torch.Tensor:
        td = posed_scene([sphere], [sphere, other], [goal, goal], cfg)
        return policy(with_angle(td, 0.0))[GROUP, "action"][0, 0]

    alone = action(None)
    assert alone[AMP] == 1.0 and abs(alone[OMEGA]) < 1e-5  # on it, flowing at the goal
    torch.testing.assert_close(action((7.0 + 2.05 * diameter, 7.0)), alone)
    blocked = action((7.0 + 1.5 * diameter, 7.5))  # ahead, a little to the left (+y)
    assert 0.4 < blocked[AMP] < 0.6  # half-way from touching to the clearance: half speed
    assert blocked[OMEGA] < -0.5  # turns clockwise, away from it
    touching = action((7.0 + diameter, 7.0))
    assert touching[AMP] == pytest.approx(0.0, abs=1e-6)
    behind = action((7.0 - 1.5 * diameter, 7.0))  # behind it: full speed, straight on
    torch.testing.assert_close(behind, alone)
    unsteered = ScriptedHeuristicPolicy(cfg, clearance=None)
    td = posed_scene([sphere], [sphere, (7.0 + diameter, 7.0)], [goal, goal], cfg)
    torch.testing.assert_close(unsteered(with_angle(td, 0.0))[GROUP, "action"][0, 0], alone)


def test_rotor_heuristic_spins_beside_the_sphere_with_its_rim_moving_towards_the_goal():
    """With the goal along +x, the first rotor stands one width (sigma = 1 cell) to the
    sphere's right seen along the way, at +y, spinning anticlockwise; the second as far to
    its left, clockwise: at the sphere either surface moves along +x."""
    cfg = family_config("rotors", num_agents=2)
    policy = ScriptedHeuristicPolicy(cfg)
    sphere, goal = (7.0, 7.0), (12.0, 7.0)
    td = posed_scene([(7.0, 8.0), (7.0, 6.0)], [sphere], [goal], cfg)
    action = policy(td)[GROUP, "action"][0]
    assert action[0, AMP] > 0.5 and action[1, AMP] < -0.5
    assert action[:, VX : VY + 1].abs().max() < 1e-5  # both already where they should be
    swapped = policy(posed_scene([(7.0, 6.0), (7.0, 8.0)], [sphere], [goal], cfg))
    assert swapped[GROUP, "action"][0, 0, VY] > 0.5 and swapped[GROUP, "action"][0, 1, VY] < -0.5


def test_rotor_heuristic_steers_clear_of_another_sphere_and_stops_short_of_one_ahead():
    """Sphere 0 at (7, 7), its goal along +x at (12, 7), its two rotors (agents 0 and 2;
    agent 1 serves slot 1) in place on either side (shape actions: the amplitude action is
    the spin set point). Another sphere in play one diameter and a half ahead, a little to
    the left (+y), turns the way the rims drive it clockwise, so both rotors move on along +x,
    and halves their spins; touching straight ahead, it stops them; ``clearance=None`` leaves
    them spinning in place as without it."""
    cfg = TerraShiftConfig(
        actuator="rotors", action_mode="shape", num_agents=3, num_objects=2, num_goals=1
    )
    diameter = 2 * cfg.sphere_radius / cfg.cell_size  # [cells]
    sphere, goal = (7.0, 7.0), (12.0, 7.0)

    def action(other: tuple[float, float] | None, clearance: float | None = 2.0):
        td = posed_scene([(7.0, 8.0), (2.0, 2.0), (7.0, 6.0)], [sphere, other], [goal, goal], cfg)
        return ScriptedHeuristicPolicy(cfg, clearance=clearance)(td)[GROUP, "action"][0, 0::2]

    alone = action(None)
    assert alone[0, AMP] == 1.0 and alone[1, AMP] == -1.0
    assert alone[:, VX : VY + 1].abs().max() < 1e-5
    blocked = action((7.0 + 1.5 * diameter, 7.5))
    assert 0.4 < blocked[0, AMP] < 0.6 and -0.6 < blocked[1, AMP] < -0.4
    assert blocked[0, VX] > 0.1 and blocked[1, VX] < -0.1  # round, clockwise, to the new way
    touching = action((7.0 + diameter, 7.0))
    torch.testing.assert_close(touching[:, AMP], torch.zeros(2), atol=1e-6, rtol=0)
    torch.testing.assert_close(action((7.0 + diameter, 7.0), clearance=None), alone)


@pytest.mark.parametrize(("actuator", "margin"), [("surface_flow", 0.2), ("rotors", 0.1)])
def test_sliding_heuristic_keeps_more_spheres_than_it_did_without_steering_clear(actuator, margin):
    """Sixteen evaluation episodes on box columns: steering the spheres clear of each other
    delivers nearly all of them, driving each straight at its goal about seven (surface flow)
    or eight (rotors) in ten (a sphere that the surface presses against another ends rolling
    in place)."""
    cfg = TerraShiftConfig(
        actuator=actuator, column_shape="box", respawn=False, max_episode_steps=160
    )
    goals = {}
    for clearance in (None, 2.0):
        env = TerraShiftEnv(cfg, num_envs=16, seed=0)
        scores = evaluate(env, ScriptedHeuristicPolicy(cfg, clearance=clearance), progress=False)
        goals[clearance] = scores["goal_fraction"]
    assert goals[2.0] >= 0.95 and goals[None] <= goals[2.0] - margin, goals


@pytest.mark.parametrize("actuator", sorted(ACTUATORS))
def test_every_family_passes_torchrl_spec_checks_and_takes_every_baseline(actuator):
    env = TerraShiftEnv(num_envs=2, seed=0, actuator=actuator, max_episode_steps=8)
    check_env_specs(env, seed=0)
    for policy in (RandomPolicy(seed=0), ZeroPolicy(), ScriptedHeuristicPolicy(env.config)):
        td = env.rollout(10, policy, break_when_any_done=False)
        assert torch.isfinite(td["next", GROUP, "reward"]).all()
        assert td[GROUP, "action"].abs().max() <= 1.0
