"""Heightmap branch: token grid sizes, the adaptive tokenizer's bounded selection, position code."""

from __future__ import annotations

import pytest
import torch

from terrashift_rl.modules import AdaptiveSpatialTokenizer, HeightmapEncoder, SharedEmbeddingNetwork
from terrashift_rl.modules.encodings import sincos_grid_code


@pytest.mark.parametrize(
    ("map_side", "grid_side", "candidates", "kept"),
    [(16, 4, 4, 4), (32, 4, 4, 4), (64, 8, 16, 14), (128, 16, 64, 16)],
)
def test_token_count_is_bounded_as_the_map_grows(
    small_config, map_side, grid_side, candidates, kept
):
    encoder = HeightmapEncoder(small_config)
    assert encoder.token_grid_shape(map_side, map_side) == (grid_side, grid_side)
    # The 2 x 2 patch merge halves each side of the pooled grid.
    assert (grid_side // 2) ** 2 == candidates
    tokens = encoder(torch.rand(2, 1, map_side, map_side) * 2 - 1)
    assert tokens.shape == (2, kept, small_config.embed_dim)
    assert kept <= small_config.tokenizer_max_tokens
    assert torch.isfinite(tokens).all()


def test_non_square_maps_pool_to_a_rectangular_grid(small_config):
    encoder = HeightmapEncoder(small_config)
    assert encoder.token_grid_shape(32, 64) == (4, 8)
    assert encoder(torch.zeros(2, 1, 32, 64)).shape == (2, 8, small_config.embed_dim)


def test_tokenizer_budget_follows_base_min_max():
    tokenizer = AdaptiveSpatialTokenizer(8, base_tokens=12, min_tokens=8, max_tokens=16)
    assert tokenizer.token_budget(12) == 12
    for candidates in range(1, 300):
        budget = tokenizer.token_budget(candidates)
        assert budget == min(candidates, max(8, min(16, budget)))
        assert budget <= min(candidates, 16)
        assert budget >= min(candidates, 8)
    assert tokenizer.token_budget(4) == 4
    assert tokenizer.token_budget(1000) == 16


def test_tokenizer_keeps_the_highest_scoring_tokens():
    torch.manual_seed(0)
    tokenizer = AdaptiveSpatialTokenizer(4, base_tokens=2, min_tokens=2, max_tokens=2)
    tokens = torch.randn(3, 10, 4)
    scores = tokenizer.importance(tokens).squeeze(-1)
    kept = tokenizer(tokens)
    assert kept.shape == (3, 2, 4)
    best = scores.topk(2, dim=-1)
    for env in range(3):
        for rank in range(2):
            index = best.indices[env, rank]
            expected = tokens[env, index] * torch.sigmoid(best.values[env, rank])
            torch.testing.assert_close(kept[env, rank], expected)


def test_tokenizer_scorer_receives_gradients_through_the_selection():
    tokenizer = AdaptiveSpatialTokenizer(4, base_tokens=2, min_tokens=2, max_tokens=2)
    tokenizer(torch.randn(3, 10, 4)).square().sum().backward()
    for parameter in tokenizer.importance.parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0


def test_grid_code_gives_every_token_a_distinct_code():
    for side in (2, 4, 8, 16):
        code = sincos_grid_code(side, side, 32).reshape(side * side, 32)
        distances = torch.cdist(code, code) + torch.eye(side * side) * 10
        assert distances.min() > 0.1


def test_encoder_runs_once_per_environment_not_per_agent(small_config):
    encoder = HeightmapEncoder(small_config)
    calls = []
    encoder.stem.register_forward_hook(lambda module, args, output: calls.append(args[0].shape[0]))
    network = SharedEmbeddingNetwork(small_config)
    network.heightmap_encoder = encoder
    network(torch.zeros(5, 1, 32, 32), torch.zeros(5, 4, 9), torch.zeros(5, 16, 9))
    assert calls == [5]
