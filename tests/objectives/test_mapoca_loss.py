"""MAPOCALoss against a from-scratch reference, and its contracts: keys, masks, shared trunks."""

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import (
    IndependentNormal,
    NormalParamExtractor,
    ProbabilisticActor,
    recurrent_mode,
)
from torchrl.objectives import ValueEstimators

from terrashift_rl.objectives import MAPOCALoss, ValueNormalizer, mapoca

OBS_DIM, ACTION_DIM, EMBED_DIM = 3, 2, 4
N_ENVS, N_STEPS, N_AGENTS = 2, 3, 2
GAMMA, LMBDA = 0.9, 0.8
CLIP_EPSILON, CLIP_VALUE, ENTROPY_COEFF, VALUE_COEFF, BASELINE_COEFF = 0.1, 0.05, 0.01, 1.0, 0.5
TOLERANCE = {"rtol": 1e-5, "atol": 1e-6}


def masked_agent_mean(features: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    weight = mask.unsqueeze(-1).to(features.dtype)
    return (features * weight).sum(-2) / weight.sum(-2).clamp_min(1)


class ValueHead(nn.Module):
    """V from the mean embedding of the present agents."""

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(EMBED_DIM, 1)

    def forward(self, embedding: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.linear(masked_agent_mean(embedding, mask))


class BaselineHead(nn.Module):
    """b_i from g(e_i) and the mean of f(e_j, a_j) over the other present agents."""

    def __init__(self) -> None:
        super().__init__()
        self.own = nn.Linear(EMBED_DIM, EMBED_DIM)
        self.others = nn.Linear(EMBED_DIM + ACTION_DIM, EMBED_DIM)
        self.head = nn.Linear(EMBED_DIM, 1)

    def forward(
        self, embedding: torch.Tensor, action: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        weight = mask.unsqueeze(-1).to(embedding.dtype)
        others = self.others(torch.cat([embedding, action], -1)) * weight
        count = (weight.sum(-2, keepdim=True) - weight).clamp_min(1)
        pooled = (others.sum(-2, keepdim=True) - others) / count
        return self.head(torch.tanh(self.own(embedding) + pooled))


def make_modules(seed: int = 0) -> nn.ModuleDict:
    torch.manual_seed(seed)
    return nn.ModuleDict(
        {
            "trunk": nn.Sequential(nn.Linear(OBS_DIM, EMBED_DIM), nn.Tanh()),
            "policy": nn.Sequential(nn.Linear(EMBED_DIM, 2 * ACTION_DIM), NormalParamExtractor()),
            "value": ValueHead(),
            "baseline": BaselineHead(),
        }
    )


def wrap(
    modules: nn.ModuleDict,
    *,
    group: str = "agents",
    action: str = "action",
    mask: str = "mask",
    value_key: str = "state_value",
    baseline: str = "baseline",
    distribution: type = IndependentNormal,
    heads_read_embedding: bool = True,
) -> tuple[ProbabilisticActor, TensorDictModuleBase, TensorDictModuleBase, TensorDictModule]:
    """Actor, value and baseline networks sharing ``modules["trunk"]``."""
    embedding = (group, "embedding")
    trunk = TensorDictModule(
        modules["trunk"], in_keys=[(group, "observation")], out_keys=[embedding]
    )
    policy = TensorDictModule(
        modules["policy"], in_keys=[embedding], out_keys=[(group, "loc"), (group, "scale")]
    )
    actor = ProbabilisticActor(
        TensorDictSequential(trunk, policy),
        in_keys=[(group, "loc"), (group, "scale")],
        out_keys=[(group, action)],
        distribution_class=distribution,
        return_log_prob=True,
    )
    value = TensorDictModule(
        modules["value"], in_keys=[embedding, (group, mask)], out_keys=[value_key]
    )
    baseline_net = TensorDictModule(
        modules["baseline"],
        in_keys=[embedding, (group, action), (group, mask)],
        out_keys=[(group, baseline)],
    )
    if heads_read_embedding:
        return actor, value, baseline_net, trunk
    return (
        actor,
        TensorDictSequential(trunk, value),
        TensorDictSequential(trunk, baseline_net),
        trunk,
    )


def make_batch(actor: ProbabilisticActor, *, n_agents: int = N_AGENTS, seed: int = 1) -> TensorDict:
    """Two envs, three steps: env 0 is truncated at t=1 and restarts; env 1 terminates at t=2."""
    generator = torch.Generator().manual_seed(seed)
    batch = [N_ENVS, N_STEPS]
    done = torch.zeros(*batch, 1, dtype=torch.bool)
    terminated = torch.zeros(*batch, 1, dtype=torch.bool)
    done[0, 1] = True
    done[1, 2] = terminated[1, 2] = True
    observation = torch.randn(*batch, n_agents, OBS_DIM, generator=generator)
    # Within an episode the next state of step t is the state of step t + 1; after a done, and
    # at the end of the batch, it is a final state the agents never act in.
    next_observation = torch.randn(*batch, n_agents, OBS_DIM, generator=generator)
    goes_on = ~done[:, :-1, 0]
    next_observation[:, :-1][goes_on] = observation[:, 1:][goes_on]
    data = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": observation,
                    "mask": torch.ones(*batch, n_agents, dtype=torch.bool),
                },
                batch_size=[*batch, n_agents],
            ),
            "next": TensorDict(
                {
                    "agents": TensorDict(
                        {
                            "observation": next_observation,
                            "reward": torch.randn(*batch, n_agents, 1, generator=generator),
                            "mask": torch.ones(*batch, n_agents, dtype=torch.bool),
                        },
                        batch_size=[*batch, n_agents],
                    ),
                    "done": done,
                    "terminated": terminated,
                },
                batch_size=batch,
            ),
        },
        batch_size=batch,
    )
    torch.manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        actor(data)
    return data


def perturb(modules: nn.Module, *, scale: float = 0.3, seed: int = 2) -> None:
    """Stands in for an optimiser step between the value-estimation pass and the loss."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in modules.parameters():
            parameter.add_(scale * torch.randn(parameter.shape, generator=generator))


def make_loss(actor, value, baseline, **kwargs) -> MAPOCALoss:
    options = {
        "clip_epsilon": CLIP_EPSILON,
        "entropy_coeff": ENTROPY_COEFF,
        "value_coeff": VALUE_COEFF,
        "baseline_coeff": BASELINE_COEFF,
        "clip_value": CLIP_VALUE,
        "normalize_advantage": False,
    }
    options.update(kwargs)
    loss = MAPOCALoss(actor, value, baseline, **options)
    return loss.make_value_estimator(ValueEstimators.GAE, gamma=GAMMA, lmbda=LMBDA)


# ---------------------------------------------------------------------------------------------
# The from-scratch reference: python loops over envs, steps and agents, calling the raw modules.


def critic_outputs(modules, observation, action, mask):
    """V (float) and b (list of floats) of one step, from the raw modules."""
    embedding = modules["trunk"](observation)
    value = modules["value"](embedding, mask).item()
    baseline = modules["baseline"](embedding, action, mask).squeeze(-1).tolist()
    return value, baseline


def reference_returns(modules, data, *, reduction="mean"):
    """Team λ-returns G[n][t], old V[n][t] and b[n][t][i] by the textbook recursion."""
    with torch.no_grad():
        value, next_value, baseline = {}, {}, {}
        for n in range(N_ENVS):
            for t in range(N_STEPS):
                value[n, t], baseline[n, t] = critic_outputs(
                    modules,
                    data["agents", "observation"][n, t],
                    data["agents", "action"][n, t],
                    data["agents", "mask"][n, t],
                )
                next_value[n, t], _ = critic_outputs(
                    modules,
                    data["next", "agents", "observation"][n, t],
                    data["agents", "action"][n, t],
                    data["next", "agents", "mask"][n, t],
                )
    returns = {}
    for n in range(N_ENVS):
        gae = 0.0
        for t in reversed(range(N_STEPS)):
            present = data["agents", "mask"][n, t].tolist()
            rewards = [
                r
                for r, p in zip(
                    data["next", "agents", "reward"][n, t, :, 0].tolist(), present, strict=True
                )
                if p
            ]
            team_reward = sum(rewards) / (len(rewards) if reduction == "mean" else 1)
            not_terminated = 1.0 - float(data["next", "terminated"][n, t])
            not_done = 1.0 - float(data["next", "done"][n, t])
            delta = team_reward + GAMMA * not_terminated * next_value[n, t] - value[n, t]
            gae = delta + GAMMA * LMBDA * not_done * gae
            returns[n, t] = gae + value[n, t]
    return returns, value, baseline


def distance(error: float, loss_critic_type: str) -> float:
    if loss_critic_type == "l2":
        return error**2
    return 0.5 * error**2 if abs(error) < 1 else abs(error) - 0.5


def clipped_regression(estimate, old, target, loss_critic_type):
    clipped = old + min(max(estimate - old, -CLIP_VALUE), CLIP_VALUE)
    loss = max(
        distance(estimate - target, loss_critic_type), distance(clipped - target, loss_critic_type)
    )
    return loss, clipped != estimate


def reference_losses(modules, data, *, distribution, per_dimension_ratio, loss_critic_type):
    """Every loss term, by loops, from the current modules and the stored old estimates."""
    objective, value_loss, baseline_loss, entropy = [], [], [], []
    counts = {"ratio_clipped": 0, "ratio_kept": 0, "log_ratio_clamped": 0, "value_clipped": 0}
    with torch.no_grad():
        for n in range(N_ENVS):
            for t in range(N_STEPS):
                observation = data["agents", "observation"][n, t]
                action = data["agents", "action"][n, t]
                mask = data["agents", "mask"][n, t]
                target = data["value_target"][n, t].item()
                value, baseline = critic_outputs(modules, observation, action, mask)
                loss, clipped = clipped_regression(
                    value, data["state_value"][n, t].item(), target, loss_critic_type
                )
                value_loss.append(loss)
                counts["value_clipped"] += clipped
                loc, scale = modules["policy"](modules["trunk"](observation))
                for i in range(N_AGENTS):
                    loss, clipped = clipped_regression(
                        baseline[i],
                        data["agents", "baseline"][n, t, i].item(),
                        target,
                        loss_critic_type,
                    )
                    baseline_loss.append(loss)
                    counts["value_clipped"] += clipped
                    normal = torch.distributions.Normal(loc[i], scale[i])
                    log_prob = normal.log_prob(action[i]).tolist()
                    old_log_prob = data["agents", "action_log_prob"][n, t, i]
                    old_log_prob = (
                        old_log_prob.tolist() if old_log_prob.ndim else [old_log_prob.item()]
                    )
                    if per_dimension_ratio:
                        log_ratios = [
                            lp - old for lp, old in zip(log_prob, old_log_prob, strict=True)
                        ]
                    else:
                        log_ratios = [sum(log_prob) - sum(old_log_prob)]
                    advantage = data["agents", "advantage"][n, t, i].item()
                    surrogates = []
                    for log_ratio in log_ratios:
                        counts["log_ratio_clamped"] += abs(log_ratio) > 8
                        ratio = math.exp(min(max(log_ratio, -8.0), 8.0))
                        clipped_ratio = min(max(ratio, 1 - CLIP_EPSILON), 1 + CLIP_EPSILON)
                        counts["ratio_clipped" if clipped_ratio != ratio else "ratio_kept"] += 1
                        surrogates.append(min(ratio * advantage, clipped_ratio * advantage))
                    objective.append(sum(surrogates) / len(surrogates))
                    entropy.append(normal.entropy().sum().item())

    def mean(values):
        return sum(values) / len(values)

    losses = {
        "loss_objective": -mean(objective),
        "loss_critic": VALUE_COEFF * mean(value_loss),
        "loss_baseline": BASELINE_COEFF * mean(baseline_loss),
        "loss_entropy": -ENTROPY_COEFF * mean(entropy),
        "entropy": mean(entropy),
    }
    return losses, counts


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("distribution", "per_dimension_ratio", "loss_critic_type", "reduction"),
    [
        (IndependentNormal, False, "smooth_l1", "mean"),
        (IndependentNormal, False, "l2", "sum"),
        (torch.distributions.Normal, False, "smooth_l1", "mean"),
        (torch.distributions.Normal, True, "l2", "mean"),
    ],
)
def test_matches_hand_computed_reference(
    distribution, per_dimension_ratio, loss_critic_type, reduction
):
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules, distribution=distribution)
    data = make_batch(actor)
    loss = make_loss(
        actor,
        value,
        baseline,
        per_dimension_ratio=per_dimension_ratio,
        loss_critic_type=loss_critic_type,
        team_reward_reduction=reduction,
    )

    returns, old_value, old_baseline = reference_returns(modules, data, reduction=reduction)
    loss.value_estimator(data)
    for n in range(N_ENVS):
        for t in range(N_STEPS):
            torch.testing.assert_close(
                data["value_target"][n, t].item(), returns[n, t], **TOLERANCE
            )
            torch.testing.assert_close(
                data["state_value"][n, t].item(), old_value[n, t], **TOLERANCE
            )
            for i in range(N_AGENTS):
                torch.testing.assert_close(
                    data["agents", "baseline"][n, t, i].item(), old_baseline[n, t][i], **TOLERANCE
                )
                torch.testing.assert_close(
                    data["agents", "advantage"][n, t, i].item(),
                    returns[n, t] - old_baseline[n, t][i],
                    **TOLERANCE,
                )

    # One sample far off-policy, so the ±8 clamp of the log-ratio is exercised.
    data["agents", "action_log_prob"][0, 0, 0] -= 20.0
    perturb(modules)
    expected, counts = reference_losses(
        modules,
        data,
        distribution=distribution,
        per_dimension_ratio=per_dimension_ratio,
        loss_critic_type=loss_critic_type,
    )
    assert counts["ratio_clipped"] and counts["ratio_kept"], counts
    assert counts["log_ratio_clamped"] and counts["value_clipped"], counts

    output = loss(data)
    for key, value in expected.items():
        torch.testing.assert_close(output[key].item(), value, **TOLERANCE)
    assert not any(
        value.requires_grad for key, value in output.items() if not key.startswith("loss")
    )


def test_returns_bootstrap_on_truncation_but_not_termination():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)
    loss.value_estimator(data)
    returns = data["value_target"].clone()

    shifted = data.clone()
    # A different next observation changes V(s') only: it matters at the truncated step
    # (env 0, t=1) and before it, and must not at the terminal step (env 1, t=2).
    shifted["next", "agents", "observation"][0, 1] += 5.0
    shifted["next", "agents", "observation"][1, 2] += 5.0
    loss.value_estimator(shifted)
    assert not torch.allclose(shifted["value_target"][0, :2], returns[0, :2])
    torch.testing.assert_close(shifted["value_target"][1], returns[1])

    # The truncation stops the λ-recursion: the next episode's reward does not flow back.
    shifted = data.clone()
    shifted["next", "agents", "reward"][0, 2] += 5.0
    loss.value_estimator(shifted)
    torch.testing.assert_close(shifted["value_target"][0, :2], returns[0, :2])
    assert not torch.allclose(shifted["value_target"][0, 2], returns[0, 2])


def test_td_lambda_gives_the_reference_returns():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline).make_value_estimator(
        ValueEstimators.TDLambda, gamma=GAMMA, lmbda=LMBDA
    )
    returns, _, _ = reference_returns(modules, data)
    loss.value_estimator(data)
    expected = torch.tensor([[returns[n, t] for t in range(N_STEPS)] for n in range(N_ENVS)])
    torch.testing.assert_close(data["value_target"].squeeze(-1), expected, **TOLERANCE)


@pytest.mark.parametrize("reuse_root_values", [False, True])
def test_value_estimation_in_pieces_gives_the_same_results(reuse_root_values):
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    whole, pieces = make_batch(actor), make_batch(actor)
    make_loss(actor, value, baseline).value_estimator(whole)
    loss = make_loss(actor, value, baseline).make_value_estimator(
        ValueEstimators.GAE,
        gamma=GAMMA,
        lmbda=LMBDA,
        max_batch=1,
        reuse_root_values=reuse_root_values,
    )
    sizes = []  # elements of every call of the value network
    hook = modules["value"].register_forward_pre_hook(
        lambda module, args: sizes.append(args[0].shape[:-2].numel())
    )
    loss.value_estimator(pieces)
    hook.remove()
    for key in ("state_value", "value_target", ("agents", "baseline"), ("agents", "advantage")):
        torch.testing.assert_close(pieces[key], whole[key], **TOLERANCE)
    # one env's steps at a time; with reuse, "next" runs only where an episode ends or the
    # batch does (3 states: env 0 at t = 1 and 2, env 1 at t = 2), in one call
    expected = [N_STEPS] * N_ENVS * 2 if not reuse_root_values else [N_STEPS] * N_ENVS + [3]
    assert sizes == expected
    with pytest.raises(ValueError, match="max_batch"):
        loss.make_value_estimator(ValueEstimators.GAE, max_batch=0)


@pytest.mark.parametrize(
    ("piece_elements", "piece_sizes"),
    [(6, [6]), (4, [3, 3]), (2, [3, 3])],  # the whole batch; one env's steps; at least a row
)
def test_value_estimation_runs_in_bounded_pieces_by_default(
    monkeypatch, piece_elements, piece_sizes
):
    # By default the networks run on whole rows that hold at most AUTO_PIECE_ELEMENTS elements:
    # the same results as one pass.
    monkeypatch.setattr(mapoca, "AUTO_PIECE_ELEMENTS", piece_elements)
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    sizes = []  # elements of every call of the value network
    hook = modules["value"].register_forward_pre_hook(
        lambda module, args: sizes.append(args[0].shape[:-2].numel())
    )
    whole, pieces = make_batch(actor), make_batch(actor)
    loss = make_loss(actor, value, baseline)
    one_pass = make_loss(actor, value, baseline).make_value_estimator(
        ValueEstimators.GAE, gamma=GAMMA, lmbda=LMBDA, max_batch=None
    )
    one_pass.value_estimator(whole)
    assert sizes == [N_ENVS * N_STEPS] * 2  # the states, then the next states
    sizes.clear()
    assert loss.value_estimator.max_batch == "auto"
    loss.value_estimator(pieces)
    hook.remove()
    assert sizes == piece_sizes * 2
    for key in ("state_value", "value_target", ("agents", "baseline"), ("agents", "advantage")):
        torch.testing.assert_close(pieces[key], whole[key], **TOLERANCE)
    with pytest.raises(ValueError, match="max_batch"):
        loss.make_value_estimator(ValueEstimators.GAE, max_batch="all")


@pytest.mark.parametrize("value_type", [ValueEstimators.GAE, ValueEstimators.TDLambda])
@pytest.mark.parametrize(
    ("reuse_root_values", "reads"), [(False, {}), (True, {"aten::nonzero": 1})]
)
def test_the_value_estimation_pass_reads_nothing_on_the_host(
    value_type, reuse_root_values, reads, host_reads
):
    # On CUDA each read waits for the device. The pass makes none, in pieces, with masks and
    # return statistics, but one where it reuses root values: how many states follow an episode's
    # end (the second pass's size).
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    assert data["next", "done"][:, :-1].any()  # an episode ends inside the batch
    loss = make_loss(
        actor, value, baseline, normalize_advantage=True, value_normalizer=ValueNormalizer()
    ).make_value_estimator(
        value_type, gamma=GAMMA, lmbda=LMBDA, max_batch=1, reuse_root_values=reuse_root_values
    )
    assert host_reads(loss.value_estimator, data) == reads
    assert data["agents", "advantage"].isfinite().all()


def test_reusing_root_values_gives_the_same_results():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    plain, reused = make_batch(actor), make_batch(actor)
    make_loss(actor, value, baseline).value_estimator(plain)
    loss = make_loss(actor, value, baseline).make_value_estimator(
        ValueEstimators.GAE, gamma=GAMMA, lmbda=LMBDA, reuse_root_values=True
    )
    loss.value_estimator(reused)
    for key in ("state_value", "value_target", ("agents", "baseline"), ("agents", "advantage")):
        torch.testing.assert_close(reused[key], plain[key], **TOLERANCE)

    # Within an episode "next" is not read: V(s_{t+1}) comes from the root of step t + 1 ...
    corrupted = make_batch(actor)
    corrupted["next", "agents", "observation"][1, 0] += 5.0  # env 1 goes on after t=0
    loss.value_estimator(corrupted)
    torch.testing.assert_close(corrupted["value_target"], plain["value_target"], **TOLERANCE)
    # ... but at a truncation (env 0, t=1) and at the batch's last step it is.
    for step in (1, 2):
        corrupted = make_batch(actor)
        corrupted["next", "agents", "observation"][0, step] += 5.0
        loss.value_estimator(corrupted)
        assert not torch.allclose(
            corrupted["value_target"][0, step], plain["value_target"][0, step]
        )


def test_reusing_the_actors_outputs_gives_the_same_results():
    # A collected batch holds the embedding the actor wrote: with reuse_actor_outputs the heads
    # read it there, and the trunk runs on the next states alone.
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    plain, reused = make_batch(actor), make_batch(actor)
    options = {"gamma": GAMMA, "lmbda": LMBDA, "reuse_root_values": True}
    make_loss(actor, value, baseline).make_value_estimator(**options).value_estimator(plain)
    loss = make_loss(actor, value, baseline).make_value_estimator(
        **options, reuse_actor_outputs=True
    )
    sizes = []  # elements of every call of the trunk
    hook = modules["trunk"].register_forward_pre_hook(
        lambda module, args: sizes.append(args[0].shape[:-2].numel())
    )
    loss.value_estimator(reused)
    hook.remove()
    assert sizes == [3]  # "next" where an episode ends or the batch does
    for key in ("state_value", "value_target", ("agents", "baseline"), ("agents", "advantage")):
        torch.testing.assert_close(reused[key], plain[key], **TOLERANCE)

    stale = make_batch(actor)  # what is read is the stored embedding
    stale["agents", "embedding"] += 1.0
    loss.value_estimator(stale)
    assert not torch.allclose(stale["state_value"], plain["state_value"])
    del stale["agents", "embedding"]
    with pytest.raises(KeyError, match="reuse_actor_outputs.*'embedding'"):
        loss.value_estimator(stale)


def test_value_normalizer_trains_critics_on_normalised_returns():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    normalizer = ValueNormalizer(decay=0.5)
    normalizer.update(torch.tensor([2.0, 5.0, -1.0]))
    mean, std = (s.item() for s in normalizer.statistics())
    loss = make_loss(actor, value, baseline, value_normalizer=normalizer, clip_value=None)
    normalised = make_batch(actor)
    loss.value_estimator(normalised)

    # The same critics with their outputs mapped to return units, and no normaliser.
    raw_modules = make_modules()
    raw_value_head, raw_baseline_head = raw_modules["value"], raw_modules["baseline"]
    raw_actor, _, _, _ = wrap(raw_modules)
    denormalised_value = TensorDictModule(
        lambda e, m: raw_value_head(e, m) * std + mean,
        in_keys=[("agents", "embedding"), ("agents", "mask")],
        out_keys=["state_value"],
    )
    denormalised_baseline = TensorDictModule(
        lambda e, a, m: raw_baseline_head(e, a, m) * std + mean,
        in_keys=[("agents", "embedding"), ("agents", "action"), ("agents", "mask")],
        out_keys=[("agents", "baseline")],
    )
    raw = make_batch(raw_actor)
    make_loss(raw_actor, denormalised_value, denormalised_baseline).value_estimator(raw)

    torch.testing.assert_close(normalised["value_target"], raw["value_target"], **TOLERANCE)
    torch.testing.assert_close(
        normalised["agents", "advantage"], raw["agents", "advantage"], **TOLERANCE
    )
    # stored old estimates are the critics' own outputs
    torch.testing.assert_close(
        normalised["state_value"] * std + mean, raw["state_value"], **TOLERANCE
    )

    # The pass moved the statistics towards the new targets (debiased EMA, decay 0.5).
    targets = raw["value_target"]
    first = torch.tensor([2.0, 5.0, -1.0])
    expected_mean = (0.25 * first.mean() + 0.5 * targets.mean()) / 0.75
    expected_square = (0.25 * first.square().mean() + 0.5 * targets.square().mean()) / 0.75
    new_mean, new_std = normalizer.statistics()
    torch.testing.assert_close(new_mean, expected_mean)
    torch.testing.assert_close(new_std, (expected_square - expected_mean**2).sqrt())

    # The value loss compares the critic's output with the target in normalised units.
    out = loss(normalised)
    with torch.no_grad():
        data = normalised.copy()
        actor.get_dist(data)
        current_value = value(data)["state_value"]
    target = (normalised["value_target"] - new_mean) / new_std
    expected_loss = VALUE_COEFF * nn.functional.smooth_l1_loss(current_value, target)
    torch.testing.assert_close(out["loss_critic"], expected_loss, **TOLERANCE)


def test_unsupported_value_estimator_is_refused():
    actor, value, baseline, _ = wrap(make_modules())
    loss = MAPOCALoss(actor, value, baseline)
    with pytest.raises(NotImplementedError, match="TDLambda"):
        loss.make_value_estimator(ValueEstimators.TD0)


def test_advantage_normalisation_is_over_all_steps_and_agents():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    returns, _, old_baseline = reference_returns(modules, data)
    raw = torch.tensor(
        [
            [
                [returns[n, t] - old_baseline[n, t][i] for i in range(N_AGENTS)]
                for t in range(N_STEPS)
            ]
            for n in range(N_ENVS)
        ]
    )
    make_loss(actor, value, baseline, normalize_advantage=True).value_estimator(data)
    expected = (raw - raw.mean()) / (raw.std(correction=0) + 1e-8)
    torch.testing.assert_close(data["agents", "advantage"].squeeze(-1), expected, **TOLERANCE)


@pytest.mark.parametrize("weight", [0.0, 0.25, 1.0])
def test_counterfactual_weight_blends_the_value_into_the_advantages_reference(weight):
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    returns, old_value, old_baseline = reference_returns(modules, data)
    expected = torch.tensor(
        [
            [
                [
                    returns[n, t]
                    - (weight * old_baseline[n, t][i] + (1 - weight) * old_value[n, t])
                    for i in range(N_AGENTS)
                ]
                for t in range(N_STEPS)
            ]
            for n in range(N_ENVS)
        ]
    )
    mask = data["agents", "mask"]
    loss = make_loss(actor, value, baseline)
    loss.counterfactual_weight = weight  # assigned in place, as a schedule does
    loss.value_estimator(data)
    advantage = data["agents", "advantage"].squeeze(-1)
    torch.testing.assert_close(advantage[mask], expected[mask], **TOLERANCE)
    # the baselines still train: their loss does not depend on the weight
    assert loss(data)["loss_baseline"].item() > 0.0


@pytest.mark.parametrize("weight", [-0.1, 1.5, True])
def test_counterfactual_weight_outside_0_1_is_refused(weight):
    actor, value, baseline, _ = wrap(make_modules())
    with pytest.raises(ValueError, match="counterfactual_weight must be a float in"):
        MAPOCALoss(actor, value, baseline, counterfactual_weight=weight)


def test_forward_runs_the_value_estimation_pass_when_advantages_are_missing():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)
    lazy = loss(data.clone())
    loss.value_estimator(data)
    eager = loss(data)
    for key, value in eager.items():
        torch.testing.assert_close(lazy[key], value)
    assert ("agents", "advantage") in data.keys(include_nested=True)


def test_set_keys_remaps_every_key():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)

    team_actor, team_value, team_baseline, _ = wrap(
        modules,
        group="team",
        action="move",
        mask="present",
        value_key="team_value",
        baseline="counterfactual",
    )
    team_loss = make_loss(team_actor, team_value, team_baseline)
    team_loss.set_keys(
        group="team",
        sample_log_prob=("team", "move_lp"),
        reward="team_reward",
        done=("team", "done"),
        terminated=("team", "terminated"),
        mask=("team", "present"),
        value="team_value",
        baseline=("team", "counterfactual"),
        value_target="team_return",
        advantage=("team", "credit"),
    )
    assert team_loss.tensor_keys.action == ("team", "move")  # read from the actor

    per_agent = [*data.batch_size, N_AGENTS]
    team_data = TensorDict(
        {
            "team": TensorDict(
                {
                    "observation": data["agents", "observation"],
                    "present": data["agents", "mask"],
                    "move": data["agents", "action"],
                    "move_lp": data["agents", "action_log_prob"],
                },
                batch_size=per_agent,
            ),
            "next": TensorDict(
                {
                    "team": TensorDict(
                        {
                            "observation": data["next", "agents", "observation"],
                            "present": data["next", "agents", "mask"],
                            "done": data["next", "done"].unsqueeze(-2).expand(*per_agent, 1),
                            "terminated": data["next", "terminated"]
                            .unsqueeze(-2)
                            .expand(*per_agent, 1),
                        },
                        batch_size=per_agent,
                    ),
                    "team_reward": data["next", "agents", "reward"].mean(-2),
                },
                batch_size=data.batch_size,
            ),
        },
        batch_size=data.batch_size,
    )

    loss.value_estimator(data)
    team_loss.value_estimator(team_data)
    for default_key, team_key in [
        ("state_value", "team_value"),
        ("value_target", "team_return"),
        (("agents", "baseline"), ("team", "counterfactual")),
        (("agents", "advantage"), ("team", "credit")),
    ]:
        torch.testing.assert_close(team_data[team_key], data[default_key])
    written = set(team_data.keys(include_nested=True, leaves_only=True))
    assert not written & {
        "state_value",
        "value_target",
        ("team", "advantage"),
        ("team", "baseline"),
    }

    perturb(modules)
    expected, output = loss(data), team_loss(team_data)
    for key, value in expected.items():
        torch.testing.assert_close(output[key], value)


def test_set_keys_group_moves_the_group_keys_only():
    actor, value, baseline, _ = wrap(make_modules())
    loss = MAPOCALoss(actor, value, baseline)
    loss.set_keys(group="team", baseline=("critics", "baseline"))
    keys = loss.tensor_keys
    assert keys.group == "team"
    assert (keys.action, keys.mask, keys.reward, keys.advantage) == (
        ("team", "action"),
        ("team", "mask"),
        ("team", "reward"),
        ("team", "advantage"),
    )
    assert keys.baseline == ("critics", "baseline")  # explicit keys win
    assert (keys.value, keys.done) == ("state_value", "done")  # root keys stay
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(observation="obs")


def with_absent_agent(data: TensorDict) -> TensorDict:
    """``data`` plus a third agent, absent everywhere, whose entries are large finite garbage."""
    generator = torch.Generator().manual_seed(3)

    def add_agent(tensor: torch.Tensor, garbage: torch.Tensor) -> torch.Tensor:
        return torch.cat([tensor, garbage.to(tensor.dtype)], dim=2)

    def garbage_like(tensor: torch.Tensor) -> torch.Tensor:
        shape = list(tensor.shape)
        shape[2] = 1
        return 1e3 * torch.randn(shape, generator=generator)

    batch = data.batch_size
    absent = torch.zeros(*batch, 1, dtype=torch.bool)
    extended = data.clone()
    for group in ("agents", ("next", "agents")):
        keys = extended.get(group).keys()
        entries = {
            key: add_agent(extended.get(group).get(key), garbage_like(extended.get(group).get(key)))
            for key in keys
        }
        entries["mask"] = add_agent(data.get(group).get("mask"), absent)
        extended.set(group, TensorDict(entries, batch_size=[*batch, N_AGENTS + 1]))
    return extended


def test_absent_agents_change_nothing():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    extended = with_absent_agent(data)
    assert extended["agents", "observation"].shape[2] == N_AGENTS + 1

    loss = make_loss(actor, value, baseline, normalize_advantage=True)
    loss.value_estimator(data)
    loss.value_estimator(extended)
    for key in ("value_target", "state_value"):
        torch.testing.assert_close(extended[key], data[key])
    for key in (("agents", "baseline"), ("agents", "advantage")):
        torch.testing.assert_close(extended[key][:, :, :N_AGENTS], data[key])
    assert (extended["agents", "advantage"][:, :, N_AGENTS] == 0).all()

    perturb(modules)
    expected, output = loss(data), loss(extended)
    for key, value in expected.items():
        torch.testing.assert_close(output[key], value)


def test_per_agent_done_flags_end_the_team_when_every_present_agent_is_done():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    root_flags = make_loss(actor, value, baseline)
    agent_flags = make_loss(actor, value, baseline)
    agent_flags.set_keys(done=("agents", "done"), terminated=("agents", "terminated"))
    per_agent = [*data.batch_size, N_AGENTS, 1]
    for flag in ("done", "terminated"):
        flags = data["next", flag].unsqueeze(-2).expand(per_agent).clone()
        flags[0, 0, 1] = True  # agent 1 alone ends at env 0, t=0: the team goes on
        flags[1, 2, 1] = False  # at env 1, t=2 the team ends, though agent 1 (absent) does not
        data["next", "agents", flag] = flags
    data["agents", "mask"][1, 2, 1] = False

    for agent_1_present in (False, True):
        data["agents", "mask"][0, 0, 1] = agent_1_present
        expected = data.clone()
        root_flags.value_estimator(expected)
        agent_flags.value_estimator(data)
        torch.testing.assert_close(data["value_target"], expected["value_target"])


# one term at a time on purpose: the warning about a backward pass without loss_baseline is due
@pytest.mark.filterwarnings("ignore:MAPOCALoss. the last backward pass:UserWarning")
@pytest.mark.parametrize("heads_read_embedding", [True, False])
def test_shared_trunk_gets_gradients_from_every_term(heads_read_embedding):
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules, heads_read_embedding=heads_read_embedding)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)
    loss.value_estimator(data)
    perturb(modules)
    trunk_parameters = list(modules["trunk"].parameters())
    for term, own_head in [
        ("loss_objective", "policy"),
        ("loss_critic", "value"),
        ("loss_baseline", "baseline"),
    ]:
        loss.zero_grad(set_to_none=True)
        loss(data)[term].backward()
        for parameter in trunk_parameters:
            assert parameter.grad is not None and parameter.grad.abs().sum() > 0, term
        for head in ("policy", "value", "baseline"):
            grads = [p.grad for p in modules[head].parameters()]
            if head == own_head:
                assert all(g is not None and g.abs().sum() > 0 for g in grads), term
            else:
                assert all(g is None or not g.any() for g in grads), (term, head)


def test_parameters_are_deduplicated():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules, heads_read_embedding=False)
    loss = MAPOCALoss(actor, value, baseline)
    parameters = list(loss.parameters())
    assert len({id(p) for p in parameters}) == len(parameters) == len(list(modules.parameters()))
    trunk_ids = {id(p) for p in modules["trunk"].parameters()}
    assert sum(id(p) in trunk_ids for p in parameters) == len(trunk_ids)
    torch.optim.Adam(loss.parameters())  # a duplicate would make Adam raise


@pytest.mark.parametrize(("heads_read_embedding", "update_calls"), [(True, 1), (False, 3)])
def test_trunk_runs_once_when_heads_read_its_embedding(heads_read_embedding, update_calls):
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules, heads_read_embedding=heads_read_embedding)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)
    calls = []
    modules["trunk"].register_forward_hook(lambda *args: calls.append(1))
    loss.value_estimator(data)
    assert len(calls) == (2 if heads_read_embedding else 3)  # current and next states
    calls.clear()
    loss(data)
    assert len(calls) == update_calls

    other_actor, other_value, other_baseline, _ = wrap(
        modules, heads_read_embedding=not heads_read_embedding
    )
    other = make_loss(other_actor, other_value, other_baseline)
    other_data = data.clone()
    other.value_estimator(other_data)
    perturb(modules)
    expected, output = loss(data), other(other_data)
    for key, value in expected.items():
        torch.testing.assert_close(output[key], value)


def test_coefficients_and_clip_ranges_are_schedulable():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)
    loss.value_estimator(data)
    perturb(modules)
    before = loss(data)

    buffer = loss.entropy_coeff
    loss.entropy_coeff = 0.5
    loss.value_coeff = 2.0 * VALUE_COEFF
    loss.baseline_coeff = 0.0
    loss.clip_epsilon = 1e4
    loss.clip_value = 1e6
    after = loss(data)
    assert loss.entropy_coeff is buffer and loss.entropy_coeff.item() == 0.5
    assert "entropy_coeff" in loss.state_dict()
    torch.testing.assert_close(after["loss_entropy"], -0.5 * before["entropy"])
    assert after["loss_baseline"].item() == 0.0
    assert after["clip_fraction"].item() == 0.0 < before["clip_fraction"].item()
    assert after["value_clip_fraction"].item() == 0.0 < before["value_clip_fraction"].item()


def with_teacher(data: TensorDict, *, seed: int = 4) -> TensorDict:
    """``data`` plus a random teacher action in [-1, 1] for every agent."""
    generator = torch.Generator().manual_seed(seed)
    shape = [*data["agents"].batch_size, ACTION_DIM]
    data["agents", "teacher_action"] = 2 * torch.rand(shape, generator=generator) - 1
    return data


def test_teacher_term_is_the_masked_mean_squared_distance_to_the_teacher():
    coeff = 0.7
    actor, value, baseline, _ = wrap(make_modules())
    data = with_teacher(make_batch(actor))
    data["agents", "mask"][0, 1, 1] = False
    loss = make_loss(actor, value, baseline, teacher_coeff=coeff)
    with torch.no_grad():
        mean = actor.get_dist(data.copy()).mean
    distance = (mean - data["agents", "teacher_action"]).square().sum(-1)
    expected = distance[data["agents", "mask"]].mean()
    assert not torch.isclose(expected, distance.mean())  # the absent agent counts for nothing

    out = loss(data.clone())
    torch.testing.assert_close(out["teacher_distance"], expected)
    torch.testing.assert_close(out["loss_teacher"], coeff * expected)
    assert out["loss_teacher"].requires_grad and not out["teacher_distance"].requires_grad
    # a third agent, absent everywhere, with a garbage teacher action changes nothing
    extended = loss(with_absent_agent(data))
    for key in ("loss_teacher", "teacher_distance"):
        torch.testing.assert_close(extended[key], out[key])


def test_teacher_term_pulls_the_policy_mean_towards_the_teacher():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = with_teacher(make_batch(actor))
    loss = make_loss(actor, value, baseline, teacher_coeff=1.0)
    loss.value_estimator(data)
    loss(data)["loss_teacher"].backward()
    for head in ("trunk", "policy"):
        assert all(
            p.grad is not None and p.grad.abs().sum() > 0 for p in modules[head].parameters()
        )
    for head in ("value", "baseline"):
        assert all(p.grad is None or not p.grad.any() for p in modules[head].parameters())

    optimizer = torch.optim.SGD(modules.parameters(), lr=0.1)
    distances = []
    for _ in range(20):
        out = loss(data)
        distances.append(out["teacher_distance"].item())
        optimizer.zero_grad()
        out["loss_teacher"].backward()
        optimizer.step()
    assert (torch.tensor(distances).diff() < 0).all(), distances  # every step gets closer
    assert distances[-1] < 0.75 * distances[0], distances


def test_teacher_keys_exist_only_with_a_teacher():
    actor, value, baseline, _ = wrap(make_modules())
    data = make_batch(actor)
    teacher_outputs = {"loss_teacher", "teacher_distance"}
    plain = make_loss(actor, value, baseline)
    assert ("agents", "teacher_action") not in plain.in_keys
    assert not teacher_outputs & set(plain.out_keys)
    out = plain(data.clone())  # the batch has no teacher action: none is read
    assert set(out.keys()) == set(plain.out_keys)

    taught = make_loss(actor, value, baseline, teacher_coeff=0.5)
    assert ("agents", "teacher_action") in taught.in_keys
    out = taught(with_teacher(data))
    assert set(out.keys()) == set(taught.out_keys) >= teacher_outputs
    taught.set_keys(group="team")
    assert ("team", "teacher_action") in taught.in_keys


def test_teacher_coeff_is_schedulable():
    actor, value, baseline, _ = wrap(make_modules())
    data = with_teacher(make_batch(actor))
    loss = make_loss(actor, value, baseline, teacher_coeff=1)  # an int, as Hydra may give it
    buffer = loss.teacher_coeff
    loss.teacher_coeff = 0.25
    assert loss.teacher_coeff.item() == 0.25  # a float buffer: fractions are not truncated
    loss.teacher_coeff = 0.0
    out = loss(data)
    assert loss.teacher_coeff is buffer and "teacher_coeff" in loss.state_dict()
    assert out["loss_teacher"].item() == 0.0 < out["teacher_distance"].item()


def test_diagnostics():
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor)
    loss = make_loss(actor, value, baseline)
    loss.value_estimator(data)
    on_policy = loss(data)
    # Before any update the new policy is the old one: every ratio is 1.
    assert on_policy["kl_approx"].abs().item() < 1e-6
    torch.testing.assert_close(on_policy["ESS"].item(), 1.0)
    assert on_policy["clip_fraction"].item() == 0.0
    assert set(on_policy.keys()) == set(loss.out_keys)

    perturb(modules)
    off_policy = loss(data)
    assert off_policy["kl_approx"].item() > 0
    assert 0 < off_policy["ESS"].item() < 1
    current = loss.value_network(actor.get_dist_params(data.copy()))
    value_target, state_value = data["value_target"], current["state_value"]
    expected = 1 - (value_target - state_value).var(correction=0) / value_target.var(correction=0)
    torch.testing.assert_close(off_policy["explained_variance"], expected.detach())


class RecurrentTrunk(nn.Module):
    """e_t = tanh(W x_t + U h_{t-1}), with torchrl's conventions for recurrent state.

    Step mode (collection) zeroes the incoming state at ``is_init``. Recurrent mode runs along
    the last batch dim, starting each row and each ``is_init`` step from the stored state.
    """

    def __init__(self) -> None:
        super().__init__()
        self.input = nn.Linear(OBS_DIM, EMBED_DIM)
        self.recurrent = nn.Linear(EMBED_DIM, EMBED_DIM, bias=False)
        self.modes = []

    def cell(self, observation, hidden):
        return torch.tanh(self.input(observation) + self.recurrent(hidden))

    def forward(self, observation, hidden, is_init):
        self.modes.append(recurrent_mode())
        is_init = is_init[..., None, :]  # [*B, 1, 1] against [*B, K, d]
        if not recurrent_mode():
            embedding = self.cell(observation, torch.where(is_init, 0.0, hidden))
            return embedding, embedding
        outputs, carried = [], None
        for t in range(observation.shape[-3]):
            stored = hidden[..., t, :, :]
            if carried is not None:
                stored = torch.where(is_init[..., t, :, :], stored, carried)
            carried = self.cell(observation[..., t, :, :], stored)
            outputs.append(carried)
        embedding = torch.stack(outputs, -3)
        return embedding, embedding


def test_recurrent_trunk_values_of_next_states_match_collection():
    torch.manual_seed(0)
    trunk_net = RecurrentTrunk()
    modules = make_modules()
    trunk = TensorDictModule(
        trunk_net,
        in_keys=[("agents", "observation"), ("agents", "hidden"), "is_init"],
        out_keys=[("agents", "embedding"), ("next", "agents", "hidden")],
    )
    policy = TensorDictModule(
        modules["policy"],
        in_keys=[("agents", "embedding")],
        out_keys=[("agents", "loc"), ("agents", "scale")],
    )
    actor = ProbabilisticActor(
        TensorDictSequential(trunk, policy),
        in_keys=[("agents", "loc"), ("agents", "scale")],
        out_keys=[("agents", "action")],
        distribution_class=IndependentNormal,
        return_log_prob=True,
    )
    value = TensorDictModule(
        modules["value"],
        in_keys=[("agents", "embedding"), ("agents", "mask")],
        out_keys=["state_value"],
    )
    baseline = TensorDictModule(
        modules["baseline"],
        in_keys=[("agents", "embedding"), ("agents", "action"), ("agents", "mask")],
        out_keys=[("agents", "baseline")],
    )
    loss = make_loss(actor, value, baseline)

    # Collect step by step as a collector would: env 0 is truncated at t=2 and restarts at t=3.
    n_steps = 6
    truncated_at = 2
    hidden = torch.zeros(N_ENVS, N_AGENTS, EMBED_DIM)
    observation = torch.randn(N_ENVS, N_AGENTS, OBS_DIM)
    is_init = torch.ones(N_ENVS, 1, dtype=torch.bool)
    mask = torch.ones(N_ENVS, N_AGENTS, dtype=torch.bool)
    steps, collected_value, next_value = [], [], []
    for t in range(n_steps):
        step = TensorDict(
            {
                "agents": TensorDict(
                    {"observation": observation, "hidden": hidden, "mask": mask},
                    batch_size=[N_ENVS, N_AGENTS],
                ),
                "is_init": is_init,
            },
            batch_size=[N_ENVS],
        )
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            actor(step)
            collected_value.append(value(step)["state_value"])
        next_observation = torch.randn(N_ENVS, N_AGENTS, OBS_DIM)
        done = torch.zeros(N_ENVS, 1, dtype=torch.bool)
        done[0] = t == truncated_at
        next_hidden = step["next", "agents", "hidden"]
        step["next"] = TensorDict(
            {
                "agents": TensorDict(
                    {
                        "observation": next_observation,
                        "hidden": next_hidden,
                        "reward": torch.randn(N_ENVS, N_AGENTS, 1),
                        "mask": mask,
                    },
                    batch_size=[N_ENVS, N_AGENTS],
                ),
                "done": done,
                "terminated": torch.zeros_like(done),
                "is_init": torch.zeros_like(done),
            },
            batch_size=[N_ENVS],
        )
        with torch.no_grad():  # V(s_{t+1}) in step mode, from the state the trunk carried
            next_value.append(value(actor.get_dist_params(step["next"].copy()))["state_value"])
        steps.append(step)
        # The reset after the truncation starts a fresh episode with a zeroed state.
        restart = done.squeeze(-1)
        observation = torch.where(
            restart[:, None, None], torch.randn(N_ENVS, N_AGENTS, OBS_DIM), next_observation
        )
        hidden = torch.where(restart[:, None, None], 0.0, next_hidden)
        is_init = done.clone()
    data = torch.stack(steps, dim=1)
    data.refine_names(..., "time")

    trunk_net.modes.clear()
    loss.value_estimator(data)
    # step mode: every element runs from the state stored with it, exact across the reset
    assert trunk_net.modes and not any(trunk_net.modes)
    torch.testing.assert_close(data["state_value"], torch.stack(collected_value, 1))

    value_now = torch.stack(collected_value, 1).squeeze(-1)
    value_next = torch.stack(next_value, 1).squeeze(-1)
    team_reward = data["next", "agents", "reward"].mean(-2).squeeze(-1)
    done = data["next", "done"].squeeze(-1)
    returns = torch.zeros_like(value_now)
    for n in range(N_ENVS):
        gae = 0.0
        for t in reversed(range(n_steps)):
            delta = team_reward[n, t] + GAMMA * value_next[n, t] - value_now[n, t]
            gae = delta + GAMMA * LMBDA * (~done[n, t]) * gae
            returns[n, t] = gae + value_now[n, t]
    torch.testing.assert_close(data["value_target"].squeeze(-1), returns, **TOLERANCE)


@pytest.mark.parametrize(
    ("seed", "cap"),
    [(15, 1.0), (15, 0.3), (1, 1.0)],
    ids=["a-blend", "the-schedule's-cap", "value-alone"],
)
def test_least_variance_weight_takes_the_blend_whose_advantages_vary_least(seed, cap):
    modules = make_modules()
    actor, value, baseline, _ = wrap(modules)
    data = make_batch(actor, seed=seed)  # batch 15: the least noisy blend lies near 0.54
    returns, old_value, old_baseline = reference_returns(modules, data)
    entries = [(n, t, i) for n in range(N_ENVS) for t in range(N_STEPS) for i in range(N_AGENTS)]
    mask = data["agents", "mask"]
    present = [entry for entry in entries if mask[entry]]
    residual = torch.tensor([returns[n, t] - old_value[n, t] for n, t, _ in present])
    difference = torch.tensor([old_baseline[n, t][i] - old_value[n, t] for n, t, i in present])
    # the least varying of the advantages G - V - w (b_i - V), by search over w in [0, 1]
    grid = torch.linspace(0, 1, 1_000_001, dtype=torch.float64).unsqueeze(-1)
    spread = (residual - grid * difference).var(dim=-1, correction=0)
    weight = min(cap, grid[spread.argmin()].item())
    loss = make_loss(actor, value, baseline, least_variance_weight=True)
    loss.counterfactual_weight = cap  # the weight can only go down from the schedule's
    loss.value_estimator(data)
    advantage = data["agents", "advantage"].squeeze(-1)[mask]
    torch.testing.assert_close(advantage, residual - weight * difference, atol=1e-5, rtol=1e-4)
