"""TerraShiftEnv: specs, resets, seeding, event counts, bad input, TorchRL interoperability."""

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs
from torchrl.modules import MultiAgentMLP, ProbabilisticActor, TanhNormal
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from terrashift_rl.envs import GROUP, PRIVILEGED, TerraShiftEnv
from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import COLUMN_SHAPES

N = 3


def random_actions(steps: int, env: TerraShiftEnv, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(steps, *env.sim.action_shape, generator=generator) * 2 - 1


def play(env: TerraShiftEnv, actions: torch.Tensor) -> TensorDict:
    td = env.reset()
    frames = []
    for action in actions:
        td[GROUP, "action"] = action
        out, td = env.step_and_maybe_reset(td)
        frames.append(out)
    return torch.stack(frames)


def observing_env(camera: int, *, objects: bool, privileged: bool) -> TerraShiftEnv:
    """The default scene with a ``camera``-pixel camera (0: none), the object sequence
    observed, handed to the critics alone (``privileged``) or neither."""
    return TerraShiftEnv(
        num_envs=N,
        seed=0,
        camera_resolution=camera,
        observe_objects=objects,
        privileged_objects=privileged,
    )


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_check_env_specs(shape):
    check_env_specs(TerraShiftEnv(num_envs=N, seed=0, column_shape=shape))


@pytest.mark.parametrize(
    ("camera", "objects", "privileged"),
    [(24, True, False), (24, False, False), (0, False, False), (24, False, True)],
)
def test_check_env_specs_with_a_camera_and_without_objects(camera, objects, privileged):
    env = observing_env(camera, objects=objects, privileged=privileged)
    check_env_specs(env)
    td = env.rollout(2)
    assert ("camera" in td) == bool(camera)
    assert ("objects" in td) == ("objects_mask" in td) == objects
    assert (PRIVILEGED in td) == privileged
    if privileged:  # the observed sequence's tensors, under another key
        m = env.config.num_objects
        assert td[PRIVILEGED, "objects"].shape == (N, 2, m, 9)
        assert torch.equal(
            td["next", PRIVILEGED, "objects"][:, -1], env.sim.view("object_features")
        )
        assert torch.equal(
            td["next", PRIVILEGED, "objects_mask"][:, -1], env.sim.view("object_mask")
        )
    if camera:
        assert td["camera"].shape == (N, 2, 1, camera, camera)
        assert td["camera"].min() >= 0.0 and td["camera"].max() <= 1.0


@pytest.mark.parametrize("privileged", [False, True])
def test_without_objects_the_observation_is_the_images_and_the_wavelets(privileged):
    env = observing_env(16, objects=False, privileged=privileged)
    critics_alone = {(PRIVILEGED, "objects"), (PRIVILEGED, "objects_mask")} if privileged else set()
    assert set(env.observation_spec.keys(True, True)) == {
        (GROUP, "observation"),
        (GROUP, "mask"),
        "heightmap",
        "camera",
        "episode_goals",
        "episode_out_of_bounds",
        "episode_surface_work",
        *critics_alone,
    }


@pytest.mark.parametrize(("objects", "privileged"), [(False, False), (True, False), (False, True)])
def test_sphere_positions_show_in_no_observation_but_the_images(objects, privileged):
    """Moving the spheres changes only the images among what a policy from pixels reads; the
    object sequence changes where observed, and under ``"privileged"`` where handed to the
    critics, which the actor does not read."""
    env = observing_env(24, objects=objects, privileged=privileged)
    td = env.reset()
    for action in random_actions(4, env):
        td[GROUP, "action"] = action
        td = env.step(td)["next"]
    td[GROUP, "action"] = random_actions(1, env, seed=1)[0]
    state = env.sim.state_dict()
    seen = env.step(td.clone())["next"]
    state["sphere_position"][..., 0] += 0.03  # every sphere 3 cm along x, nothing else
    env.sim.load_state_dict(state)
    moved = env.step(td.clone())["next"]
    changed = {
        key
        for key in env.observation_spec.keys(True, True)
        if not torch.equal(seen[key], moved[key])
    }
    critics_alone = {(PRIVILEGED, "objects")} if privileged else set()
    assert changed == {"camera", "heightmap", *(["objects"] if objects else []), *critics_alone}
    if not objects:
        pixels = TerraShiftModelConfig(camera_channels=1, object_tokens=False)
        networks = make_terrashift_networks(dataclasses.replace(pixels, critic_objects=privileged))
        assert changed & set(networks.actor.in_keys) == {"camera", "heightmap"}
        assert critics_alone <= set(networks.value_head.in_keys)


def test_keys_and_shapes_follow_multi_agent_conventions():
    env = TerraShiftEnv(num_envs=N, seed=0)
    td = env.rollout(2)
    k, m = env.config.num_agents, env.config.num_objects
    assert td[GROUP, "observation"].shape == (N, 2, k, 9)
    assert td[GROUP, "action"].shape == (N, 2, k, 6)
    assert td["next", GROUP, "reward"].shape == (N, 2, k, 1)
    assert td["heightmap"].shape == (N, 2, 1, 32, 32)
    assert td["objects"].shape == (N, 2, m, 9)
    assert td["objects_mask"].dtype == torch.bool
    for key in ("done", "terminated", "truncated"):
        assert td["next", key].shape == (N, 2, 1)
        assert td["next", GROUP, key].shape == (N, 2, k, 1)
    # every agent receives the same team reward
    reward = td["next", GROUP, "reward"]
    assert (reward == reward[..., :1, :]).all()


def test_step_limit_truncates_and_never_terminates_in_training_mode():
    env = TerraShiftEnv(num_envs=N, seed=0, max_episode_steps=4)
    td = env.rollout(9, break_when_any_done=False)
    truncated = td["next", "truncated"].squeeze(-1)
    assert truncated[:, [3, 7]].all()
    assert truncated.sum() == 2 * N
    assert not td["next", "terminated"].any()
    assert (td["next", "done"] == td["next", "truncated"]).all()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_staggered_episodes_truncate_when_their_counters_say(device):
    torch.manual_seed(0)
    limit = 6
    env = TerraShiftEnv(num_envs=32, seed=0, max_episode_steps=limit, device=device)
    td = env.reset()
    env.stagger_episodes()
    offsets = env.sim.view("step_count").clone().long()
    assert offsets.min() >= 0 and offsets.max() < limit
    assert len(offsets.unique()) > 1
    frames = []
    for action in random_actions(2 * limit, env):
        td[GROUP, "action"] = action.to(device)
        out, td = env.step_and_maybe_reset(td)
        frames.append(out["next", "truncated"].squeeze(-1))
    truncated = torch.stack(frames, dim=1)  # [envs, decisions]
    first = truncated.long().argmax(dim=1)
    torch.testing.assert_close(first, limit - 1 - offsets)  # the first episode is shortened
    later = truncated.clone()
    later[torch.arange(32, device=device), first] = False
    torch.testing.assert_close(later.long().argmax(dim=1), first + limit)  # then full length


def test_partial_reset_touches_only_masked_environments():
    env = TerraShiftEnv(num_envs=4, seed=0)
    td = env.reset()
    for action in random_actions(3, env):
        td[GROUP, "action"] = action
        td = env.step(td)["next"]
    before = env.sim.view("agent_features").clone()
    steps_before = env.sim.view("step_count").clone()
    mask = torch.tensor([True, False, True, False])
    td["_reset"] = mask.unsqueeze(-1)
    out = env.reset(td)
    steps = env.sim.view("step_count")
    assert (steps[mask] == 0).all() and (steps[~mask] == steps_before[~mask]).all()
    kept = ~mask
    torch.testing.assert_close(out[GROUP, "observation"][kept], before[kept])
    assert not torch.equal(out[GROUP, "observation"][mask], before[mask])
    # the first observation after the reset already holds a spawned sphere
    assert out["objects_mask"][mask, 0].all()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_same_seed_reproduces_and_other_seed_differs(device):
    actions = random_actions(6, TerraShiftEnv(num_envs=N, seed=0, device=device)).to(device)
    first = play(TerraShiftEnv(num_envs=N, seed=7, device=device), actions)
    again = play(TerraShiftEnv(num_envs=N, seed=7, device=device), actions)
    other = play(TerraShiftEnv(num_envs=N, seed=8, device=device), actions)
    assert (first == again).all()
    assert not torch.equal(first["heightmap"], other["heightmap"])
    env = TerraShiftEnv(num_envs=N, seed=123, device=device)
    env.set_seed(7)
    assert (play(env, actions) == first).all()


def test_goal_event_is_counted_and_rewarded_then_cleared_by_reset():
    env = TerraShiftEnv(num_envs=1, seed=0, action_repeat=1)
    td = env.reset()
    cfg, sim = env.config, env.sim
    ix, iy = sim.view("goal_cell")[0, 0].tolist()
    top = cfg.column_rest_top + sim.view("column_height")[0, iy, ix].item()
    centre = lambda i: (i + 0.5) * cfg.cell_size - 0.5  # noqa: E731
    # put sphere 0 right on its goal
    sim.view("sphere_position")[0, 0] = torch.tensor(
        [centre(ix), centre(iy), top + cfg.sphere_radius]
    )
    td[GROUP, "action"] = torch.zeros(sim.action_shape)
    out = env.step(td)["next"]
    assert out["episode_goals"].item() == 1
    assert not out["objects_mask"][0, 0]
    assert out[GROUP, "reward"][0, 0, 0].item() > 0.9 * cfg.goal_reward / cfg.reward_normalizer
    assert env.reset()["episode_goals"].item() == 0


@pytest.mark.parametrize(
    ("action", "message", "check_every_step"),
    [
        (torch.zeros(N, 8, 5), "shape", False),
        (torch.zeros(N, 8, 6, dtype=torch.float64), "float32", False),
        (torch.zeros(N, 8, 6, device="meta"), "must be on", False),
        (torch.full((N, 8, 6), float("nan")), "NaN", True),
        (torch.full((N, 8, 6), float("inf")), "NaN or infinite", True),
    ],
)
def test_bad_actions_raise_and_leave_the_state_untouched(action, message, check_every_step):
    env = TerraShiftEnv(num_envs=N, seed=0, check_every_step=check_every_step)
    td = env.reset().clear_device_()  # a device-less tensordict keeps the action's device
    state = env.sim.view("agent_features").clone()
    td[GROUP, "action"] = action
    with pytest.raises(ValueError, match=message) as info:
        env.step(td)
    assert "('agents', 'action')" in str(info.value)
    torch.testing.assert_close(env.sim.view("agent_features"), state)
    assert (env.sim.view("step_count") == 0).all()


def test_non_finite_actions_are_refused_at_the_next_check_and_never_simulated():
    env = TerraShiftEnv(num_envs=N, seed=0)
    td = env.reset()
    actions = torch.zeros(3, N, 8, 6)
    actions[1, 2, 5, 0] = float("nan")  # one value of the second step
    actions[2, 0, 0, 3] = -float("inf")
    for action in actions:
        td[GROUP, "action"] = action
        td = env.step_and_maybe_reset(td)[1]
    assert td[GROUP, "observation"].isfinite().all()  # simulated as 0: the state stays finite
    message = r"^\('agents', 'action'\) held NaN or infinite values in 2 of the 3 steps"
    with pytest.raises(ValueError, match=message):
        env.check_actions()
    env.check_actions()  # each check starts a new count
    # the same actions with 0 in place of the non-finite values give the same state
    zeros = play(TerraShiftEnv(num_envs=N, seed=0), actions.nan_to_num(0.0, 0.0, 0.0))
    torch.testing.assert_close(td[GROUP, "observation"], zeros[-1]["next", GROUP, "observation"])


class HostSynchronisation(AssertionError):
    pass


def test_a_step_reads_no_tensor_value_on_the_host(monkeypatch):
    # Each of these waits for the device on CUDA; on the CPU they are how a value would be read.
    env = TerraShiftEnv(num_envs=N, seed=0)
    td = env.reset()
    td[GROUP, "action"] = torch.full((N, 8, 6), float("nan"))

    def refuse(tensor, *args):
        raise HostSynchronisation

    for name in ("__bool__", "__int__", "__float__", "item", "tolist"):
        monkeypatch.setattr(torch.Tensor, name, refuse)
    env._step(td)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="1 of the 1 steps"):
        env.check_actions()
    # the debug option reads the flag at every step
    env.check_every_step = True
    monkeypatch.setattr(torch.Tensor, "__bool__", refuse)
    with pytest.raises(HostSynchronisation):
        env._step(td)


@pytest.mark.gpu
def test_a_step_on_cuda_does_not_synchronise():
    env = TerraShiftEnv(num_envs=N, seed=0, device="cuda")
    td = env.reset()
    td[GROUP, "action"] = torch.full((N, 8, 6), float("nan"), device="cuda")
    env._step(td)  # Warp's first launches and graph captures may synchronise
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            env._step(td)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match="4 of the 4 steps"):
        env.check_actions()


def test_out_of_range_actions_are_clipped():
    actions = random_actions(3, TerraShiftEnv(num_envs=N, seed=0))
    clipped = play(TerraShiftEnv(num_envs=N, seed=1), actions.sign())
    scaled = play(TerraShiftEnv(num_envs=N, seed=1), actions.sign() * 5)
    assert torch.equal(clipped[GROUP, "observation"], scaled[GROUP, "observation"])


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="grid_size"):
        TerraShiftEnv(num_envs=1, grid_size=1)
    with pytest.raises(ValueError, match="unknown TerraShiftConfig field"):
        TerraShiftEnv(num_envs=1, grid_sise=15)
    with pytest.raises(ValueError, match="num_envs"):
        TerraShiftEnv(num_envs=0)


def test_collector_runs_with_partial_resets():
    env = TerraShiftEnv(num_envs=2, seed=0, max_episode_steps=3)
    collector = Collector(env, policy=None, frames_per_batch=16, total_frames=32)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    assert batches[0].batch_size == (2, 8)
    assert batches[0]["next", "truncated"].any()


def test_torchrl_mappo_loss_runs_unchanged():
    env = TerraShiftEnv(num_envs=2, seed=0)
    k = env.config.num_agents

    def mlp(outputs: int, centralised: bool) -> MultiAgentMLP:
        return MultiAgentMLP(
            n_agent_inputs=9,
            n_agent_outputs=outputs,
            n_agents=k,
            centralised=centralised,
            share_params=True,
            depth=1,
            num_cells=16,
        )

    policy = ProbabilisticActor(
        TensorDictModule(
            torch.nn.Sequential(mlp(12, False), NormalParamExtractor()),
            in_keys=[(GROUP, "observation")],
            out_keys=[(GROUP, "loc"), (GROUP, "scale")],
        ),
        spec=env.full_action_spec_unbatched[GROUP, "action"],
        in_keys=[(GROUP, "loc"), (GROUP, "scale")],
        out_keys=[(GROUP, "action")],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        return_log_prob=True,
    )
    critic = TensorDictModule(
        mlp(1, True), in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "state_value")]
    )
    loss = ClipPPOLoss(policy, critic, normalize_advantage=False)
    loss.set_keys(
        reward=(GROUP, "reward"),
        action=(GROUP, "action"),
        value=(GROUP, "state_value"),
        done=(GROUP, "done"),
        terminated=(GROUP, "terminated"),
        sample_log_prob=(GROUP, "action_log_prob"),
    )
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.95, lmbda=0.92)
    with torch.no_grad():
        data = env.rollout(5, policy=policy, break_when_any_done=False)
        loss.value_estimator(data, params=loss.critic_network_params, target_params=None)
    losses = loss(data)
    total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
    total.backward()
    assert torch.isfinite(total)
    assert all(p.grad is not None for p in policy.parameters())
