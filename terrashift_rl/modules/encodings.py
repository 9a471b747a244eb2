"""Fixed sinusoidal codes for slot indices, agent indices and token-grid positions."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["sincos_code", "sincos_grid_code"]

# Token centres are placed on [0, GRID_CODE_EXTENT] whatever the grid size, so a token covering
# a given patch of the platform gets the same code on a 4 x 4 and an 8 x 8 grid. With the
# geometric frequencies below (fastest: 1 rad per unit) this extent still separates neighbouring
# tokens by half a radian on grids up to 32 tokens a side.
GRID_CODE_EXTENT = 16.0


def sincos_code(
    positions: Tensor, dim: int, *, base: float = 10_000.0, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Transformer sinusoidal code of (possibly fractional) positions.

    Args:
        positions: positions of any shape [...].
        dim: code width; even. The first half holds sines, the second cosines, at the
            frequencies ``base ** (-k / (dim / 2))`` for k = 0 .. dim/2 - 1.
        base: ratio between the fastest and the slowest frequency.
        dtype: dtype of the code.

    Returns:
        The code, shape [..., dim].

    Examples:
        >>> code = sincos_code(torch.arange(4), 8)
        >>> code.shape
        torch.Size([4, 8])
        >>> code[0]
        tensor([0., 0., 0., 0., 1., 1., 1., 1.])
    """
    half = dim // 2
    frequencies = base ** (-torch.arange(half, device=positions.device, dtype=dtype) / half)
    angles = positions.to(dtype).unsqueeze(-1) * frequencies
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


def sincos_grid_code(
    rows: int,
    cols: int,
    dim: int,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """2-D sinusoidal code of the token centres of a rows x cols grid.

    Half of the width codes the row coordinate, half the column coordinate. Coordinates are the
    token centres scaled to a fixed extent, so the code depends on where a token lies on the
    heightmap, not on how many tokens the grid has.

    Args:
        rows: grid rows.
        cols: grid columns.
        dim: code width; a multiple of 4.
        device: device of the code.
        dtype: dtype of the code.

    Returns:
        The code, shape [rows, cols, dim].

    Examples:
        >>> sincos_grid_code(2, 3, 8).shape
        torch.Size([2, 3, 8])
    """
    row_centres = (torch.arange(rows, device=device, dtype=dtype) + 0.5) * (GRID_CODE_EXTENT / rows)
    col_centres = (torch.arange(cols, device=device, dtype=dtype) + 0.5) * (GRID_CODE_EXTENT / cols)
    row_code = sincos_code(row_centres, dim // 2, dtype=dtype)
    col_code = sincos_code(col_centres, dim // 2, dtype=dtype)
    return torch.cat(
        [row_code[:, None, :].expand(rows, cols, -1), col_code[None, :, :].expand(rows, cols, -1)],
        dim=-1,
    )
