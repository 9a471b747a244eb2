"""MAPOCALoss used as a TorchRL user would, from the public API and with torchrl's idioms.

Data in VMAS's layout (group ``"agents"``, per-agent rewards, team done flags, no mask), a
Gaussian actor, the generic critics; the calls of torchrl's PPO and MAPPO examples; the errors
that name a missing or mis-shaped key; the guard against a loop that never trains the baselines.
"""

import warnings

import pytest
import torch
from tensordict import TensorDict, TensorDictParams
from tensordict.nn import TensorDictModule
from torch import nn
from torch._dynamo.testing import CompileCounterWithBackend
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import (
    IndependentNormal,
    MultiAgentMLP,
    NormalParamExtractor,
    ProbabilisticActor,
)
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from terrashift_rl.modules import CentralValue, CounterfactualBaseline
from terrashift_rl.objectives import MAPOCALoss

N_ENVS, N_STEPS, N_AGENTS, OBS_DIM, ACTION_DIM = 2, 4, 3, 5, 2
BATCH = [N_ENVS, N_STEPS]


def make_actor() -> ProbabilisticActor:
    return ProbabilisticActor(
        TensorDictModule(
            nn.Sequential(nn.Linear(OBS_DIM, 2 * ACTION_DIM), NormalParamExtractor()),
            in_keys=[("agents", "observation")],
            out_keys=[("agents", "loc"), ("agents", "scale")],
        ),
        in_keys=[("agents", "loc"), ("agents", "scale")],
        out_keys=[("agents", "action")],
        distribution_class=IndependentNormal,
        return_log_prob=True,
    )


def make_loss(value_network: TensorDictModule | None = None, **kwargs) -> MAPOCALoss:
    torch.manual_seed(0)
    actor = make_actor()
    value = CentralValue(OBS_DIM, width=8, depth=1, num_heads=2)
    baseline = CounterfactualBaseline(OBS_DIM, ACTION_DIM, width=8, depth=1, num_heads=2)
    loss = MAPOCALoss(actor, value if value_network is None else value_network, baseline, **kwargs)
    return loss.make_value_estimator(ValueEstimators.GAE, gamma=0.9, lmbda=0.8)


def collect(loss: MAPOCALoss, *, seed: int = 1) -> TensorDict:
    """A collected batch in VMAS's keys: env 1 ends its episode at the second step."""
    generator = torch.Generator().manual_seed(seed)
    done = torch.zeros(*BATCH, 1, dtype=torch.bool)
    done[1, 1] = True
    data = TensorDict(
        {
            ("agents", "observation"): torch.randn(*BATCH, N_AGENTS, OBS_DIM, generator=generator),
            ("next", "agents", "observation"): torch.randn(
                *BATCH, N_AGENTS, OBS_DIM, generator=generator
            ),
            ("next", "agents", "reward"): torch.randn(*BATCH, N_AGENTS, 1, generator=generator),
            ("next", "done"): done,
            ("next", "terminated"): done.clone(),
        },
        batch_size=BATCH,
        names=[None, "time"],
    )
    torch.manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return loss.actor_network(data)


ESTIMATES = ("value_target", "state_value", ("agents", "advantage"), ("agents", "baseline"))


@pytest.mark.parametrize("detach", [False, True])
def test_ppo_examples_value_estimator_call_works(detach):
    loss = make_loss()
    data, expected = collect(loss), collect(loss)
    params = loss.critic_network_params
    loss.value_estimator(
        data,
        params=params.detach() if detach else params,
        target_params=loss.target_critic_network_params,
    )
    loss.value_estimator(expected)
    for key in ESTIMATES:
        torch.testing.assert_close(data[key], expected[key])


def test_critic_params_are_laid_out_and_behave_as_clip_ppo_loss_s():
    loss = make_loss()
    ppo = ClipPPOLoss(make_actor(), loss.value_network)
    params, target = loss.critic_network_params, loss.target_critic_network_params
    assert isinstance(params, TensorDictParams) and isinstance(
        ppo.critic_network_params, TensorDictParams
    )
    assert type(target) is type(ppo.target_critic_network_params)
    # the networks' own tensors, each network's under its name; the target detached, equal
    for name in ("value_network", "baseline_network"):
        network = getattr(loss, name)
        own = dict(network.named_parameters())
        held = {".".join(key): value for key, value in params[name].items(True, True)}
        assert own.keys() <= held.keys()
        assert all(held[key] is parameter for key, parameter in own.items())
        torch.testing.assert_close(target[name], params[name].data)
    for leaf in (target, params.detach(), ppo.target_critic_network_params):
        assert not any(value.requires_grad for value in leaf.values(True, True))
    assert all(value.requires_grad for value in params.values(True, True))
    # not registered: the state dict holds every tensor once, under the networks' names
    assert not any(key.startswith("critic_network_params") for key in loss.state_dict())


def test_other_critic_params_run_the_estimation_with_them():
    loss, moved = make_loss(), make_loss()
    with torch.no_grad():
        for parameter in moved.value_network.parameters():
            parameter.add_(0.1)
        for parameter in moved.baseline_network.parameters():
            parameter.mul_(1.5)
    own = loss.critic_network_params.detach().clone()
    data, expected, mixed = collect(loss), collect(loss), collect(loss)
    loss.value_estimator(
        data,
        params=moved.critic_network_params.detach(),
        target_params=moved.target_critic_network_params,
    )
    moved.value_estimator(expected)
    for key in ESTIMATES:
        torch.testing.assert_close(data[key], expected[key])
    # the networks get their own back
    assert (loss.critic_network_params.detach() == own).all()
    # target_params give V(s_{t+1}) alone: the old value and baselines are params'
    loss.value_estimator(mixed, target_params=moved.target_critic_network_params)
    own_estimate = loss.value_estimator(collect(loss))
    for key in ("state_value", ("agents", "baseline")):
        torch.testing.assert_close(mixed[key], own_estimate[key])
    assert not torch.allclose(mixed["value_target"], own_estimate["value_target"])
    with pytest.raises(ValueError, match="params must be laid out as loss.critic_network_params"):
        loss.value_estimator(data, params=TensorDict.from_module(loss.value_network))


def test_each_pass_encodes_every_agent_once_per_critic():
    """The estimation pass runs V on the collected and the next states and the baselines on
    the collected ones; a loss call runs each once; every encoder sees K agents per sample."""
    loss = make_loss()
    data = collect(loss)
    rows: dict[str, list[int]] = {}
    encoders = {
        "value": loss.value_network.module.encoder,
        "own_state": loss.baseline_network.module.own_state,
        "other_state_action": loss.baseline_network.module.other_state_action,
    }
    for name, encoder in encoders.items():
        encoder.register_forward_hook(
            lambda module, inputs, output, name=name: rows.setdefault(name, []).append(
                inputs[0].shape[:-1].numel()
            )
        )
    loss.value_estimator(data)
    agents = N_ENVS * N_STEPS * N_AGENTS
    assert rows == {
        "value": [agents, agents],
        "own_state": [agents],
        "other_state_action": [agents],
    }
    rows.clear()
    loss(data[:, :3].reshape(-1))
    agents = N_ENVS * 3 * N_AGENTS
    assert rows == {"value": [agents], "own_state": [agents], "other_state_action": [agents]}


def test_in_keys_are_exactly_what_the_two_passes_need():
    loss = make_loss()
    data = collect(loss)
    assert ("agents", "mask") not in loss.in_keys  # optional: VMAS's data has none
    selected = data.select(*loss.in_keys)  # strict: every listed key is there
    loss.value_estimator(selected)
    loss.value_estimator(data)
    torch.testing.assert_close(loss(selected.reshape(-1)), loss(data.reshape(-1)))
    for key in loss.in_keys:
        with pytest.raises(KeyError):
            without = data.select(*loss.in_keys).exclude(key)
            loss(loss.value_estimator(without).reshape(-1))


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        (("agents", "action_log_prob"), r"\('agents', 'action_log_prob'\).*\[\*B, K\]"),
        # the baseline network reads the action first, and names it too
        (("agents", "action"), r"\('agents', 'action'\).*\[\*B, K, 2\]"),
        (("next", "agents", "reward"), r"\('next', 'agents', 'reward'\).*\[\*B, K, 1\]"),
        (("next", "done"), r"\('next', 'done'\).*\[\*B, 1\]"),
        (("next", "terminated"), r"\('next', 'terminated'\).*\[\*B, 1\]"),
        ("value_target", r"'value_target'.*\[\*B, 1\].*value_estimator"),
        ("state_value", r"'state_value'.*\[\*B, 1\].*value_estimator"),
        (("agents", "baseline"), r"\('agents', 'baseline'\).*\[\*B, K, 1\].*value_estimator"),
    ],
)
def test_a_missing_input_raises_an_error_naming_the_key_and_shape(key, expected):
    loss = make_loss()
    data = collect(loss)
    if key in ("value_target", "state_value", ("agents", "baseline")):
        loss.value_estimator(data)
    with pytest.raises(KeyError, match=expected):
        loss(data.exclude(key))


@pytest.mark.parametrize(
    ("key", "shape", "expected"),
    [
        (
            ("agents", "action_log_prob"),
            [*BATCH, 4],
            r"'action_log_prob'.*\[2, 4, 3\].*\[2, 4, 4\]",
        ),
        (("agents", "action"), [*BATCH, 4, ACTION_DIM], r"'action'.*\[2, 4, 3\].*\[2, 4, 4, 2\]"),
        (("next", "agents", "reward"), [*BATCH, 4, 1], r"'reward'.*\[2, 4, 3, 1\].*\[2, 4, 4, 1\]"),
        (("next", "done"), [*BATCH, 2], r"'done'.*\[2, 4, 1\].*\[2, 4, 2\]"),
        ("value_target", [*BATCH, 2], r"'value_target'.*\[2, 4, 1\].*\[2, 4, 2\]"),
        (("agents", "advantage"), [*BATCH, N_AGENTS, 2], r"'advantage'.*\[2, 4, 3, 1\]"),
    ],
)
def test_a_mis_shaped_input_raises_an_error_naming_the_key_and_shape(key, shape, expected):
    loss = make_loss()
    data = collect(loss)
    if key in ("value_target", ("agents", "advantage")):
        loss.value_estimator(data)
    # the group's batch is [*B] here, so a tensor of another agent count fits in it
    data.set(key, torch.zeros(shape, dtype=data.get(key).dtype))
    with pytest.raises(ValueError, match=expected):
        loss(data)


def test_a_per_agent_value_is_refused_with_what_to_do():
    torch.manual_seed(0)
    mappo_critic = TensorDictModule(  # torchrl's MAPPO critic: one value per agent
        MultiAgentMLP(OBS_DIM, 1, N_AGENTS, centralized=True, share_params=True, depth=1),
        in_keys=[("agents", "observation")],
        out_keys=[("agents", "state_value")],
    )
    loss = make_loss(mappo_critic)
    data = collect(loss)
    with pytest.raises(KeyError, match=r"no 'state_value'.*\[\*B, 1\].*set_keys.*pooled"):
        loss.value_estimator(data)
    loss.set_keys(value=("agents", "state_value"))
    with pytest.raises(ValueError, match=r"per agent.*\[2, 4, 3, 1\].*\[2, 4, 1\].*CentralValue"):
        loss.value_estimator(data)


def test_a_baseline_network_writing_elsewhere_is_named():
    loss = make_loss()
    loss.set_keys(baseline=("agents", "counterfactual"))
    with pytest.raises(KeyError, match=r"no \('agents', 'counterfactual'\).*'baseline'\)\]"):
        loss.value_estimator(collect(loss))


def train(loss: MAPOCALoss, terms: list[str] | None, iterations: int = 3) -> list[str]:
    """A few updates that back-propagate ``terms`` (every ``loss_*`` term if None); returns
    the warnings they raised."""
    optimiser = torch.optim.Adam(loss.parameters(), lr=1e-3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for iteration in range(iterations):
            losses = loss(loss.value_estimator(collect(loss, seed=iteration)).reshape(-1))
            total = sum(
                value
                for key, value in losses.items()
                if (key.startswith("loss_") if terms is None else key in terms)
            )
            optimiser.zero_grad()
            total.backward()
            optimiser.step()
    return [str(warning.message) for warning in caught if "MAPOCALoss" in str(warning.message)]


def baseline_moved(loss: MAPOCALoss, before: list[torch.Tensor]) -> bool:
    after = list(loss.baseline_network.parameters())
    return any(not torch.equal(old, new) for old, new in zip(before, after, strict=True))


def test_a_mappo_loop_that_leaves_the_baseline_out_is_warned_once():
    loss = make_loss()
    before = [p.clone() for p in loss.baseline_network.parameters()]
    caught = train(loss, ["loss_objective", "loss_critic", "loss_entropy"])
    assert len(caught) == 1
    assert "loss_baseline" in caught[0] and "k.startswith('loss_')" in caught[0]
    assert not baseline_moved(loss, before)  # what the warning is about


@pytest.mark.parametrize(
    "terms",
    [
        None,  # the documented sum of every loss_* term
        ["loss_critic", "loss_baseline"],  # a critic-only step, as the trainer's warm-up makes
        ["loss_objective", "loss_entropy"],  # a policy-only step
    ],
)
def test_loops_that_train_the_baseline_or_no_critic_are_not_warned(terms):
    loss = make_loss()
    before = [p.clone() for p in loss.baseline_network.parameters()]
    assert train(loss, terms) == []
    assert baseline_moved(loss, before) == (terms is None or "loss_baseline" in terms)


def test_defaults_are_clip_ppo_loss_s_but_for_the_three_the_docstring_explains():
    loss = make_loss()
    ppo = ClipPPOLoss(make_actor(), loss.value_network)
    assert float(loss.clip_epsilon) == float(ppo.clip_epsilon)
    assert float(loss.entropy_coeff) == float(ppo.entropy_coeff)
    assert float(loss.value_coeff) == float(ppo.critic_coeff)
    assert loss.loss_critic_type == ppo.loss_critic_type
    assert loss.clip_value is None and ppo.clip_value is None
    assert loss.normalize_advantage and not ppo.normalize_advantage
    for default in ("normalize_advantage=True", "baseline_coeff=0.5", "max_log_ratio=8.0"):
        assert f"``{default}``" in MAPOCALoss.__doc__
    assert (loss.normalize_advantage, float(loss.baseline_coeff), loss.max_log_ratio) == (
        True,
        0.5,
        8.0,
    )


def compile_as_the_readme_does(loss: MAPOCALoss, backend) -> None:
    """The README's torch.compile recipe: the critics' networks (for the estimation pass) and
    the loss (for the mini-batches)."""
    loss.value_network.module.compile(backend=backend)
    loss.baseline_network.module.compile(backend=backend)
    loss.compile(backend=backend)


def test_the_compiled_loss_gives_the_eager_results_and_compiles_once():
    # TorchDynamo and AOTAutograd as torch.compile runs them, without Inductor's code
    # generation (a minute on the CPU): the graphs' results are the eager ones.
    counter = CompileCounterWithBackend("aot_eager")
    eager, compiled = make_loss(), make_loss()
    compile_as_the_readme_does(compiled, counter)
    pair = (eager, compiled)
    optimisers = [torch.optim.Adam(loss.parameters(), lr=1e-2) for loss in pair]
    for iteration in range(2):
        batches = [loss.value_estimator(collect(loss, seed=iteration)) for loss in pair]
        for key in ESTIMATES:
            torch.testing.assert_close(batches[1][key], batches[0][key])
        results = []
        for loss, optimiser, data in zip(pair, optimisers, batches, strict=True):
            losses = loss(data.reshape(-1))
            optimiser.zero_grad()
            sum(value for key, value in losses.items() if key.startswith("loss_")).backward()
            results.append((losses, [p.grad.clone() for p in loss.parameters()]))
            optimiser.step()
        torch.testing.assert_close(results[1][0], results[0][0])
        torch.testing.assert_close(results[1][1], results[0][1])
        if iteration == 0:
            compiled_frames = counter.frame_count
    assert compiled_frames > 0
    assert counter.frame_count == compiled_frames  # the second update recompiled nothing


def test_the_compiled_loss_still_warns_of_a_baseline_left_out():
    loss = make_loss()
    loss.compile(backend="aot_eager")
    assert len(train(loss, ["loss_objective", "loss_critic", "loss_entropy"])) == 1
