"""MAPOCATrainer's value-estimation shortcut and its compiled networks, on the real environment."""

import pytest
import torch
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ValueEstimators

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import MAPOCATrainer, TrainConfig, make_training_env

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


def make_trainer(**train) -> MAPOCATrainer:
    torch.manual_seed(0)
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    config = TrainConfig(num_envs=3, steps_per_iteration=8, minibatches=1, **train)
    env = make_training_env(ENV, networks, num_envs=3, device=torch.device("cpu"), seed=0)
    return MAPOCATrainer(env, networks, config)


def test_values_of_next_states_read_from_the_next_root_are_exact():
    trainer = make_trainer(normalize_value=False)
    data = trainer.collect()
    assert data["next", "truncated"].any()  # 8 decisions cross a 6-decision episode's end
    trainer.networks.eval()
    reused = data.clone()
    trainer.loss.value_estimator(reused)
    # A second loss on the same networks that runs them on every "next" state.
    trainer.loss.make_value_estimator(
        ValueEstimators.GAE, gamma=trainer.config.gamma, lmbda=trainer.config.lmbda
    )
    plain = data.clone()
    trainer.loss.value_estimator(plain)
    for key in ESTIMATED:
        torch.testing.assert_close(reused[key], plain[key], atol=1e-5, rtol=1e-5)


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


@pytest.mark.parametrize(("desired_kl", "growth"), [(10.0, 1.5), (1e-12, 1 / 1.5)])
def test_learning_rates_follow_the_kl_of_each_iteration(desired_kl, growth):
    trainer = make_trainer(desired_kl=desired_kl, schedule_iterations=1000)
    first = trainer.train_iteration()
    second = trainer.train_iteration()
    assert first["kl_approx"] < 0.5 * desired_kl or first["kl_approx"] > 2 * desired_kl
    schedule = trainer.schedules["lr_factor"]
    expected = first["lr_trunk_policy"] * growth * schedule(1) / schedule(0)
    assert second["lr_trunk_policy"] == pytest.approx(expected)
    assert trainer.state_dict()["kl_lr_factor"] == pytest.approx(growth**2)
    restored = make_trainer(desired_kl=desired_kl, schedule_iterations=1000)
    restored.load_state_dict(trainer.state_dict())
    assert restored.kl_lr_factor == trainer.kl_lr_factor


def test_learning_rate_adaptation_stays_within_its_bounds():
    trainer = make_trainer(desired_kl=0.01)
    for _ in range(30):
        trainer._adapt_learning_rates(1.0)
    assert trainer.kl_lr_factor == 0.01
    trainer._adapt_learning_rates(0.01)  # within [target / 2, 2 target]: unchanged
    assert trainer.kl_lr_factor == 0.01
