"""Draws the README's picture: the scripted heuristic sorting the pretraining scene, as a GIF.

    python benchmarks/plot_heuristic_rollout.py --out docs/figures/heuristic_pretrain.gif

One evaluation-mode episode (no respawn) of the pretraining scene of ``--seed``, played on the
CPU by :class:`~terrashift_rl.envs.baselines.ScriptedHeuristicPolicy` until every sphere is
resolved, drawn by the project's renderer every ``--every`` decisions and at the last: the
scene half of each frame, in one palette of ``--colors`` colours without dithering (which keeps
the file small), the last frame held for a second.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from common import benchmark_parser
from PIL import Image
from torchrl.envs.utils import step_mdp

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.envs.render import Renderer, save_video


def heuristic_episode(*, seed: int, every: int, size: int) -> np.ndarray:
    """Frames [T, size, size, 3] of one evaluation episode played by the scripted heuristic."""
    env = TerraShiftEnv(num_envs=1, seed=seed, respawn=False)
    policy = ScriptedHeuristicPolicy(env.config)
    renderer = Renderer(env.config, width=2 * size, height=size)
    frames = []
    with torch.no_grad():
        td = env.reset()
        for decision in range(env.config.max_episode_steps + 1):
            done = decision > 0 and bool(td["done"].any())
            if decision % every == 0 or done:
                frames.append(renderer.frame(env.sim)[:, :size])  # the left half: the scene
            if done:
                break
            td = step_mdp(env.step(policy(td)))
    return np.stack(frames)


def one_palette(frames: np.ndarray, colors: int) -> np.ndarray:
    """``frames`` in one palette of ``colors`` colours drawn from a sample of them, undithered."""
    sample = Image.fromarray(np.concatenate(frames[:: max(1, len(frames) // 8)]))
    palette = sample.quantize(colors, dither=Image.Dither.NONE)
    return np.stack(
        [
            np.asarray(
                Image.fromarray(frame)
                .quantize(palette=palette, dither=Image.Dither.NONE)
                .convert("RGB")
            )
            for frame in frames
        ]
    )


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--seed", type=int, default=0, help="the scene's seed")
    parser.add_argument("--every", type=int, default=4, help="decisions per frame")
    parser.add_argument("--size", type=int, default=280, help="frame side [pixels]")
    parser.add_argument("--colors", type=int, default=32)
    parser.add_argument("--fps", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("docs/figures/heuristic_pretrain.gif"))
    args = parser.parse_args()
    frames = one_palette(
        heuristic_episode(seed=args.seed, every=args.every, size=args.size), args.colors
    )
    held = np.concatenate([frames, np.repeat(frames[-1:], args.fps, axis=0)])
    path = save_video(held, args.out, fps=args.fps)
    print(f"wrote {path} ({len(frames)} frames, {path.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
