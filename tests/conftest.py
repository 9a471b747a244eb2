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
