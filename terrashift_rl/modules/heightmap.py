"""Heightmap encoder: CNN stem, pooled token grid, Swin-style stages and an adaptive tokenizer.

The heightmap is a per-environment observation, so this branch runs once per environment step;
the agents of that environment share its tokens through cross-attention.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.encodings import sincos_grid_code
from terrashift_rl.modules.layers import MultiHeadAttention, UpdateDropout, feed_forward

__all__ = [
    "AdaptiveSpatialTokenizer",
    "HeightmapEncoder",
    "PatchMerging",
    "WindowAttentionBlock",
    "stack_camera",
]


class WindowAttentionBlock(nn.Module):
    """Pre-norm transformer block whose self-attention stays inside square windows.

    Windows do not overlap and are not shifted between stages (as in the original TerraShift).

    Args:
        embed_dim: token width.
        num_heads: attention heads.
        window_size: window side; divides both sides of the grid.
        ffn_dim: hidden width of the feed-forward block.
        dropout: dropout probability (update passes only).

    Examples:
        >>> block = WindowAttentionBlock(8, 2, window_size=2, ffn_dim=16)
        >>> block(torch.randn(3, 4, 6, 8)).shape
        torch.Size([3, 4, 6, 8])
    """

    def __init__(
        self,
        embed_dim: int,
        num_heads: int,
        *,
        window_size: int,
        ffn_dim: int,
        dropout: float = 0.0,
    ) -> None:
        super().__init__()
        self.window_size = window_size
        self.attention_norm = nn.LayerNorm(embed_dim)
        self.attention = MultiHeadAttention(embed_dim, num_heads)
        self.feed_forward_norm = nn.LayerNorm(embed_dim)
        self.feed_forward = feed_forward(embed_dim, ffn_dim, embed_dim, dropout=dropout)
        self.residual_dropout = UpdateDropout(dropout)

    def forward(self, grid: Tensor) -> Tensor:
        """Refine a token grid [B, R, C, d]; R and C are multiples of the window side."""
        batch, rows, cols, dim = grid.shape
        side = self.window_size
        windows = (
            grid.reshape(batch, rows // side, side, cols // side, side, dim)
            .transpose(2, 3)
            .reshape(batch, (rows // side) * (cols // side), side * side, dim)
        )
        normed = self.attention_norm(windows)
        windows = windows + self.residual_dropout(self.attention(normed, normed))
        grid = (
            windows.reshape(batch, rows // side, cols // side, side, side, dim)
            .transpose(2, 3)
            .reshape(batch, rows, cols, dim)
        )
        return grid + self.residual_dropout(self.feed_forward(self.feed_forward_norm(grid)))


class PatchMerging(nn.Module):
    """Swin patch merging: each 2 x 2 block of tokens becomes one token of the same width.

    Examples:
        >>> PatchMerging(8)(torch.randn(3, 4, 4, 8)).shape
        torch.Size([3, 2, 2, 8])
    """

    def __init__(self, embed_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(4 * embed_dim)
        self.reduction = nn.Linear(4 * embed_dim, embed_dim, bias=False)

    def forward(self, grid: Tensor) -> Tensor:
        """Merge a token grid [B, R, C, d] (R and C even) into [B, R/2, C/2, d]."""
        batch, rows, cols, dim = grid.shape
        blocks = (
            grid.reshape(batch, rows // 2, 2, cols // 2, 2, dim)
            .permute(0, 1, 3, 2, 4, 5)
            .reshape(batch, rows // 2, cols // 2, 4 * dim)
        )
        return self.reduction(self.norm(blocks))


class AdaptiveSpatialTokenizer(nn.Module):
    """Keeps a bounded number of the most informative spatial tokens.

    A small MLP scores every token; the top ``budget`` tokens are kept, each scaled by the sigmoid
    of its score, which is how the scorer receives gradients (top-k selection alone has none).

    The budget adapts to the number N of candidate tokens: it is the geometric mean
    ``sqrt(base_tokens * N)`` rounded and clamped to [min_tokens, max_tokens], and never more than
    N. It equals ``base_tokens`` when N does, grows slower than the map's area, and is capped, so
    the cross-attention cost stays bounded on large maps. With the defaults (12/8/16) a 32 x 32
    map gives 4 candidates (all kept), 64 x 64 gives 16 (14 kept) and 128 x 128 gives 64
    (16 kept). The budget depends only on shapes, so batches keep a static shape.

    Args:
        embed_dim: token width.
        base_tokens: budget when there are exactly this many candidates.
        min_tokens: lower bound of the budget.
        max_tokens: upper bound of the budget.
        hidden_dim: hidden width of the importance scorer.

    Examples:
        >>> tokenizer = AdaptiveSpatialTokenizer(8, base_tokens=12, min_tokens=8, max_tokens=16)
        >>> [tokenizer.token_budget(n) for n in (4, 16, 64, 256)]
        [4, 14, 16, 16]
        >>> tokenizer(torch.randn(3, 64, 8)).shape
        torch.Size([3, 16, 8])
    """

    def __init__(
        self,
        embed_dim: int,
        *,
        base_tokens: int,
        min_tokens: int,
        max_tokens: int,
        hidden_dim: int = 64,
    ) -> None:
        super().__init__()
        if not 1 <= min_tokens <= base_tokens <= max_tokens:
            raise ValueError("expected 1 <= min_tokens <= base_tokens <= max_tokens.")
        self.base_tokens = base_tokens
        self.min_tokens = min_tokens
        self.max_tokens = max_tokens
        self.importance = nn.Sequential(
            nn.Linear(embed_dim, hidden_dim), nn.GELU(), nn.Linear(hidden_dim, 1)
        )

    def token_budget(self, num_candidates: int) -> int:
        """Number of tokens kept out of ``num_candidates``."""
        budget = round(math.sqrt(self.base_tokens * num_candidates))
        return min(num_candidates, max(self.min_tokens, min(self.max_tokens, budget)))

    def forward(self, tokens: Tensor) -> Tensor:
        """Select from candidate tokens [B, N, d]; returns [B, token_budget(N), d]."""
        scores = self.importance(tokens).squeeze(-1)
        kept_scores, kept_index = scores.topk(self.token_budget(tokens.shape[-2]), dim=-1)
        kept = tokens.gather(-2, kept_index.unsqueeze(-1).expand(-1, -1, tokens.shape[-1]))
        return kept * torch.sigmoid(kept_scores).unsqueeze(-1)


def average_pool(features: Tensor, rows: int, cols: int) -> Tensor:
    """Adaptive average pooling of [B, C, H, W] to rows x cols. Where the sizes divide it is a
    plain average pool, the same windows, whose CUDA backward (unlike the adaptive one's) has a
    deterministic implementation (``train.deterministic``).

    Examples:
        >>> x = torch.randn(2, 3, 8, 8)
        >>> torch.allclose(average_pool(x, 4, 4), nn.functional.adaptive_avg_pool2d(x, 4))
        True
    """
    height, width = features.shape[-2:]
    if height % rows == 0 and width % cols == 0:
        return nn.functional.avg_pool2d(features, (height // rows, width // cols))
    return nn.functional.adaptive_avg_pool2d(features, (rows, cols))


def stack_camera(heightmap: Tensor, camera: Tensor) -> Tensor:
    """The heightmap [B, C, H, W] on the camera's pixel lattice [B, C', H', W'], with the camera
    stacked on as further channels: [B, C + C', H', W'].

    Both sample a lattice spanning the platform edge to edge, so bilinear interpolation with
    aligned corners puts every heightmap ray where it is on the camera's lattice (at equal
    sizes the heightmap is used as it is). The camera is never resampled: its grey levels are
    codes, which blending would mix.

    Examples:
        >>> heightmap, camera = torch.randn(2, 1, 3, 3), torch.rand(2, 1, 5, 5)
        >>> images = stack_camera(heightmap, camera)
        >>> images.shape
        torch.Size([2, 2, 5, 5])
        >>> torch.equal(images[:, :1, ::2, ::2], heightmap), torch.equal(images[:, 1:], camera)
        (True, True)
    """
    if heightmap.shape[-2:] != camera.shape[-2:]:
        heightmap = nn.functional.interpolate(
            heightmap, size=camera.shape[-2:], mode="bilinear", align_corners=True
        )
    return torch.cat([heightmap, camera.to(heightmap.dtype)], dim=-3)


class HeightmapEncoder(nn.Module):
    """Turns heightmaps into a bounded set of spatial tokens (Algorithm 2, lines 2-18).

    With ``camera_channels`` its input is the heightmap and the camera stacked by
    :func:`stack_camera`: one stem sees heights and markers at the same pixels.

    Coordinate channels -> CNN stem (conv, GroupNorm, GELU per stage) -> adaptive average pool to
    a token grid -> 1 x 1 projection to d -> LayerNorm -> 2-D sin-cos position code -> windowed
    self-attention stages -> 2 x 2 patch merge -> LayerNorm -> adaptive tokenizer.

    The token grid grows with the map (``heightmap_cells_per_token`` cells per token and side,
    rounded up to a multiple of every window and of the merge), and every weight is independent
    of the grid, so one checkpoint encodes 32 x 32 and 64 x 64 maps.

    Args:
        config: network sizes.

    Examples:
        >>> encoder = HeightmapEncoder(TerraShiftModelConfig.small())
        >>> encoder(torch.rand(2, 1, 32, 32) * 2 - 1).shape
        torch.Size([2, 4, 32])
        >>> encoder.token_grid_shape(64, 64), encoder(torch.zeros(2, 1, 64, 64)).shape
        ((8, 8), torch.Size([2, 14, 32]))
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        stem: list[nn.Module] = []
        in_channels = config.heightmap_channels + config.camera_channels + 2
        for channels, kernel, stride, groups in zip(
            config.cnn_channels,
            config.cnn_kernels,
            config.cnn_strides,
            config.cnn_groups,
            strict=True,
        ):
            stem += [
                nn.Conv2d(in_channels, channels, kernel, stride=stride, padding=kernel // 2),
                nn.GroupNorm(groups, channels),
                nn.GELU(),
            ]
            in_channels = channels
        self.stem = nn.Sequential(*stem)
        self.cells_per_token = config.heightmap_cells_per_token
        self.grid_multiple = config.token_grid_multiple
        self.projection = nn.Conv2d(in_channels, config.embed_dim, kernel_size=1)
        self.token_norm = nn.LayerNorm(config.embed_dim)
        self.stages = nn.ModuleList(
            WindowAttentionBlock(
                config.embed_dim,
                config.num_heads,
                window_size=window,
                ffn_dim=config.ffn_dim,
                dropout=config.dropout,
            )
            for window in config.swin_windows
        )
        self.merge = PatchMerging(config.embed_dim)
        self.output_norm = nn.LayerNorm(config.embed_dim)
        self.tokenizer = AdaptiveSpatialTokenizer(
            config.embed_dim,
            base_tokens=config.tokenizer_base_tokens,
            min_tokens=config.tokenizer_min_tokens,
            max_tokens=config.tokenizer_max_tokens,
            hidden_dim=config.tokenizer_hidden_dim,
        )

    def token_grid_shape(self, map_rows: int, map_cols: int) -> tuple[int, int]:
        """Pooled token grid (rows, cols) for a map of map_rows x map_cols cells."""
        unit = self.cells_per_token * self.grid_multiple
        return (
            self.grid_multiple * max(1, math.ceil(map_rows / unit)),
            self.grid_multiple * max(1, math.ceil(map_cols / unit)),
        )

    def forward(self, heightmap: Tensor) -> Tensor:
        """Encode heightmaps [B, C, H, W] into spatial tokens [B, N, d]."""
        batch, _, map_rows, map_cols = heightmap.shape
        row_coords = torch.linspace(-1.0, 1.0, map_rows, device=heightmap.device)
        col_coords = torch.linspace(-1.0, 1.0, map_cols, device=heightmap.device)
        coords = torch.stack(torch.meshgrid(row_coords, col_coords, indexing="ij"))
        features = self.stem(
            torch.cat([heightmap, coords.to(heightmap.dtype).expand(batch, -1, -1, -1)], dim=1)
        )
        rows, cols = self.token_grid_shape(map_rows, map_cols)
        pooled = average_pool(features, rows, cols)
        grid = self.token_norm(self.projection(pooled).permute(0, 2, 3, 1))
        grid = grid + sincos_grid_code(rows, cols, grid.shape[-1], device=grid.device).to(
            grid.dtype
        )
        for stage in self.stages:
            grid = stage(grid)
        tokens = self.output_norm(self.merge(grid).flatten(1, 2))
        return self.tokenizer(tokens)
