"""MA-POCA, MAPPO and IPPO through one trainer: each trains, resumes exactly from a checkpoint and
finetunes; MAPPO's and IPPO's advantages are GAE's, computed here by hand."""

import dataclasses
import math
import warnings

import pytest
import torch
from tensordict import TensorDict
from test_trainer import (
    ENV,  # the same small scene and trainer
    train_config,
)
from test_trainer import make_trainer as make_training
from torchrl.modules import set_recurrent_mode

from terrashift_rl.modules import TerraShiftModelConfig, keys, make_terrashift_networks
from terrashift_rl.modules.independent import AGENT_VALUE
from terrashift_rl.training import (
    ALGORITHMS,
    OnPolicyTrainer,
    TrainConfig,
    load_checkpoint,
    make_training_env,
    save_checkpoint,
    terrashift,
)

ALGOS = ("mapoca", "mappo", "ippo")
# metrics that measure time, not learning
TIMINGS = ("_seconds", "_per_s")


def make_trainer(algo: str, *, seed: int = 0, **train) -> OnPolicyTrainer:
    return make_training(seed=seed, algo=algo, **train)


def weights(trainer: OnPolicyTrainer) -> dict[str, torch.Tensor]:
    return {name: p.detach().clone() for name, p in trainer._named_parameters()}


def test_the_registry_holds_the_three_algorithms():
    assert tuple(ALGORITHMS) == ALGOS
    assert TrainConfig().algo == "mapoca"


@pytest.mark.parametrize("algo", ALGOS)
def test_each_algorithm_trains_its_policy_and_critics(algo):
    trainer = make_trainer(algo)
    before = weights(trainer)
    for _ in range(2):
        metrics = trainer.train_iteration()
        losses = {name: value for name, value in metrics.items() if name.startswith("loss_")}
        assert {"loss_objective", "loss_critic", "loss_entropy"} <= losses.keys()
        assert all(math.isfinite(value) for value in losses.values()), losses
        assert math.isfinite(metrics["kl_approx"]) and 0.0 <= metrics["clip_fraction"] <= 1.0
    after = weights(trainer)
    critics = {
        "mapoca": ("value_head.", "baseline_head."),
        "mappo": ("value_head.",),
        "ippo": ("algorithm_networks.agent_value_head.",),
    }
    for prefix in ("trunk.", "policy_head.", *critics[algo]):
        assert any(
            not torch.equal(after[name], before[name]) for name in after if name.startswith(prefix)
        ), prefix
    unused = {"mapoca": (), "mappo": ("baseline_head.",), "ippo": ("value_head.", "baseline_head.")}
    for name in after:
        if name.startswith(unused[algo]):
            assert torch.equal(after[name], before[name]), name


@pytest.mark.parametrize("algo", ("mappo", "ippo"))
def test_the_critic_loss_trains_the_shared_trunk_through_the_fresh_embedding(algo):
    # the critic reads the embedding the actor has just written in the same pass: were it the
    # stale one stored in the batch, no gradient would reach the trunk from the value loss
    trainer = make_trainer(algo)
    data = trainer.collect()
    trainer.algorithm.estimate(data)
    trainer._train_mode(True)
    with set_recurrent_mode(True):
        out = trainer.loss(data)
    out["loss_critic"].backward()
    assert any(
        p.grad is not None and p.grad.abs().sum() > 0 for p in trainer.networks.trunk.parameters()
    )
    assert all(p.grad is None for p in trainer.networks.policy_head.parameters())


@pytest.mark.parametrize("algo", ("mappo", "ippo"))
def test_critic_warmup_and_the_adaptive_learning_rate_work_with_torchrls_losses(algo):
    # a KL target far above any update's KL: every policy mini-batch raises the rate
    trainer = make_trainer(
        algo,
        critic_warmup_iterations=1,
        lr_schedule="adaptive",
        desired_kl=10.0,
        lr_trunk_policy=3.0e-4,
    )
    before = weights(trainer)
    metrics = trainer.train_iteration()
    assert metrics["critic_warmup"] == 1.0
    assert metrics["lr_trunk_policy"] == pytest.approx(3.0e-4)  # no policy step, no adapting
    after = weights(trainer)
    for name, value in after.items():
        if name.startswith(("trunk.", "policy_head.")):
            assert torch.equal(value, before[name]), name  # bit for bit
    critic = "value_head." if algo == "mappo" else "algorithm_networks."
    assert any(not torch.equal(v, before[n]) for n, v in after.items() if n.startswith(critic))
    metrics = trainer.train_iteration()
    assert metrics["critic_warmup"] == 0.0
    assert metrics["lr_trunk_policy"] == pytest.approx(3.0e-4 * 1.5**2)  # two mini-batches


@pytest.mark.parametrize("algo", ALGOS)
def test_a_checkpoint_resumes_exactly_where_the_run_would_have_gone(algo, tmp_path):
    straight = make_trainer(algo)
    straight.train_iteration()
    path = save_checkpoint(straight.state_dict(), tmp_path / "last.pt")
    expected = straight.train_iteration()

    resumed = make_trainer(algo, seed=1)  # other initial weights, scenes and random numbers
    resumed.load_state_dict(load_checkpoint(path))
    metrics = resumed.train_iteration()
    for name, value in expected.items():
        if not name.endswith(TIMINGS):
            assert metrics[name] == pytest.approx(value, rel=0, abs=0, nan_ok=True), name
    straight_weights, resumed_weights = weights(straight), weights(resumed)
    assert straight_weights.keys() == resumed_weights.keys()
    for name, value in straight_weights.items():
        assert torch.equal(resumed_weights[name], value), name
    normalizer = straight.algorithm.value_normalizer
    for name, value in normalizer.state_dict().items():
        assert torch.equal(resumed.algorithm.value_normalizer.state_dict()[name], value), name
    assert resumed.iteration == straight.iteration == 2


def test_an_ippo_checkpoint_holds_its_per_agent_value_head():
    state = make_trainer("ippo").state_dict()
    assert state["algo"] == "ippo" and "baseline_coeff" not in state["train_config"]["loss"]
    assert any(name.startswith("agent_value_head.") for name in state["algorithm_networks"])
    assert make_trainer("mapoca").state_dict()["algorithm_networks"] == {}


def test_a_checkpoint_written_before_algorithms_existed_resumes_as_mapoca(tmp_path):
    trainer = make_trainer("mapoca")
    trainer.train_iteration()
    state = trainer.state_dict()
    # the earlier layout: no algorithm, one flat dict of training and loss settings
    del state["algo"], state["algorithm_networks"]
    loss = state["train_config"].pop("loss")
    state["train_config"].update(loss, value_clip_start=loss.pop("clip_value_start"))
    path = save_checkpoint(state, tmp_path / "old.pt")
    upgraded = load_checkpoint(path)
    assert upgraded["train_config"]["loss"]["clip_value_start"] == 0.3
    make_trainer("mapoca").load_state_dict(upgraded)
    with pytest.raises(ValueError, match="trained with algo=mapoca; resume with the same"):
        make_trainer("mappo").load_state_dict(upgraded)


def test_finetuning_keeps_the_algorithms_own_networks_only_from_the_same_algorithm():
    pretrained = make_trainer("ippo", seed=1).weights_state_dict()
    finetuned = make_trainer("ippo")
    finetuned.load_weights(pretrained)
    for name, value in pretrained["algorithm_networks"].items():
        assert torch.equal(finetuned.algorithm.networks.state_dict()[name], value), name
    from_mapoca = make_trainer("ippo")
    fresh = from_mapoca.algorithm.networks.state_dict()
    mapoca = make_trainer("mapoca", seed=1).weights_state_dict()
    from_mapoca.load_weights(mapoca)
    for name, value in mapoca["networks"].items():
        assert torch.equal(from_mapoca.networks.state_dict()[name], value), name
    for name, value in fresh.items():
        assert torch.equal(from_mapoca.algorithm.networks.state_dict()[name], value), name


def hand_values(trainer: OnPolicyTrainer, data: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
    """V(s_t) and V(s_{t+1}) per agent, [N, T, K, 1], from the networks run on every element."""
    networks = trainer.networks

    def per_agent(td: TensorDict) -> torch.Tensor:
        td = networks.trunk(td.reshape(-1).copy())
        if trainer.config.algo == "mappo":  # the team value, every agent's
            team = networks.value_head(td)[keys.STATE_VALUE]
            return team[:, None, :].expand(-1, ENV.num_agents, 1)
        return trainer.algorithm.networks["agent_value_head"](td)[AGENT_VALUE]

    shape = (*data.shape, ENV.num_agents, 1)
    with torch.no_grad():
        return per_agent(data.exclude("next")).reshape(shape), per_agent(data["next"]).reshape(
            shape
        )


@pytest.mark.parametrize("normalize_value", [False, True])
@pytest.mark.parametrize("algo", ("mappo", "ippo"))
def test_advantages_and_returns_are_gae_per_agent_computed_by_hand(algo, normalize_value):
    trainer = make_trainer(algo, normalize_value=normalize_value)
    data = trainer.collect()
    nxt = data["next"]
    assert nxt["truncated"].any()  # 8 decisions cross a 6-decision episode's end
    trainer._train_mode(False)
    value, next_value = hand_values(trainer, data)
    reward = nxt["agents", "reward"]  # [N, T, K, 1], each agent holds the team reward
    done = nxt["done"][..., None, :].float()  # [N, T, 1, 1]: the team's, for every agent
    terminated = nxt["terminated"][..., None, :].float()
    gamma, lmbda = trainer.config.loss.gamma, trainer.config.loss.lmbda
    advantage = torch.zeros_like(value)
    following = torch.zeros_like(value[:, 0])
    for t in reversed(range(data.shape[1])):
        delta = reward[:, t] + gamma * next_value[:, t] * (1 - terminated[:, t]) - value[:, t]
        following = delta + gamma * lmbda * (1 - done[:, t]) * following
        advantage[:, t] = following
    value_target = advantage + value
    # standardised once per batch over environments and steps, each agent on its own
    mean = advantage.mean(dim=(0, 1), keepdim=True)
    std = advantage.std(dim=(0, 1), keepdim=True).clamp_min(1e-4)

    sizes = []  # the trunk runs on the states after episode ends and the batch's end alone
    hook = trainer.networks.trunk.register_forward_pre_hook(
        lambda module, args: sizes.append(args[0].numel())
    )
    trainer.algorithm.estimate(data)
    hook.remove()
    assert sum(sizes) == (nxt["done"][:, :-1].sum() + data.shape[0]).item()
    torch.testing.assert_close(data["agents", "advantage"], (advantage - mean) / std)
    torch.testing.assert_close(data["agents", "state_value"], value)  # the old value, stored
    stored_target = data["agents", "value_target"]
    if normalize_value:  # in the critic's units, by the statistics that include these returns
        normalizer = trainer.algorithm.value_normalizer
        assert normalizer.weight > 0
        torch.testing.assert_close(stored_target, normalizer.normalize(value_target))
    else:
        torch.testing.assert_close(stored_target, value_target)
    assert ("next", "agents", "state_value") not in data.keys(include_nested=True)
    if algo == "mappo":  # one team value, one team advantage
        team_advantage = data["agents", "advantage"]
        torch.testing.assert_close(team_advantage, team_advantage[..., :1, :].expand_as(value))


def eight_environments(algo: str, device: str, *, minibatches: int) -> OnPolicyTrainer:
    """A trainer of the small network on eight environments of ``ENV``, eight decisions each."""
    torch.manual_seed(0)
    networks = make_terrashift_networks(TerraShiftModelConfig.small()).to(device)
    config = train_config(algo=algo, num_envs=8, steps_per_iteration=8, minibatches=minibatches)
    env = make_training_env(ENV, networks, num_envs=8, device=torch.device(device), seed=0)
    return terrashift.make_trainer(env, networks, config)


ESTIMATES = {
    "mapoca": ("state_value", "value_target", ("agents", "baseline"), ("agents", "advantage")),
    **dict.fromkeys(
        ("mappo", "ippo"),
        (("agents", "state_value"), ("agents", "value_target"), ("agents", "advantage")),
    ),
}
"""What each algorithm's value-estimation pass writes."""


@pytest.mark.parametrize("algo", ALGOS)
def test_the_value_estimation_pass_reads_the_host_once(algo, host_reads):
    # On CUDA every read waits for the device: the one left is how many states follow an
    # episode's end (those the critics run on besides the batch's own).
    trainer = make_trainer(algo)
    data = trainer.collect()
    assert data["next", "done"][:, :-1].any()  # an episode ends inside the batch
    trainer.algorithm.estimate.max_batch = 1  # in pieces
    trainer._train_mode(False)
    assert host_reads(trainer.algorithm.estimate, data) == {"aten::nonzero": 1}
    assert trainer.algorithm.value_normalizer.weight > 0  # the return statistics moved


@pytest.mark.gpu
@pytest.mark.parametrize("algo", ALGOS)
def test_the_value_estimation_pass_waits_for_the_device_once_on_cuda(algo):
    trainer = eight_environments(algo, "cuda", minibatches=8)
    data = trainer.collect()
    trainer._train_mode(False)
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")  # a warning at every synchronising operation
        try:
            trainer.algorithm.estimate(data)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    waits = [str(warning.message) for warning in caught if "synchroniz" in str(warning.message)]
    assert len(waits) == 1, waits  # how many states follow an episode's end


@pytest.mark.parametrize("algo", ALGOS)
def test_the_value_estimation_pass_gives_the_same_results_whatever_its_pieces(algo):
    trainer = eight_environments(algo, "cpu", minibatches=8)
    estimate = trainer.algorithm.estimate
    assert estimate.max_batch == 4  # four mini-batches of one sequence, not one
    data = trainer.collect()
    trainer._train_mode(False)
    normalizer = trainer.algorithm.value_normalizer
    statistics = {name: value.clone() for name, value in normalizer.state_dict().items()}
    results = {}
    for max_batch in (None, 4, 3, 1):  # whole, two pieces, uneven ones, one sequence each
        estimate.max_batch = max_batch
        normalizer.load_state_dict(statistics)  # each pass starts from the same statistics
        results[max_batch] = estimate(data.clone())
    # In step mode every element is computed on its own: only the matrix products' blocking
    # changes with a piece's size, a rounding difference (a few units in the last place of a
    # float32 product), carried into the returns and the standardised advantages.
    for result in results.values():
        for key in ESTIMATES[algo]:
            torch.testing.assert_close(result[key], results[None][key], rtol=1e-5, atol=1e-5)


def test_swapping_the_algorithm_changes_no_other_setting():
    configs = [train_config(algo=algo) for algo in ALGOS]
    shared = {field.name for field in dataclasses.fields(ALGORITHMS["mappo"])}
    for config in configs:
        assert dataclasses.replace(config, loss=configs[0].loss) == configs[0]
        loss = dataclasses.asdict(config.loss)
        assert {name: loss[name] for name in shared} == {
            name: getattr(configs[0].loss, name) for name in shared
        }


@pytest.mark.gpu
@pytest.mark.parametrize("algo", ("mappo", "ippo"))
def test_ppo_algorithms_replay_the_actor_and_update_eagerly_on_cuda(algo):
    trainer = eight_environments(algo, "cuda", minibatches=2)
    for _ in range(3):  # the third collection replays the captured actor step
        assert math.isfinite(trainer.train_iteration()["loss_total"])
    assert trainer._actor_step.captured
    assert not trainer.algorithm.capturable


@pytest.mark.parametrize("algo", ("mapoca", "mappo"))
def test_privileged_critics_learn_from_the_objects_the_policy_does_not_see(algo):
    torch.manual_seed(0)
    model = dataclasses.replace(
        TerraShiftModelConfig.small(), object_tokens=False, critic_objects=True
    )
    networks = make_terrashift_networks(model)
    scene = ENV.replace(observe_objects=False, privileged_objects=True)
    env = make_training_env(scene, networks, num_envs=3, device=torch.device("cpu"), seed=0)
    config = train_config(algo=algo, num_envs=3, steps_per_iteration=8, minibatches=1)
    trainer = terrashift.make_trainer(env, networks, config)
    before = weights(trainer)
    for _ in range(2):
        metrics = trainer.train_iteration()
        assert math.isfinite(metrics["loss_critic"])
    after = weights(trainer)
    readers = ("value_head.", "baseline_head.") if algo == "mapoca" else ("value_head.",)
    for head in readers:
        names = [name for name in after if name.startswith(f"{head}module.object_reader.")]
        assert names and any(not torch.equal(after[name], before[name]) for name in names), head
