import collections

import pytest
import torch


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


HOST_READS = ("aten::_local_scalar_dense", "aten::nonzero", "aten::masked_select", "tolist")
"""What waits on a CUDA device to bring a result to the host, counted on the CPU, where the same
operators run: scalar reads (``.item()``, ``bool(tensor)``, ``float(tensor)``), the sizes of
boolean indexing (``nonzero``, ``masked_select``) and ``.tolist()``."""


@pytest.fixture
def host_reads(monkeypatch):
    """``host_reads(function, *args)`` calls ``function`` and returns how often it made each read
    of :data:`HOST_READS` (those it made at least once)."""

    def count(function, *args):
        tolist = torch.Tensor.tolist
        calls = []

        def counted(tensor):
            calls.append("tolist")
            return tolist(tensor)

        monkeypatch.setattr(torch.Tensor, "tolist", counted)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profiler:
            function(*args)
        monkeypatch.setattr(torch.Tensor, "tolist", tolist)
        names = [event.name for event in profiler.events()] + calls
        return collections.Counter(name for name in names if name in HOST_READS)

    return count


@pytest.fixture
def rollouts_around_an_advance():
    """Rollouts of 2 decisions by the curriculum envs of 4 environments (two stages from an
    8 x 8 scene with 2 agents and 1 sphere to ``target``, half of them on the first), before and
    after its advance, with the networks of ``model``: ``(env after, before, after)``."""
    from terrashift_rl.modules import make_terrashift_networks
    from terrashift_rl.training.curriculum import Curriculum, make_curriculum_env
    from terrashift_rl.training.settings import CurriculumSettings

    def rollouts(target, model):
        settings = CurriculumSettings(
            stages=2, start_grid_size=8, start_num_agents=2, start_num_objects=1, mix=0.5
        )
        curriculum = Curriculum(target, settings)
        networks = make_terrashift_networks(model)
        envs = []
        with torch.no_grad():
            for _ in range(2):
                env = make_curriculum_env(curriculum, networks, num_envs=4, device="cpu", seed=0)
                envs.append(env.rollout(2, networks.actor))
                if not curriculum.final:
                    curriculum.advance(env_steps=8)
        return (env, *envs)

    return rollouts
