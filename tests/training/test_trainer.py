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


@pytest.mark.parametrize("stagger", [False, True])
def test_first_episodes_end_together_only_without_staggering(stagger):
    trainer = make_trainer(stagger_episodes=stagger)
    data = trainer.collect()  # 8 decisions over 6-decision episodes
    first_end = data["next", "truncated"].squeeze(-1).long().argmax(dim=1)
    if stagger:
        assert len(first_end.unique()) > 1
    else:
        assert (first_end == ENV.max_episode_steps - 1).all()
