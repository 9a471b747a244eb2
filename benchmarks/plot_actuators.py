"""Draws what each actuator family does to the surface and the spheres, seen from above.

    python benchmarks/plot_actuators.py --out docs/figures/actuator_surfaces.png

One panel per family (``terrashift_rl.sim.ACTUATORS``, by name), each the same pretraining scene of
``--seed`` (``--column-shape`` columns, evaluation mode: no respawn) played on the CPU by
:class:`~terrashift_rl.envs.baselines.ScriptedHeuristicPolicy` for ``--decisions`` decisions:
the column heights [m] of a family that moves the columns, the in-plane surface velocity
[m/s] (its speed in colour, its direction as arrows) of one that slides them; the spheres
where they are (discs), the paths they took (lines) and their goals (rings), in the goals'
colours; the patches' centres (crosses). The simulation is deterministic, so the script is
all the figure is redrawn from. The PNG is saved as a palette of ``--colors`` colours.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from common import benchmark_parser, save_palette_png
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from torchrl.envs.utils import step_mdp

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.envs.render import GOAL_COLORS
from terrashift_rl.sim import ACTUATORS, COLUMN_SHAPES, Simulator

LIGHT_GREYS = ListedColormap(colormaps["Greys"](np.linspace(0.0, 0.55, 256)))
"""Surface speed: light enough for the arrows and the spheres to stand out on it."""


def heuristic_paths(env: TerraShiftEnv, decisions: int) -> np.ndarray:
    """Sphere centres (x, y) [m] at the start and after each of ``decisions`` decisions of the
    scripted heuristic, NaN where a sphere is out of play: [decisions + 1, M, 2]."""
    policy = ScriptedHeuristicPolicy(env.config)
    sim = env.sim
    paths = []
    with torch.no_grad():
        td = env.reset()
        for decision in range(decisions + 1):
            xy = sim.view("sphere_position")[0, :, :2].numpy().copy()
            xy[sim.view("sphere_active")[0].numpy() == 0] = np.nan
            paths.append(xy)
            if decision == decisions:
                break
            td = step_mdp(env.step(policy(td)))
    return np.stack(paths)


def draw_surface(axes: Axes, sim: Simulator, paths: np.ndarray) -> None:
    """One family's panel: its surface field, the spheres' paths and goals, the patches."""
    cfg = sim.config
    half = 0.5 * cfg.platform_size
    # column i's centre [m], as the simulator places it
    centres = (np.arange(cfg.grid_size) - 0.5 * (cfg.grid_size - 1)) * cfg.cell_size
    extent = (-half, half, -half, half)
    if sim.actuator.moves_surface:
        velocity = sim.view("surface_velocity")[0].numpy()  # [G(y), G(x), 2]
        speed = np.linalg.norm(velocity, axis=-1)
        image = axes.imshow(speed, origin="lower", extent=extent, cmap=LIGHT_GREYS, vmin=0.0,
                            vmax=cfg.max_surface_speed)  # fmt: skip
        axes.quiver(centres, centres, velocity[..., 0], velocity[..., 1], color="black",
                    scale=8 * cfg.max_surface_speed, width=0.005)  # fmt: skip
        label = "surface speed [m/s]"
    else:
        height = sim.view("column_height")[0].numpy()  # [G(y), G(x)]
        limit = cfg.max_amplitude
        image = axes.imshow(height, origin="lower", extent=extent, cmap="RdBu_r", vmin=-limit,
                            vmax=limit)  # fmt: skip
        label = "column height [m]"
    axes.figure.colorbar(image, ax=axes, shrink=0.8, label=label)
    goal_cell = sim.view("goal_cell")[0].numpy()
    for goal, (ix, iy) in enumerate(goal_cell):
        colour = GOAL_COLORS[goal % len(GOAL_COLORS)]
        axes.add_patch(Circle((centres[ix], centres[iy]), cfg.goal_radius, fill=False,
                              edgecolor=colour, linewidth=2))  # fmt: skip
    for sphere in range(paths.shape[1]):
        colour = GOAL_COLORS[(sphere % cfg.num_goals) % len(GOAL_COLORS)]
        axes.plot(paths[:, sphere, 0], paths[:, sphere, 1], color=colour, linewidth=1.2)
        if not np.isnan(paths[-1, sphere, 0]):
            axes.add_patch(Circle(paths[-1, sphere], cfg.sphere_radius, facecolor=colour,
                                  edgecolor="black", linewidth=0.8))  # fmt: skip
    patches = (sim.view("agent_position")[0].numpy() - 0.5 * (cfg.grid_size - 1)) * cfg.cell_size
    axes.plot(patches[:, 0], patches[:, 1], "x", color="black", markersize=6)
    axes.set_xlim(-half, half)
    axes.set_ylim(-half, half)
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--seed", type=int, default=0, help="the scene's seed")
    parser.add_argument("--decisions", type=int, default=40, help="decisions played")
    parser.add_argument("--column-shape", default="box", choices=COLUMN_SHAPES)
    parser.add_argument("--colors", type=int, default=256)
    parser.add_argument("--out", type=Path, default=Path("docs/figures/actuator_surfaces.png"))
    args = parser.parse_args()
    figure = Figure(figsize=(4.2 * len(ACTUATORS), 3.8), dpi=90, layout="constrained")
    FigureCanvasAgg(figure)
    for axes, family in zip(figure.subplots(1, len(ACTUATORS)), sorted(ACTUATORS), strict=True):
        env = TerraShiftEnv(num_envs=1, seed=args.seed, respawn=False, actuator=family,
                            column_shape=args.column_shape)  # fmt: skip
        paths = heuristic_paths(env, args.decisions)
        draw_surface(axes, env.sim, paths)
        goals = int(env.sim.view("episode_goals")[0])
        lost = int(env.sim.view("episode_out_of_bounds")[0])
        axes.set_title(f"{family}: {goals} at their goals, {lost} lost")
    figure.suptitle(
        f"The scripted heuristic after {args.decisions} decisions ({args.column_shape} columns, "
        f"seed {args.seed}); spheres and the paths they took, their goals (rings), the patches "
        "(\N{MULTIPLICATION SIGN})",
        fontsize=10,
    )
    save_palette_png(figure, args.out, args.colors)


if __name__ == "__main__":
    main()
