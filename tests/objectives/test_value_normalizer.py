"""ValueNormalizer: debiased running statistics, identity before any data, clear errors."""

import numpy as np
import pytest
import torch

from terrashift_rl.objectives import ValueNormalizer


def test_statistics_are_the_debiased_moving_averages():
    decay = 0.9
    normalizer = ValueNormalizer(decay=decay)
    batches = [np.random.default_rng(seed).normal(3.0, 2.0, 50) for seed in range(4)]
    mean = square = weight = 0.0
    for batch in batches:
        normalizer.update(torch.as_tensor(batch, dtype=torch.float32))
        mean = decay * mean + (1 - decay) * batch.mean()
        square = decay * square + (1 - decay) * (batch**2).mean()
        weight = decay * weight + (1 - decay)
    expected_mean = mean / weight
    expected_std = np.sqrt(square / weight - expected_mean**2)
    got_mean, got_std = normalizer.statistics()
    assert got_mean.item() == pytest.approx(expected_mean, rel=1e-5)
    assert got_std.item() == pytest.approx(expected_std, rel=1e-5)
    values = torch.linspace(-3, 3, 7)
    torch.testing.assert_close(normalizer.denormalize(normalizer.normalize(values)), values)


def test_identity_before_the_first_update_and_a_variance_floor():
    normalizer = ValueNormalizer(epsilon=1e-2)
    values = torch.tensor([-1.5, 0.0, 2.0])
    torch.testing.assert_close(normalizer.normalize(values), values)
    torch.testing.assert_close(normalizer.denormalize(values), values)
    normalizer.update(torch.full((8,), 4.0))  # zero variance: the floor holds
    mean, std = normalizer.statistics()
    assert mean.item() == pytest.approx(4.0) and std.item() == pytest.approx(0.1)


def test_state_dict_round_trip():
    normalizer = ValueNormalizer(decay=0.5)
    normalizer.update(torch.tensor([1.0, 2.0, 6.0]))
    restored = ValueNormalizer(decay=0.5)
    restored.load_state_dict(normalizer.state_dict())
    for got, expected in zip(restored.statistics(), normalizer.statistics(), strict=True):
        torch.testing.assert_close(got, expected)


def test_bad_input_is_refused_and_non_finite_targets_leave_the_statistics():
    with pytest.raises(ValueError, match="decay"):
        ValueNormalizer(decay=1.0)
    with pytest.raises(ValueError, match="epsilon"):
        ValueNormalizer(epsilon=0.0)
    normalizer = ValueNormalizer()
    normalizer.update(torch.tensor([1.0, 3.0]))
    before = {name: value.clone() for name, value in normalizer.state_dict().items()}
    for bad in (float("nan"), float("inf"), float("-inf")):
        normalizer.update(torch.tensor([1.0, bad]))  # no host read: skipped on the device
        for name, value in normalizer.state_dict().items():
            assert torch.equal(value, before[name]), (bad, name)
    normalizer.update(torch.tensor([5.0, 7.0]))
    assert normalizer.weight > before["weight"]  # a finite update still moves them
