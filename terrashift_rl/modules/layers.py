"""Attention, feed-forward and dropout blocks shared by the encoders, trunk and critic heads.

Dropout follows one rule everywhere: it acts only in forward passes that autograd records while
the module is in training mode, i.e. in the gradient update. Collection, GAE and evaluation run
without autograd (torchrl collectors and value estimators use ``torch.no_grad``), so they are
deterministic even if nobody calls ``.eval()``, and the log-probabilities stored at collection are
the ones a no-grad recomputation with the same weights gives.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "MultiHeadAttention",
    "ResidualSelfAttention",
    "UpdateDropout",
    "dropout_active",
    "feed_forward",
    "masked_mean",
]


def dropout_active(module: nn.Module) -> bool:
    """Whether dropout applies in the current pass: training mode and autograd recording.

    Examples:
        >>> layer = nn.Linear(2, 2)
        >>> dropout_active(layer)
        True
        >>> with torch.no_grad():
        ...     dropout_active(layer)
        False
        >>> dropout_active(layer.eval())
        False
    """
    return module.training and torch.is_grad_enabled()


class UpdateDropout(nn.Dropout):
    """Dropout that acts only in passes that will be backpropagated (see :func:`dropout_active`).

    Examples:
        >>> dropout = UpdateDropout(0.5)
        >>> with torch.no_grad():
        ...     bool((dropout(torch.ones(8)) == 1).all())
        True
    """

    def forward(self, input: Tensor) -> Tensor:
        return F.dropout(input, self.p, training=dropout_active(self))


def feed_forward(
    in_dim: int, hidden_dim: int, out_dim: int, *, dropout: float = 0.0
) -> nn.Sequential:
    """Linear -> GELU -> dropout -> Linear.

    Examples:
        >>> feed_forward(4, 8, 2)(torch.zeros(3, 4)).shape
        torch.Size([3, 2])
    """
    return nn.Sequential(
        nn.Linear(in_dim, hidden_dim),
        nn.GELU(),
        UpdateDropout(dropout),
        nn.Linear(hidden_dim, out_dim),
    )


def masked_mean(values: Tensor, mask: Tensor | None, *, dim: int = -2) -> Tensor:
    """Mean over ``dim`` of the entries where ``mask`` is True (zeros where none is).

    Args:
        values: values, e.g. [B, K, d].
        mask: bool, the shape of ``values`` without its last dim (e.g. [B, K]); None keeps all.
        dim: the dim to average over.

    Examples:
        >>> values = torch.tensor([[[1.0], [3.0], [100.0]]])
        >>> masked_mean(values, torch.tensor([[True, True, False]]))
        tensor([[2.]])
    """
    if mask is None:
        return values.mean(dim)
    weights = mask.unsqueeze(-1).to(values.dtype)
    return (values * weights).sum(dim) / weights.sum(dim).clamp_min(1.0)


class MultiHeadAttention(nn.Module):
    """Multi-head attention of queries over a context, with a key mask.

    A query whose every key is masked attends to nothing: its output is exactly zero (rather than
    the NaN that a fully masked softmax gives), so padding can never leak in.

    Attention is written out (two einsums and a softmax) rather than calling
    ``scaled_dot_product_attention``: every set here holds 1 to 16 tokens, where SDPA's fused CUDA
    kernels pad each (batch, head) pair to 64 x 64 tiles and dominate a training step (its cuDNN
    backend also failed in bf16 backward with large batches; docs/benchmarks.md). There is no
    dropout on the attention weights; blocks drop the attention's output instead.

    Args:
        embed_dim: width of queries, keys and outputs.
        num_heads: attention heads; divides ``embed_dim``.

    Examples:
        >>> attention = MultiHeadAttention(8, 2)
        >>> agents, tokens = torch.randn(3, 4, 8), torch.randn(3, 5, 8)
        >>> key_mask = torch.tensor([True, True, False, False, False]).expand(3, 5)
        >>> attention(agents, tokens, key_mask).shape
        torch.Size([3, 4, 8])
        >>> attention(agents, tokens, torch.zeros(3, 5, dtype=torch.bool)).abs().max()
        tensor(0., grad_fn=<MaxBackward1>)
    """

    def __init__(self, embed_dim: int, num_heads: int) -> None:
        super().__init__()
        if embed_dim % num_heads:
            raise ValueError(f"num_heads {num_heads} does not divide embed_dim {embed_dim}.")
        self.num_heads = num_heads
        self.scale = (embed_dim // num_heads) ** -0.5
        self.query_projection = nn.Linear(embed_dim, embed_dim)
        self.key_value_projection = nn.Linear(embed_dim, 2 * embed_dim)
        self.output_projection = nn.Linear(embed_dim, embed_dim)

    def forward(self, query: Tensor, context: Tensor, key_mask: Tensor | None = None) -> Tensor:
        """Attend from ``query`` [..., Q, d] to ``context`` [..., C, d].

        Args:
            query: queries, [..., Q, d].
            context: keys and values, [..., C, d].
            key_mask: bool, True where a key may be attended: [..., C] for every query alike, or
                [..., Q, C] per query. None attends to every key.

        Returns:
            The attended values, [..., Q, d].
        """
        queries = self.query_projection(query).unflatten(-1, (self.num_heads, -1))
        keys_values = self.key_value_projection(context).unflatten(-1, (2, self.num_heads, -1))
        keys, values = keys_values.unbind(-3)
        scores = torch.einsum("...qhc,...khc->...hqk", queries, keys) * self.scale
        has_key = None
        if key_mask is not None:
            if key_mask.dim() == query.dim() - 1:
                key_mask = key_mask.unsqueeze(-2)
            has_key = key_mask.any(-1, keepdim=True)
            # Rows without any key attend everywhere (finite softmax) and are zeroed below.
            attendable = (key_mask | ~has_key).unsqueeze(-3)
            scores = scores.masked_fill(~attendable, float("-inf"))
        weights = scores.softmax(-1).to(values.dtype)
        attended = torch.einsum("...hqk,...khc->...qhc", weights, values)
        output = self.output_projection(attended.flatten(-2))
        if has_key is not None:
            output = output.masked_fill(~has_key, 0.0)
        return output


class ResidualSelfAttention(nn.Module):
    """MA-POCA's residual self-attention over a set: ``LayerNorm(x + Attention(LayerNorm(x)))``.

    Args:
        embed_dim: width of the set's elements.
        num_heads: attention heads.
        dropout: dropout on the attention's output (update passes only).

    Examples:
        >>> block = ResidualSelfAttention(8, 2)
        >>> block(torch.randn(3, 4, 8), torch.ones(3, 4, dtype=torch.bool)).shape
        torch.Size([3, 4, 8])
    """

    def __init__(self, embed_dim: int, num_heads: int, *, dropout: float = 0.0) -> None:
        super().__init__()
        self.input_norm = nn.LayerNorm(embed_dim)
        self.attention = MultiHeadAttention(embed_dim, num_heads)
        self.attention_dropout = UpdateDropout(dropout)
        self.output_norm = nn.LayerNorm(embed_dim)

    def forward(self, elements: Tensor, key_mask: Tensor | None = None) -> Tensor:
        """Self-attend within [..., N, d]; ``key_mask`` [..., N] or [..., N, N] as in attention."""
        normed = self.input_norm(elements)
        attended = self.attention_dropout(self.attention(normed, normed, key_mask))
        return self.output_norm(elements + attended)
