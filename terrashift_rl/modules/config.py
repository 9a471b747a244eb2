"""Sizes of the TerraShift networks, as a Hydra structured config.

The defaults are the sizes of the reported pretraining run (TerraShift paper, Table 1 (b) and (c)).
Nothing here depends on the number of agents, objects or grid columns: the same weights run the
15 x 15 pretraining task with 8 agents and the 30 x 30 finetuning task with 16.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from terrashift_rl.fields import Allowed, above, at_least, check_fields, interval, one_of, setting

__all__ = ["DISTRIBUTIONS", "TerraShiftModelConfig"]

STAGES = Allowed(
    lambda value: 1 <= len(value) <= 8 and all(entry >= 1 for entry in value),
    "a list of 1 to 8 integers, each >= 1",
)
"""The values of a per-stage list (the CNN stem's convolutions, the Swin stages)."""

DISTRIBUTIONS = ("beta", "normal")
"""Values of :attr:`TerraShiftModelConfig.distribution`."""


@dataclass
class TerraShiftModelConfig:
    """Network sizes; the defaults reproduce Table 1 of the TerraShift paper.

    Usable as a Hydra structured config (``OmegaConf.structured(TerraShiftModelConfig)``).

    Examples:
        >>> config = TerraShiftModelConfig()
        >>> config.embed_dim, config.trunk_layers, config.gru_layers
        (128, 3, 2)
        >>> TerraShiftModelConfig.small().embed_dim
        32
    """

    embed_dim: int = setting(128, at_least(1))
    """Width d of every token and agent embedding."""
    num_heads: int = setting(8, at_least(1))
    """Attention heads in the trunk, the Swin stages and the critic heads."""
    dropout: float = setting(0.0, interval(0, 1, high_open=True))
    """Dropout probability, applied only in passes that will be backpropagated (see
    ``layers``). Table 1 uses 0.05, but collection has none, so in an update the ratio of new
    to stored log-probabilities then also carries dropout's noise: late in a run most of the
    logged approximate KL and clip fraction (``benchmarks/diagnose_policy.py``), and runs with
    it lost more and more spheres (docs/experiments.md)."""

    agent_observation_dim: int = setting(9, at_least(1))
    """Features per agent: wavelet [x, y, theta, A, sigma_x, sigma_y, v_x, v_y, omega]."""
    agent_hidden_dim: int = setting(128, at_least(1))
    """Hidden width of the agent MLP (9 -> 128 -> d)."""
    agent_id_code: bool = setting(True)
    """Add a sinusoidal agent-index code; breaks permutation equivariance over agents."""
    agent_id_dim: int = setting(16, at_least(1))
    """Width of the sinusoidal agent-index code before its projection to d."""

    object_feature_dim: int = setting(9, at_least(1))
    """Features per object slot: position, goal position, velocity."""
    object_hidden_dim: int = setting(64, at_least(1))
    """Hidden width of the per-slot object MLP (9 -> 64 -> d)."""
    relative_objects: bool = setting(False)
    """Give every agent its own object tokens, encoded from the slot's features and the offsets
    from the agent's wavelet to the object and to its goal, straight and the short way round
    a wrapping grid (17 -> 64 -> d). Off is the paper's
    design: one token per object, shared by all agents. Reads x, y as the first two agent
    features and as features 0-1 (object) and 3-4 (goal) of a slot, all over the platform."""

    heightmap_channels: int = setting(1, at_least(1))
    """Channels of the heightmap observation (coordinate channels are added on top)."""
    camera_channels: int = setting(0, at_least(0))
    """Channels of the camera observation (``"camera"``), stacked on the heightmap's as further
    inputs of the CNN stem (which then runs on the camera's pixel lattice); 0: no camera, 1
    for TerraShift's greyscale camera (``camera_resolution`` > 0)."""
    object_tokens: bool = setting(True)
    """Read the object sequence (``"objects"``, ``"objects_mask"``) as a token set the agents
    attend to; False for an environment with ``observe_objects=False``: the agents attend to
    the spatial tokens alone, and the critics, which share the trunk, see no more than the
    policy does (unless ``critic_objects``)."""
    critic_objects: bool = setting(False)
    """The value and baseline heads read the object sequence handed to the critics alone
    (``("privileged", "objects")``, from a scene with ``privileged_objects``): in each head
    every agent's embedding attends to the objects' tokens before the head's own attention, so
    the critics see where spheres and goals are while the policy sees only what the trunk
    reads (centralised training, decentralised execution). Refused with ``object_tokens``,
    where the trunk already reads the objects for every head."""
    cnn_channels: list[int] = setting([16, 32, 32], STAGES)
    """Output channels of the CNN stem's convolutions."""
    cnn_kernels: list[int] = setting([5, 3, 3], STAGES)
    """Kernel sizes of the CNN stem's convolutions."""
    cnn_strides: list[int] = setting([2, 2, 1], STAGES)
    """Strides of the CNN stem's convolutions."""
    cnn_groups: list[int] = setting([4, 8, 8], STAGES)
    """GroupNorm groups after each convolution of the CNN stem."""
    heightmap_cells_per_token: int = setting(8, at_least(1))
    """Heightmap cells per pooled token along each side: a 32 x 32 map pools to 4 x 4 tokens,
    64 x 64 to 8 x 8 (rounded up to a multiple of the Swin windows and the patch merge)."""
    swin_windows: list[int] = setting([2, 4], STAGES)
    """Window side of each windowed self-attention stage; a 2 x 2 patch merge follows the last."""
    tokenizer_base_tokens: int = setting(12, at_least(1))
    """Spatial-token budget when the heightmap yields exactly this many candidate tokens."""
    tokenizer_min_tokens: int = setting(8, at_least(1))
    """Lower bound of the spatial-token budget (never more than the candidates)."""
    tokenizer_max_tokens: int = setting(16, at_least(1))
    """Upper bound of the spatial-token budget, whatever the heightmap size."""
    tokenizer_hidden_dim: int = setting(64, at_least(1))
    """Hidden width of the tokenizer's importance scorer."""

    trunk_layers: int = setting(3, interval(1, 64))
    """Layers of [parallel cross-attention, agent self-attention, feed-forward]."""
    ffn_dim: int = setting(384, at_least(1))
    """Hidden width of every feed-forward block (trunk and Swin stages)."""
    output_hidden_dim: int = setting(192, at_least(1))
    """Hidden width of the trunk's output MLP (d -> 192 -> d)."""
    gru_layers: int = setting(2, interval(1, 16))
    """Stacked GRU layers of the agent memory (hidden size d)."""

    policy_hidden_dim: int = setting(192, at_least(1))
    """Hidden width of the shared policy MLP (d -> 192 -> 192)."""
    min_concentration: float = setting(1.01, above(0))
    """Lower bound of both Beta concentrations; above 1 the density is unimodal and finite."""
    distribution: str = setting("beta", one_of(*DISTRIBUTIONS))
    """The policy's action distribution: ``beta`` (the paper's: a Beta per action dimension on
    ``[-action_range, action_range]``, concentrations from the network) or ``normal`` (a
    Gaussian whose mean comes from the network and whose standard deviation is one learned
    parameter per action dimension, shared by every state, as in RSL-RL and rl_games; the
    simulator clips its samples to the actuators' [-1, 1]). A Beta whose mean nears an end of
    its support must be concentrated, so there a decisive action costs entropy; a Gaussian's
    mean and spread are set apart."""
    initial_std: float = setting(0.5, above(0))
    """With ``distribution=normal``, the standard deviation every action dimension starts
    from, > 0 (0.5 is about the spread of the Beta head's initial Beta(1.7, 1.7) on [-1, 1])."""
    initial_action_mean: list[float] = setting([])
    """The policy's mean action at initialisation, one value per action dimension (TerraShift's
    v_x, v_y, omega, amplitude, sigma_x, sigma_y), each inside +-action_range; empty: the
    middle of the range. It shifts the initial biases of the policy's output layers, so it
    holds exactly where the rest of those layers reads zero: a Beta keeps its smaller
    concentration at the centred start's (``min_concentration + log 2``) and raises the other;
    a Gaussian's mean moves by it. It changes only initial weights, so a run may resume with
    another value."""
    critic_hidden_dim: int = setting(128, at_least(1))
    """Hidden width of the value and baseline MLPs."""
    action_range: float = setting(1.0, at_least(1))
    """The policy's Beta spans [-action_range, action_range] in every action dimension, >= 1.
    The simulator clips actions to the actuators' [-1, 1]; above 1, a mean action reaches an
    actuator's limit at a moderate concentration instead of the Beta's very edge (2: a mean at
    three quarters of the Beta's support), and samples beyond the limit act as the limit."""

    def __post_init__(self) -> None:
        check_fields(self, "model")
        stem = ("cnn_channels", "cnn_kernels", "cnn_strides", "cnn_groups")
        if len({len(getattr(self, name)) for name in stem}) != 1:
            raise ValueError(
                f"model.{', model.'.join(stem)} must have the same length, got "
                + ", ".join(str(getattr(self, name)) for name in stem)
            )
        for channels, groups in zip(self.cnn_channels, self.cnn_groups, strict=True):
            if channels % groups:
                raise ValueError(
                    f"model.cnn_groups must divide model.cnn_channels entry by entry, got "
                    f"{self.cnn_groups} for {self.cnn_channels}"
                )
        if self.embed_dim % self.num_heads or self.embed_dim % 4:
            raise ValueError(
                f"model.embed_dim must be a multiple of 4 (the 2-D sin-cos code) and of "
                f"model.num_heads ({self.num_heads}), got {self.embed_dim}"
            )
        if self.agent_id_dim % 2:
            raise ValueError(
                f"model.agent_id_dim must be even (sine and cosine halves), got {self.agent_id_dim}"
            )
        budget = (self.tokenizer_min_tokens, self.tokenizer_base_tokens, self.tokenizer_max_tokens)
        if not budget[0] <= budget[1] <= budget[2]:
            raise ValueError(
                "model.tokenizer_min_tokens <= model.tokenizer_base_tokens <= "
                f"model.tokenizer_max_tokens must hold, got {budget}"
            )
        if self.critic_objects and self.object_tokens:
            raise ValueError(
                "model.critic_objects=true gives the critics the object sequence that "
                "model.object_tokens=true already gives the trunk, and so every head: set "
                "model.object_tokens=false (the policy then reads no objects) or "
                "model.critic_objects=false"
            )
        if any(abs(value) >= self.action_range for value in self.initial_action_mean):
            raise ValueError(
                f"model.initial_action_mean must hold values inside +-model.action_range "
                f"({self.action_range}), got {list(self.initial_action_mean)}"
            )

    @property
    def token_grid_multiple(self) -> int:
        """The pooled token grid's side is a multiple of this (every window and the 2x2 merge)."""
        return math.lcm(2, *self.swin_windows)

    @classmethod
    def small(cls) -> TerraShiftModelConfig:
        """A narrow, shallow preset for CPU tests; same structure, same budgets."""
        return cls(
            embed_dim=32,
            num_heads=4,
            agent_hidden_dim=32,
            agent_id_dim=8,
            object_hidden_dim=16,
            cnn_channels=[4, 8, 8],
            cnn_groups=[2, 4, 4],
            trunk_layers=2,
            ffn_dim=64,
            output_hidden_dim=48,
            policy_hidden_dim=48,
            critic_hidden_dim=32,
            tokenizer_hidden_dim=16,
        )
