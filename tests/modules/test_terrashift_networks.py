"""The factory: one shared trunk, the loss-time flow, checkpoints across task sizes, configs."""

from __future__ import annotations

import io

import pytest
import torch
from omegaconf import OmegaConf
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode
from torchrl.objectives.value import GAE

from terrashift_rl.modules import TerraShiftModelConfig, keys, make_terrashift_networks


def test_the_three_networks_share_one_trunk(networks):
    trunk = networks.trunk
    assert networks.actor.module[0][0] is trunk
    assert networks.value_network[0] is trunk
    assert networks.baseline_network[0] is trunk
    names = list(networks.state_dict())
    assert len(names) == len(set(names))
    assert sum(name.startswith("trunk.") for name in names) == len(list(trunk.state_dict()))


def test_train_and_eval_reach_the_compositions(networks):
    networks.train()
    assert networks.actor.training and networks.value_network.training
    networks.eval()
    assert not networks.actor.training and not networks.baseline_network.training
    assert not any(module.training for module in networks.modules())


def test_heads_after_the_actor_equal_the_standalone_networks(networks, make_batch):
    data = make_batch((4,), num_agents=8)
    with torch.no_grad():
        shared = networks.value_head(networks.baseline_head(networks.actor(data.clone())))
        standalone_value = networks.value_network(data.clone())
        standalone_baseline = networks.baseline_network(shared.clone())
    torch.testing.assert_close(shared[keys.STATE_VALUE], standalone_value[keys.STATE_VALUE])
    torch.testing.assert_close(shared[keys.BASELINE], standalone_baseline[keys.BASELINE])
    assert shared[keys.STATE_VALUE].shape == (4, 1)
    assert shared[keys.BASELINE].shape == (4, 8, 1)


def parameters_without_gradient(networks, data) -> list[str]:
    """The loss-time flow on [N, T] sequences: the actor's distribution writes the embedding,
    the heads read it; one backward pass through the shared trunk and the GRU over time.
    Returns the names of the parameters no gradient reached."""
    networks.train()
    with set_recurrent_mode(True):
        dist = networks.actor.get_dist(data)
        networks.value_head(data)
        networks.baseline_head(data)
    loss = (
        dist.log_prob(data[keys.ACTION]).mean()
        + dist.entropy().mean()
        + data[keys.STATE_VALUE].square().mean()
        + data[keys.BASELINE].square().mean()
    )
    loss.backward()
    return [
        name
        for name, parameter in networks.named_parameters()
        if parameter.grad is None or parameter.grad.abs().sum() == 0
    ]


def test_gradients_reach_every_parameter_in_a_loss_pass(networks, make_batch):
    data = make_batch((2, 3), num_agents=4, is_init=False)
    data["is_init"][:, 0] = True
    data["objects_mask"][..., -1] = False
    assert parameters_without_gradient(networks, data) == []


@pytest.mark.parametrize(
    ("num_agents", "map_side", "spatial_tokens"),
    [(8, 32, 4), (16, 32, 4), (16, 64, 14), (16, 128, 16)],
    ids=["pretrain-15x15-8-agents", "finetune-30x30-16-agents", "64x64-map", "128x128-map"],
)
def test_one_checkpoint_runs_every_task_size(
    networks, small_config, make_batch, num_agents, map_side, spatial_tokens
):
    buffer = io.BytesIO()
    torch.save(networks.state_dict(), buffer)
    buffer.seek(0)
    restored = make_terrashift_networks(small_config).eval()
    restored.load_state_dict(torch.load(buffer))

    data = make_batch((3,), num_agents=num_agents, map_side=map_side)
    heightmap_tokens = restored.trunk.network.heightmap_encoder(data["heightmap"])
    assert heightmap_tokens.shape[-2] == spatial_tokens
    with torch.no_grad():
        original = networks.value_network(data.clone())
        loaded = restored.value_network(data.clone())
        dist = restored.actor.get_dist(data.clone())
    torch.testing.assert_close(loaded[keys.STATE_VALUE], original[keys.STATE_VALUE])
    assert dist.batch_shape == (3, num_agents)


@pytest.mark.parametrize("recurrent", [False, True], ids=["step-mode", "recurrent-mode"])
def test_value_network_works_with_torchrl_gae(networks, mock_env_class, recurrent):
    env = TransformedEnv(
        mock_env_class(2, num_agents=4), Compose(InitTracker(), networks.make_tensordict_primer(4))
    )
    with torch.no_grad():
        rollout = env.rollout(6, networks.actor)
    rollout["next", "reward"] = rollout["next", "agents", "reward"].sum(-2)
    with torch.no_grad():
        values = networks.value_network(rollout.clone())[keys.STATE_VALUE]
        next_values = networks.value_network(rollout["next"].clone())[keys.STATE_VALUE]
    # shifted=True: torchrl's default path marks the step after every episode start as a reset
    # too, which would zero the memory behind V(s_1) of each episode.
    estimator = GAE(gamma=0.95, lmbda=0.92, value_network=networks.value_network, shifted=True)
    with torch.no_grad(), set_recurrent_mode(recurrent):
        estimator(rollout)
    assert rollout["advantage"].shape == (2, 6, 1)
    assert torch.isfinite(rollout["advantage"]).all()
    torch.testing.assert_close(rollout[keys.STATE_VALUE], values)
    torch.testing.assert_close(rollout["next", keys.STATE_VALUE], next_values)


def test_config_is_a_hydra_structured_config():
    schema = OmegaConf.structured(TerraShiftModelConfig)
    merged = OmegaConf.merge(schema, OmegaConf.create({"embed_dim": 64, "num_heads": 4}))
    config = OmegaConf.to_object(merged)
    assert isinstance(config, TerraShiftModelConfig)
    assert (config.embed_dim, config.cnn_channels) == (64, [16, 32, 32])
    with pytest.raises(ValueError, match="num_heads"):
        TerraShiftModelConfig(embed_dim=100, num_heads=8)


def test_default_config_matches_table_1():
    config = TerraShiftModelConfig()
    assert (config.embed_dim, config.num_heads, config.trunk_layers) == (128, 8, 3)
    assert (config.cnn_channels, config.cnn_kernels, config.cnn_strides, config.cnn_groups) == (
        [16, 32, 32],
        [5, 3, 3],
        [2, 2, 1],
        [4, 8, 8],
    )
    assert config.swin_windows == [2, 4]
    budget = (config.tokenizer_base_tokens, config.tokenizer_min_tokens)
    assert budget + (config.tokenizer_max_tokens,) == (12, 8, 16)
    assert (config.gru_layers, config.min_concentration) == (2, 1.01)
    assert config.dropout == 0.0  # Table 1: 0.05, which corrupts PPO's ratio (docs/results.md)
    assert (config.policy_hidden_dim, config.critic_hidden_dim, config.ffn_dim) == (192, 128, 384)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("relative_objects", [False, True])
def test_cuda_bf16_autocast_training_pass(make_batch, relative_objects):
    torch.manual_seed(0)
    config = TerraShiftModelConfig(relative_objects=relative_objects)
    networks = make_terrashift_networks(config).cuda().eval()
    data = make_batch((4, 8), num_agents=8, is_init=False).cuda()
    data["is_init"][:, 0] = True
    with set_recurrent_mode(True):
        reference = networks.actor.get_dist(data.clone()).log_prob(data[keys.ACTION])
        with torch.autocast("cuda", dtype=torch.bfloat16):
            td = data.clone()
            dist = networks.actor.get_dist(td)
            networks.value_head(td)
            networks.baseline_head(td)
    assert td[keys.NEXT_RECURRENT_STATE].dtype == torch.float32
    log_prob = dist.log_prob(data[keys.ACTION])
    torch.testing.assert_close(log_prob, reference, atol=0.5, rtol=0.05)
    (
        log_prob.mean() + td[keys.STATE_VALUE].float().mean() + td[keys.BASELINE].float().mean()
    ).backward()
    assert all(p.grad is not None for p in networks.parameters())
