"""Draws the overhead camera beside the scene and the heightmap, at a few moments of a rollout.

    python benchmarks/plot_camera.py --out docs/figures/camera_frames.png

The pretrain scene with ``camera_resolution`` R (64 by default), one environment stepped on
the CPU with random actions (seed 0); each row is a moment: the project's renderer (the scene
and the heightmap observation) and the camera image as the agents receive it, grey levels
0 (black) to 1 (white). The PNG is saved as a 256-colour palette.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from common import save_palette_png
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from terrashift_rl.envs.render import Renderer
from terrashift_rl.sim import Simulator, TerraShiftConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--camera-resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, nargs="+", default=[0, 30, 60], help="moments")
    args = parser.parse_args()
    config = TerraShiftConfig.preset("pretrain", camera_resolution=args.camera_resolution)
    sim = Simulator(config, num_envs=1, seed=0)
    sim.reset()
    renderer = Renderer(config, width=720, height=360)
    generator = torch.Generator().manual_seed(0)
    figure = Figure(figsize=(10.8, 3.6 * len(args.steps)), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    rows = figure.subplots(len(args.steps), 2, width_ratios=[2, 1], squeeze=False)
    step = 0
    for (scene_axes, camera_axes), moment in zip(rows, sorted(args.steps), strict=True):
        while step < moment:
            sim.step(torch.rand(sim.action_shape, generator=generator) * 2 - 1)
            step += 1
        scene_axes.imshow(renderer.frame(sim))
        scene_axes.set_axis_off()
        camera_axes.imshow(
            sim.view("camera")[0, 0].numpy(),
            origin="lower",  # rows run along +y, as the heightmap's
            extent=(-0.5, 0.5, -0.5, 0.5),
            cmap="gray",
            vmin=0.0,
            vmax=1.0,
            interpolation="nearest",
        )
        camera_axes.set_title(
            f"camera observation ({config.camera_resolution}\N{MULTIPLICATION SIGN}"
            f"{config.camera_resolution})",
            fontsize=9,
        )
        camera_axes.set_xlabel("x [m]", fontsize=8)
        camera_axes.set_ylabel("y [m]", fontsize=8)
        camera_axes.tick_params(labelsize=7)
    save_palette_png(figure, args.out)


if __name__ == "__main__":
    main()
