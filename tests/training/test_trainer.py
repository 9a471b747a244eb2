"""The trainer on the real environment: the value-estimation shortcut, compiled networks,
CUDA-graph replay of acting and updating against eager execution, and deterministic runs."""

import ast
import copy
import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator, set_recurrent_mode
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.modules import TerraShiftModelConfig, keys, make_terrashift_networks
from terrashift_rl.modules.layers import MultiHeadAttention
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.sim.types import ACTION_NAMES
from terrashift_rl.training import (
    ALGORITHMS,
    Algorithm,
    OnPolicyTrainer,
    TrainConfig,
    TrainerHook,
    action_medians,
    concentration_metrics,
    make_training_env,
    terrashift,
)
from terrashift_rl.training import trainer as trainer_module
from terrashift_rl.training.graphs import CudaGraphed

ENV = TerraShiftConfig(
    grid_size=8,
    num_agents=4,
    num_objects=2,
    num_goals=2,
    spawn_margin=1,
    max_episode_steps=6,
    heightmap_resolution=16,
)
ESTIMATED = ("state_value", "value_target", ("agents", "baseline"), ("agents", "advantage"))
CUDA = torch.device("cuda")
# no dropout: eager and replayed updates then draw no random numbers and must agree
MODEL = dataclasses.replace(TerraShiftModelConfig.small(), dropout=0.0)


def train_config(*, algo: str = "mapoca", **settings) -> TrainConfig:
    """A :class:`TrainConfig` from the ``train`` and ``loss`` settings of ``algo`` in one
    list."""
    loss = ALGORITHMS[algo]
    names = {field.name for field in dataclasses.fields(loss)}
    return TrainConfig(
        **{name: value for name, value in settings.items() if name not in names},
        loss=loss(**{name: value for name, value in settings.items() if name in names}),
    )


def make_trainer(
    *, seed: int = 0, model: dict | None = None, scene: TerraShiftConfig = ENV, **train
) -> OnPolicyTrainer:
    """A trainer of the small network (with ``model`` overrides) on three environments of
    ``scene``."""
    torch.manual_seed(seed)
    networks = make_terrashift_networks(
        dataclasses.replace(TerraShiftModelConfig.small(), **(model or {}))
    )
    config = train_config(num_envs=3, steps_per_iteration=8, minibatches=1, **train)
    env = make_training_env(scene, networks, num_envs=3, device=torch.device("cpu"), seed=seed)
    return terrashift.make_trainer(env, networks, config)


def test_values_of_next_states_read_from_the_next_root_are_exact():
    trainer = make_trainer(normalize_value=False)
    data = trainer.collect()
    assert data["next", "truncated"].any()  # 8 decisions cross a 6-decision episode's end
    trainer.networks.eval()
    reused = data.clone()
    trainer.loss.value_estimator(reused)
    # A second loss on the same networks that runs them on every "next" state.
    trainer.loss.make_value_estimator(
        ValueEstimators.GAE, gamma=trainer.config.loss.gamma, lmbda=trainer.config.loss.lmbda
    )
    plain = data.clone()
    trainer.loss.value_estimator(plain)
    for key in ESTIMATED:
        torch.testing.assert_close(reused[key], plain[key], atol=1e-5, rtol=1e-5)


def test_concentration_metrics_are_the_median_alpha_plus_beta_of_each_action():
    # five agent-steps (one environment, five decisions, one agent); action d's beta runs over
    # (d + 1) * [5, 1, 4, 2, 3], alpha is 1, so its median alpha + beta is 1 + 3 (d + 1)
    beta = torch.tensor([5.0, 1.0, 4.0, 2.0, 3.0])[:, None] * torch.arange(1.0, 7.0)
    data = TensorDict(batch_size=[1, 5])
    data.set(keys.BETA_CONCENTRATION1, torch.ones(1, 5, 1, 6))
    data.set(keys.BETA_CONCENTRATION0, beta[None, :, None])
    metrics = concentration_metrics(data)
    assert list(metrics) == [f"concentration_{name}" for name in ACTION_NAMES]
    assert list(metrics.values()) == [1.0 + 3.0 * (d + 1) for d in range(6)]

    logged = make_trainer().train_iteration()  # a trainer logs them every iteration
    floor = 2 * TerraShiftModelConfig.small().min_concentration
    assert all(logged[key] > floor for key in metrics)


def test_action_medians_are_those_the_actuators_received():
    # five agent-steps; action d is 0.1 d above [-3, -0.5, 0, 0.4, 2], clipped to [-1, 1]
    base = torch.tensor([-3.0, -0.5, 0.0, 0.4, 2.0])[:, None] + 0.1 * torch.arange(6.0)
    data = TensorDict({keys.ACTION: base[None, :, None]}, batch_size=[1, 5])
    metrics = action_medians(data)
    assert list(metrics) == [f"action_median_{name}" for name in ACTION_NAMES]
    assert list(metrics.values()) == pytest.approx([0.1 * d for d in range(6)])
    # of an even count, the lower of the two middle values (clipped: -0.2, 0.3, 1, 1)
    data = TensorDict(
        {keys.ACTION: torch.tensor([0.3, 5.0, 7.0, -0.2])[None, :, None, None].expand(1, 4, 1, 6)},
        batch_size=[1, 4],
    )
    assert action_medians(data)["action_median_amplitude"] == pytest.approx(0.3)

    logged = make_trainer().train_iteration()  # a trainer logs them every iteration
    assert all(-1.0 <= logged[key] <= 1.0 for key in metrics)


def test_a_gaussian_policy_logs_its_spread_in_place_of_concentrations():
    # two agent-steps whose standard deviations are (d + 1) / 10 and (d + 1) / 5 in action d:
    # the lower median is the first
    scale = torch.arange(1.0, 7.0) / 10 * torch.tensor([[1.0], [2.0]])
    data = TensorDict(batch_size=[1, 2])
    data.set(keys.NORMAL_LOC, torch.zeros(1, 2, 1, 6))
    data.set(keys.NORMAL_SCALE, scale[None, :, None])
    metrics = concentration_metrics(data)
    assert list(metrics) == [f"action_std_{name}" for name in ACTION_NAMES]
    assert metrics["action_std_v_x"] == pytest.approx(0.1)
    assert metrics["action_std_sigma_y"] == pytest.approx(0.6)

    trainer = make_trainer(model={"distribution": "normal", "initial_std": 0.4})
    first, second = trainer.train_iteration(), trainer.train_iteration()
    assert not any(key.startswith("concentration_") for key in first)
    # the first batch was collected at the initial spread; the updates then moved it a little
    assert [first[key] for key in metrics] == pytest.approx([0.4] * 6)
    moved = [abs(second[key] - 0.4) for key in metrics]
    assert all(0.0 < change < 0.05 for change in moved)
    assert first["kl_approx"] > 0


@pytest.mark.slow  # tens of seconds of CPU compilation with a cold inductor cache
def test_compiled_networks_give_the_eager_loss():
    eager, compiled = make_trainer(), make_trainer(compile=True)
    data = eager.collect()
    eager.networks.eval()
    eager.loss.value_estimator(data)
    compiled.loss.value_normalizer.load_state_dict(eager.loss.value_normalizer.state_dict())
    losses = []
    for trainer in (eager, compiled):
        trainer.networks.eval()  # dropout draws differ between eager and compiled code
        with set_recurrent_mode(True):
            losses.append(trainer.loss(data.clone()))
    for key, value in losses[0].items():
        torch.testing.assert_close(losses[1][key], value, atol=1e-4, rtol=1e-4)
    state = compiled.networks.state_dict()
    assert state.keys() == eager.networks.state_dict().keys()  # checkpoints are unchanged


class _Estimated(Exception):
    """Raised after the value-estimation pass, before the update's epochs."""


def test_a_compiled_trainer_acts_and_estimates_without_compiling(monkeypatch):
    # under train.compile, acting and the value-estimation pass run the networks eagerly
    trainer = make_trainer(compile=True)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    data = trainer.collect()
    trainer.evaluation_policy(ExplorationType.DETERMINISTIC)(data[:, 0].clone())
    estimate = trainer.algorithm.estimate

    def estimate_then_stop(batch):
        estimate(batch)
        raise _Estimated

    monkeypatch.setattr(trainer.algorithm, "estimate", estimate_then_stop)
    with pytest.raises(_Estimated):
        trainer.update(data)
    assert data["state_value"].isfinite().all()  # the pass ran
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 0
    # the same networks outside the trainer's eager passes are compiled
    embedding = torch.randn(2, ENV.num_agents, TerraShiftModelConfig.small().embed_dim)
    with torch.no_grad():
        trainer.networks.value_head.module(embedding)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] > 0


@pytest.mark.parametrize("stagger", [False, True])
def test_first_episodes_end_together_only_without_staggering(stagger):
    trainer = make_trainer(stagger_episodes=stagger)
    data = trainer.collect()  # 8 decisions over 6-decision episodes
    first_end = data["next", "truncated"].squeeze(-1).long().argmax(dim=1)
    if stagger:
        assert len(first_end.unique()) > 1
    else:
        assert (first_end == ENV.max_episode_steps - 1).all()


def test_a_checkpoint_with_capturable_adamw_resumes_without_cuda_graphs():
    trainer = make_trainer()
    trainer.train_iteration()
    state = trainer.state_dict()
    # as written on CUDA with train.cuda_graphs: tensor learning rates, capturable AdamW
    for group in state["optimizer"]["param_groups"]:
        group["lr"], group["capturable"] = torch.tensor(group["lr"]), True
    resumed = make_trainer()
    resumed.load_state_dict(state)
    for group in resumed.optimizer.param_groups:
        assert isinstance(group["lr"], float) and not group["capturable"]
    resumed.train_iteration()  # AdamW would refuse tensor rates or a device step count here
    assert resumed.iteration == 2


def test_restarted_schedules_begin_again_from_their_starts_and_survive_a_resume():
    settings = {"schedule_iterations": 2, "clip_epsilon_start": 0.3, "clip_epsilon_end": 0.1}
    trainer = make_trainer(**settings)
    ran = [trainer.train_iteration() for _ in range(3)]
    assert [m["clip_epsilon"] for m in ran] == pytest.approx([0.3, 0.2, 0.1])
    trainer.restart_schedules()
    restarted = trainer.train_iteration()
    assert restarted["clip_epsilon"] == pytest.approx(0.3)
    assert restarted["lr_trunk_policy"] == pytest.approx(trainer.config.lr_trunk_policy)
    resumed = make_trainer(**settings)
    resumed.load_state_dict(trainer.state_dict())
    assert resumed.schedule_start == 3
    assert resumed.train_iteration()["clip_epsilon"] == pytest.approx(0.2)  # 1 past the start


def test_a_new_env_on_another_device_is_refused_naming_both():
    trainer = make_trainer()
    env = trainer.env
    with pytest.raises(ValueError, match="the new env is on cuda, the trainer on cpu"):
        trainer.set_env(SimpleNamespace(device=torch.device("cuda")))
    assert trainer.env is env


TEACHER = ("agents", "teacher_action")
TEACHER_METRICS = {"teacher_coeff", "loss_teacher", "teacher_distance"}


def test_teacher_action_is_the_scripted_heuristics_action():
    data = make_trainer(teacher_coeff=1.0).collect()
    observed = data.select(("agents", "observation"), "objects", "objects_mask").clone()
    expected = ScriptedHeuristicPolicy(ENV)(observed).get(("agents", "action"))
    teacher = data[TEACHER]
    torch.testing.assert_close(teacher, expected)
    assert teacher.shape == data["agents", "action"].shape
    assert teacher.abs().max() <= 1.0 and teacher.abs().max() > 0
    assert not torch.equal(teacher, data["agents", "action"])  # the policy's own stays


def test_teacher_reads_the_critics_objects_where_the_agents_observe_none():
    scene = dataclasses.replace(ENV, observe_objects=False, privileged_objects=True)
    model = {"object_tokens": False, "critic_objects": True}
    data = make_trainer(teacher_coeff=1.0, model=model, scene=scene).collect()
    assert "objects" not in data.keys(include_nested=True)  # the agents: heightmap alone
    observed = TensorDict(
        {
            ("agents", "observation"): data["agents", "observation"],
            "objects": data[keys.PRIVILEGED_OBJECTS],
            "objects_mask": data[keys.PRIVILEGED_OBJECTS_MASK],
        },
        batch_size=data.batch_size,
    )
    expected = ScriptedHeuristicPolicy(scene)(observed).get(("agents", "action"))
    torch.testing.assert_close(data[TEACHER], expected)
    assert data[TEACHER].abs().max() > 0


def test_a_teacher_without_objects_is_refused():
    scene = dataclasses.replace(ENV, observe_objects=False)
    with pytest.raises(ValueError, match="teacher reads the object sequence.*privileged_objects"):
        make_trainer(teacher_coeff=1.0, model={"object_tokens": False}, scene=scene)


@pytest.mark.parametrize(
    ("end", "expected"),
    [(0.0, [2.0, 1.5, 1.0, 0.5, 0.0, 0.0]), (1.0, [2.0, 1.75, 1.5, 1.25, 1.0, 1.0])],
)
def test_teacher_weight_falls_linearly_to_its_end(end, expected):
    trainer = make_trainer(teacher_coeff=2.0, teacher_coeff_end=end, teacher_iterations=4)
    # applied at the start of each update, at the iteration count before it
    metrics = [trainer.train_iteration() for _ in range(6)]
    assert [m["teacher_coeff"] for m in metrics] == expected
    for m in metrics:
        assert m["teacher_distance"] > 0
        assert m["loss_teacher"] == pytest.approx(m["teacher_coeff"] * m["teacher_distance"])
    assert (metrics[-1]["loss_teacher"] == 0.0) == (end == 0.0)


def test_no_teacher_by_default():
    trainer = make_trainer()
    data = trainer.collect()
    assert TEACHER not in data.keys(include_nested=True)
    assert not TEACHER_METRICS & trainer.update(data).keys()


def test_cuda_graphed_refuses_a_tensordict_off_cuda():
    graphed = CudaGraphed(lambda td: td)
    with pytest.raises(ValueError, match="CUDA device, got device cpu"):
        graphed(TensorDict({"x": torch.ones(2)}, [2], device="cpu"))
    assert graphed.calls == 0


@pytest.mark.gpu
def test_replayed_function_reads_each_calls_inputs():
    graphed = CudaGraphed(lambda td: TensorDict({"y": td["x"].square().cumsum(0)}, [3]))
    for call in range(5):
        x = torch.randn(3, device=CUDA)
        out = graphed(TensorDict({"x": x}, [3], device=CUDA))
        torch.testing.assert_close(out["y"], x.square().cumsum(0))
        assert graphed.captured == (call >= graphed.warmup)


# the Gaussian policy head with position actions, beside the default Beta head and delta actions
GAUSSIAN = dataclasses.replace(MODEL, distribution="normal")
POSITION = dataclasses.replace(ENV, action_mode="position")


@pytest.mark.gpu
@pytest.mark.parametrize(
    ("model", "scene"), [(MODEL, ENV), (GAUSSIAN, POSITION)], ids=["beta", "normal"]
)
def test_replayed_actor_step_gives_the_eager_outputs(model, scene):
    networks = make_terrashift_networks(model).to(CUDA).eval()
    env = make_training_env(scene, networks, num_envs=5, device=CUDA, seed=0)
    outputs = [keys.ACTION, keys.ACTION_LOG_PROB, keys.NEXT_RECURRENT_STATE]
    graphed = CudaGraphed(lambda td: networks.actor(td).select(*outputs))
    td = env.reset()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(5):
            inputs = td.select(*networks.actor.in_keys, strict=False)
            replayed = graphed(inputs.clone()).clone()
            eager = networks.actor(inputs.clone()).select(*outputs)
            for key in outputs:
                torch.testing.assert_close(replayed[key], eager[key])
            td = env.step_and_maybe_reset(td.update(eager))[1]
    assert graphed.captured
    # a graph captured while sampling (as collection does) draws new numbers at every replay
    sampler = CudaGraphed(lambda td: networks.actor(td).select(keys.ACTION))
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        sampled = [sampler(inputs.clone())[keys.ACTION].clone() for _ in range(4)]
    assert sampler.captured
    assert not torch.equal(sampled[-2], sampled[-1])  # two replays


@pytest.mark.gpu
@pytest.mark.parametrize(
    ("bf16", "compiled", "model", "scene"),
    [
        (False, False, MODEL, ENV),
        (True, False, MODEL, ENV),
        (False, True, MODEL, ENV),
        (False, False, GAUSSIAN, POSITION),
    ],
    ids=["fp32", "bf16", "compiled", "normal"],
)
def test_replayed_updates_give_the_eager_parameters(bf16, compiled, model, scene):
    torch.manual_seed(0)
    networks = make_terrashift_networks(model)
    # the schedules change between the two updates below
    config = TrainConfig(
        num_envs=8,
        steps_per_iteration=8,
        epochs=2,
        minibatches=4,
        schedule_iterations=3,
        tf32=False,
        bf16=bf16,
    )
    trainers = {}
    for graphs in (False, True):
        copied = copy.deepcopy(networks).to(CUDA)
        env = make_training_env(scene, copied, num_envs=8, device=CUDA, seed=0)
        # the replayed trainer's networks are also compiled when ``compiled`` is set
        variant = dataclasses.replace(config, cuda_graphs=graphs, compile=compiled and graphs)
        trainers[graphs] = terrashift.make_trainer(env, copied, variant)
    data = trainers[False].collect()
    for iteration in range(2):
        metrics = {}
        for graphs, trainer in trainers.items():
            torch.manual_seed(iteration)  # the same mini-batch order
            trainer.iteration = iteration
            metrics[graphs] = trainer.update(data.clone())
        for name, value in metrics[False].items():
            if name.endswith("_seconds"):
                continue
            # a clip fraction counts samples past a threshold: rounding can move one of 128
            tolerance = 0.02 if name.endswith("clip_fraction") else 1e-4
            assert metrics[True][name] == pytest.approx(value, rel=1e-2, abs=tolerance), name
    assert all(step.captured for step in trainers[True]._update_steps.values())
    assert metrics[True]["lr_trunk_policy"] < config.lr_trunk_policy  # the schedule moved
    # Adam turns rounding-level gradient differences into whole steps where a gradient is
    # near zero, so compare the parameters' distance against how far the 16 steps moved them.
    start = networks.state_dict()
    eager, replayed = (trainers[g].networks.state_dict() for g in (False, True))
    moved = apart = 0.0
    for name, value in eager.items():
        if value.is_floating_point():
            moved += (value.cpu() - start[name]).square().sum().item()
            apart += (replayed[name] - value).square().sum().item()
    assert moved > 0
    # bfloat16 keeps 8 significant bits, so its rounding differences are larger: 4% of the
    # movement on an H100, against under 1% in float32
    assert apart**0.5 < (0.1 if bf16 else 0.01) * moved**0.5


@pytest.fixture
def restores_determinism():
    """``train.deterministic`` sets a process-wide switch: turn it back off after the test."""
    yield
    torch.use_deterministic_algorithms(False)


@pytest.mark.gpu
@pytest.mark.usefixtures("restores_determinism")
def test_deterministic_runs_repeat_exactly_on_cuda():
    runs = []
    for _ in range(2):
        torch.manual_seed(0)
        networks = make_terrashift_networks(TerraShiftModelConfig.small()).to(CUDA)
        env = make_training_env(ENV, networks, num_envs=8, device=CUDA, seed=0)
        config = TrainConfig(num_envs=8, steps_per_iteration=8, minibatches=2, deterministic=True)
        trainer = terrashift.make_trainer(env, networks, config)
        metrics = [trainer.train_iteration() for _ in range(3)]  # the third one replays graphs
        runs.append((metrics, networks.state_dict()))
    assert torch.are_deterministic_algorithms_enabled()
    (first, first_weights), (second, second_weights) = runs
    for one, other in zip(first, second, strict=True):
        for name, value in one.items():
            if not name.endswith(("_seconds", "_per_s")):
                # episode metrics are NaN in an iteration where no episode ended
                assert other[name] == pytest.approx(value, rel=0, abs=0, nan_ok=True), name
    for name, value in first_weights.items():
        assert torch.equal(second_weights[name], value), name


@pytest.mark.parametrize(("kl_over_target", "factor"), [(3.0, 1 / 1.5), (1.0, 1.0), (0.2, 1.5)])
def test_adaptive_learning_rate_moves_against_the_kl(kl_over_target, factor):
    trainer = make_trainer(lr_schedule="adaptive", desired_kl=0.01)
    trainer._apply_schedules()
    before = [group["lr"] for group in trainer.optimizer.param_groups]
    trainer._adapt_learning_rate(torch.tensor(0.01 * kl_over_target))
    after = [group["lr"] for group in trainer.optimizer.param_groups]
    assert after == pytest.approx([before[0] * factor, before[1]])  # the critics' rate stays


def test_adaptive_learning_rate_stays_within_its_bounds_and_survives_a_resume():
    # a KL target far above any update's KL: every mini-batch raises the rate, up to lr_max
    settings = dict(
        lr_schedule="adaptive", desired_kl=10.0, lr_trunk_policy=3.0e-4, lr_max=1.0e-3, epochs=2
    )
    trainer = make_trainer(**settings)
    metrics = trainer.train_iteration()
    assert metrics["kl_approx"] < 5.0
    assert metrics["lr_trunk_policy"] == pytest.approx(3.0e-4 * 1.5**2)  # two mini-batches
    metrics = trainer.train_iteration()
    assert metrics["lr_trunk_policy"] == pytest.approx(1.0e-3)  # clamped
    assert trainer.optimizer.param_groups[1]["lr"] == pytest.approx(6.0e-4 * (1 - 0.9 / 1000))
    resumed = make_trainer(**settings)
    resumed.load_state_dict(trainer.state_dict())
    resumed._apply_schedules()  # an adaptive rate is not reset by the schedules
    assert resumed.optimizer.param_groups[0]["lr"] == pytest.approx(1.0e-3)


def test_linear_schedule_ignores_the_kl():
    trainer = make_trainer(lr_trunk_policy=3.0e-4, lr_end_factor=0.5, schedule_iterations=2)
    rates = [trainer.train_iteration()["lr_trunk_policy"] for _ in range(3)]
    assert rates == pytest.approx([3.0e-4, 2.25e-4, 1.5e-4])


def test_critic_warmup_trains_the_critics_and_leaves_the_policy_untouched():
    trainer = make_trainer(critic_warmup_iterations=2)
    networks = trainer.networks
    policy = {
        name: p.detach().clone()
        for module in (networks.trunk, networks.policy_head)
        for name, p in module.named_parameters()
    }
    critics = [p.detach().clone() for p in networks.value_head.parameters()]
    for _ in range(2):
        assert trainer.train_iteration()["critic_warmup"] == 1.0
    for module in (networks.trunk, networks.policy_head):
        for name, p in module.named_parameters():
            assert torch.equal(p, policy[name]), name  # bit for bit, weight decay included
    assert any(
        not torch.equal(p, q)
        for p, q in zip(networks.value_head.parameters(), critics, strict=True)
    )
    assert trainer.train_iteration()["critic_warmup"] == 0.0  # then the policy learns
    assert any(
        not torch.equal(p, policy[name]) for name, p in networks.policy_head.named_parameters()
    )


def test_a_non_finite_update_stops_training_naming_the_first_non_finite_loss():
    # the learning rates jump to 3e6 after the first update
    trainer = make_trainer(lr_end_factor=1.0e10, schedule_iterations=1)
    assert math.isfinite(trainer.train_iteration()["loss_total"])
    with pytest.raises(FloatingPointError, match="^iteration 2 made loss_objective = nan"):
        trainer.train_iteration()


def test_a_non_finite_parameter_stops_training_naming_it(monkeypatch):
    trainer = make_trainer()
    update = trainer.update

    def update_that_breaks_a_parameter(data):
        metrics = update(data)
        trainer.networks.value_head.get_parameter(name).data[0] = math.inf
        return metrics

    name = next(name for name, _ in trainer.networks.value_head.named_parameters())
    monkeypatch.setattr(trainer, "update", update_that_breaks_a_parameter)
    with pytest.raises(FloatingPointError, match=rf"^iteration 1 made parameter \S*{name} holds"):
        trainer.train_iteration()


def test_a_non_finite_action_stops_the_iteration_naming_the_action(monkeypatch):
    trainer = make_trainer()
    act, calls = trainer._actor_step, []

    def nan_at_the_third_step(inputs):
        outputs = act(inputs)
        calls.append(None)
        if len(calls) == 3:
            outputs[keys.ACTION][0, 1, 2] = math.nan
        return outputs

    monkeypatch.setattr(trainer, "_actor_step", nan_at_the_third_step)
    message = r"^\('agents', 'action'\) held NaN or infinite values in 1 of the 8 steps"
    with pytest.raises(ValueError, match=message):
        trainer.train_iteration()
    assert trainer.iteration == 0  # refused before any update


def test_trainer_module_knows_nothing_of_terrashift():
    tree = ast.parse(Path(trainer_module.__file__).read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {
        a.name for node in ast.walk(tree) if isinstance(node, ast.Import) for a in node.names
    }
    project = {name for name in imported if name.startswith("terrashift_rl")}
    assert project and all(name.startswith("terrashift_rl.training") for name in project)
    names = {node.id for node in ast.walk(tree) if isinstance(node, ast.Name)}
    assert not names & {"ACTION_NAMES", "TerraShiftEnv", "ScriptedHeuristicPolicy"}


# --- the trainer on a scene of its own: one agent steers its action to a target it observes ---


class TargetEnv(EnvBase):
    """Observes a target in [-1, 1] drawn at each reset; the reward is minus the squared distance
    of the action to it; episodes are truncated after ``EPISODE`` steps."""

    EPISODE = 3

    def __init__(self, num_envs: int):
        super().__init__(device="cpu", batch_size=torch.Size([num_envs]))
        n = num_envs
        self.observation_spec = Composite(observation=Unbounded((n, 1)), shape=(n,))
        self.action_spec = Bounded(-1.0, 1.0, shape=(n, 1))
        self.reward_spec = Unbounded((n, 1))
        flag = Categorical(2, shape=(n, 1), dtype=torch.bool)
        self.done_spec = Composite(
            done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=(n,)
        )
        self._target = torch.zeros(n, 1)
        self._steps = torch.zeros(n, 1, dtype=torch.int64)

    def _reset(self, tensordict=None, **kwargs):
        reset = None if tensordict is None else tensordict.get("_reset", None)
        reset = torch.ones(self.batch_size, dtype=torch.bool) if reset is None else reset
        reset = reset.reshape(*self.batch_size, 1)
        self._target = torch.where(reset, torch.rand(self._target.shape) * 2 - 1, self._target)
        self._steps = torch.where(reset, 0, self._steps)
        return self._output(reward=None)

    def _step(self, tensordict):
        self._steps = self._steps + 1
        return self._output(reward=-(tensordict["action"] - self._target).square())

    def _output(self, reward):
        truncated = self._steps >= self.EPISODE
        out = TensorDict(
            observation=self._target.clone(),
            done=truncated,
            terminated=torch.zeros_like(truncated),
            truncated=truncated.clone(),
            batch_size=self.batch_size,
        )
        if reward is not None:
            out["reward"] = reward
        return out

    def _set_seed(self, seed):
        torch.manual_seed(seed)


class Recorder(TrainerHook):
    """Records every call, adds a key to each batch and a metric to each iteration."""

    summed_metrics = ("batches",)
    state_keys = ("recorded_calls",)

    def __init__(self):
        self.calls = []

    def on_reset(self, trainer, tensordict):
        self.calls.append(("reset", trainer.iteration, tuple(tensordict.batch_size)))

    def on_batch_collected(self, trainer, data):
        self.calls.append(("batch", trainer.iteration, tuple(data.batch_size)))
        data.set("seen_by_hook", torch.ones(data.shape))

    def metrics(self, trainer, data):
        seen = data.get("seen_by_hook", None) is not None
        self.calls.append(("metrics", trainer.iteration, seen))
        return {"batches": 1.0}

    def state_dict(self):
        return {"recorded_calls": len(self.calls)}

    def load_state_dict(self, state):
        self.calls.append(("load", state["recorded_calls"]))


def make_target_trainer(hooks=()) -> OnPolicyTrainer:
    """torchrl's ClipPPOLoss on TargetEnv: no part of it is TerraShift's."""
    torch.manual_seed(0)
    env = TargetEnv(num_envs=4)
    actor = ProbabilisticActor(
        TensorDictModule(
            torch.nn.Sequential(
                torch.nn.Linear(1, 16),
                torch.nn.Tanh(),
                torch.nn.Linear(16, 2),
                NormalParamExtractor(),
            ),
            in_keys=["observation"],
            out_keys=["loc", "scale"],
        ),
        spec=env.action_spec_unbatched,
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        return_log_prob=True,
    )
    critic = ValueOperator(
        torch.nn.Sequential(torch.nn.Linear(1, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1)),
        in_keys=["observation"],
    )
    loss = ClipPPOLoss(actor, critic, clip_value=0.3, functional=False)
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.9, lmbda=0.9)
    algorithm = Algorithm(
        loss=loss,
        estimate=loss.value_estimator,
        critics=[critic],
        critic_terms=("loss_critic",),
        networks=torch.nn.ModuleDict(),
        value_normalizer=None,
        capturable=False,
    )
    optimizer = torch.optim.AdamW(
        [{"params": actor.parameters(), "lr": 1e-2}, {"params": critic.parameters(), "lr": 1e-2}]
    )
    config = train_config(algo="mappo", num_envs=4, steps_per_iteration=8, minibatches=2)
    networks = torch.nn.ModuleDict({"actor": actor, "critic": critic})
    return OnPolicyTrainer(env, actor, algorithm, optimizer, config, networks=networks, hooks=hooks)


def distance_to_target(actor) -> float:
    """Mean squared distance of the actor's mean action to the target it observes."""
    targets = TensorDict(observation=torch.linspace(-0.9, 0.9, 19)[:, None], batch_size=[19])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return (actor(targets)["action"] - targets["observation"]).square().mean().item()


def test_the_trainer_learns_on_a_scene_that_is_not_terrashift():
    trainer = make_target_trainer()
    before = {name: p.detach().clone() for name, p in trainer._named_parameters()}
    start = distance_to_target(trainer.policy)
    for _ in range(20):
        metrics = trainer.train_iteration()
        assert {"loss_objective", "loss_critic", "loss_entropy", "grad_norm"} <= metrics.keys()
        assert all(math.isfinite(metrics[key]) for key in metrics if key.startswith("loss_"))
    assert trainer.env_steps == 20 * 4 * 8 and trainer.iteration == 20
    for name, p in trainer._named_parameters():
        assert not torch.equal(p, before[name]), name
    assert distance_to_target(trainer.policy) < 0.25 * start
    state = trainer.state_dict()
    assert "simulator" not in state
    assert state["networks"].keys() == trainer.networks.state_dict().keys()


def test_hooks_are_called_in_order_and_their_metrics_and_state_kept():
    recorder = Recorder()
    trainer = make_target_trainer(hooks=[recorder])
    metrics = [trainer.train_iteration() for _ in range(2)]
    batch = (4, 8)
    assert recorder.calls == [
        ("reset", 0, (4,)),  # the first reset only
        ("batch", 0, batch),
        ("metrics", 1, True),  # after the update, with what the hook wrote into the batch
        ("batch", 1, batch),
        ("metrics", 2, True),
    ]
    assert all(m["batches"] == 1.0 for m in metrics)
    state = trainer.state_dict()
    assert state["recorded_calls"] == 5
    resumed_recorder = Recorder()
    resumed = make_target_trainer(hooks=[resumed_recorder])
    resumed.load_state_dict(state)
    resumed.train_iteration()  # carries the episodes on: no reset
    assert [call[0] for call in resumed_recorder.calls] == ["load", "batch", "metrics"]
    assert resumed_recorder.calls[0] == ("load", 5)


def test_terrashift_hooks_follow_the_settings():
    def kinds(**train):
        return [type(hook).__name__ for hook in make_trainer(**train).hooks]

    assert kinds() == ["ActionCheck", "StaggeredEpisodes", "SimulatorState", "SceneMetrics"]
    assert kinds(stagger_episodes=False, teacher_coeff=0.5) == [
        "ActionCheck",
        "ScriptedTeacher",
        "SimulatorState",
        "SceneMetrics",
    ]


@pytest.mark.gpu
def test_compiled_attention_over_small_sets_is_multiplied_and_summed_as_eager():
    # a window's self-attention of a mini-batch: 16 tokens of 4 heads x 16 channels, whose
    # batched products COMPILE_OPTIONS turns into fused multiply-and-sum kernels (in float32,
    # so eager's products are compared without TF32, which trainers switch on process-wide)
    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        torch.manual_seed(0)
        attention = MultiHeadAttention(64, 4).to(CUDA)
        compiled = copy.deepcopy(attention)
        compiled.compile(options=terrashift.COMPILE_OPTIONS)
        torch._dynamo.utils.counters.clear()
        tokens = torch.randn(4096, 16, 64, device=CUDA, requires_grad=True)
        outputs = [module(tokens, tokens) for module in (attention, compiled)]
        grads = [torch.autograd.grad(out.square().sum(), tokens)[0] for out in outputs]
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32
    assert torch._dynamo.utils.counters["inductor"]["decompose_bmm"] >= 2  # forward's two
    torch.testing.assert_close(outputs[1], outputs[0], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(grads[1], grads[0], atol=1e-3, rtol=1e-3)
