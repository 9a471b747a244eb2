"""TerraShift networks as TensorDict modules: shared trunk, Beta (or Gaussian) actor, MA-POCA
critics, and IPPO's per-agent value.

For another environment with flat per-agent observations, :class:`CentralValue` and
:class:`CounterfactualBaseline` are MA-POCA's critics built from plain sizes (:func:`mlp_value`
and :class:`CounterfactualMLP` cheaper ones for a team of a fixed size). For TerraShift,
start with :func:`make_terrashift_networks`; :mod:`terrashift_rl.modules.networks` documents
how the trunk is shared and which keys every module reads and writes, and
:mod:`terrashift_rl.modules.trunk` the recurrent-state conventions.
"""

from terrashift_rl.modules import keys
from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.critics import (
    AttentionBaseline,
    AttentionValue,
    CentralValue,
    CentralValueHead,
    CounterfactualBaseline,
    CounterfactualBaselineHead,
)
from terrashift_rl.modules.distributions import ScaledBeta
from terrashift_rl.modules.entities import AgentEncoder, ObjectEncoder
from terrashift_rl.modules.heightmap import AdaptiveSpatialTokenizer, HeightmapEncoder
from terrashift_rl.modules.independent import AgentValueHead, make_agent_value_head
from terrashift_rl.modules.mlp_critics import CounterfactualMLP, MLPBaseline, mlp_value
from terrashift_rl.modules.networks import TerraShiftNetworks, make_terrashift_networks
from terrashift_rl.modules.object_reader import ObjectReader
from terrashift_rl.modules.policy import BetaPolicyHead, GaussianPolicyHead
from terrashift_rl.modules.trunk import SharedEmbeddingNetwork, TerraShiftTrunk

__all__ = [
    "AdaptiveSpatialTokenizer",
    "AgentEncoder",
    "AgentValueHead",
    "AttentionBaseline",
    "AttentionValue",
    "BetaPolicyHead",
    "CentralValue",
    "CentralValueHead",
    "CounterfactualBaseline",
    "CounterfactualBaselineHead",
    "CounterfactualMLP",
    "GaussianPolicyHead",
    "HeightmapEncoder",
    "MLPBaseline",
    "ObjectEncoder",
    "ObjectReader",
    "ScaledBeta",
    "SharedEmbeddingNetwork",
    "TerraShiftModelConfig",
    "TerraShiftNetworks",
    "TerraShiftTrunk",
    "keys",
    "make_agent_value_head",
    "make_terrashift_networks",
    "mlp_value",
]
