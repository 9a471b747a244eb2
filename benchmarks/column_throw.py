"""Moving columns: how high a rising patch of columns throws a sphere, against the step size.

A sphere rests in a hollow between four ellipsoid columns; a 3 x 3 patch of columns around the
platform's centre then rises at a given speed for one physics tick. The peak height of the throw
(above the resting height) at the default substeps is compared with the same simulator at
16x the substeps, for the hollow inside the patch (all four supporting columns rise) and one
on its edge (two rise). Up to 3.6 m/s the field is at 0 and the patch rises by speed x tick;
for faster patches the whole field starts lower and the patch ends at max_column_height.
Prints a table and writes JSON.

    python benchmarks/column_throw.py
    python benchmarks/column_throw.py --speeds 1.8 3.6 --restitution 0.05
"""

from __future__ import annotations

from pathlib import Path

import torch
from common import benchmark_parser, run_header, table_header, table_row, write_results

from terrashift_rl.sim import ScriptedScene, TerraShiftConfig

PATCH = slice(6, 9)  # columns 6-8 along both axes of the 15 x 15 grid
HOLLOWS = {"centre": (7, 7), "edge": (8, 7)}  # the hollow at the corner of columns i, i + 1
FLIGHT_TICKS = 90  # 1.5 s: past the top of the highest throw


def throw_heights(
    speeds: list[float], *, substeps: int, restitution: float
) -> dict[str, list[float]]:
    """Peak height above rest [m] for every speed, per hollow; all throws in one batch."""
    config = TerraShiftConfig(
        num_objects=1, num_goals=1, substeps=substeps, restitution=restitution
    )
    cases = [(hollow, speed) for hollow in HOLLOWS for speed in speeds]
    scene = ScriptedScene(config, num_envs=len(cases))
    g, cell, hmax = config.grid_size, config.cell_size, config.max_column_height
    start = torch.zeros(len(cases), g, g)
    end = torch.zeros(len(cases), g, g)
    positions = torch.zeros(len(cases), 1, 3)
    for env, (hollow, speed) in enumerate(cases):
        rise = speed * config.tick_dt
        start[env] = min(0.0, hmax - rise)  # the whole field, low enough for the patch to rise
        end[env] = start[env]
        end[env, PATCH, PATCH] += rise
        ix, iy = HOLLOWS[hollow]
        positions[env, 0] = torch.tensor(
            [
                (ix + 1) * cell - 0.5,
                (iy + 1) * cell - 0.5,
                config.column_rest_top + start[env, 0, 0] + config.sphere_radius + 0.002,
            ]
        )
    scene.set_column_heights(start)
    scene.step(1)
    scene.place_spheres(positions)
    scene.step(60)  # settle
    rest = scene.sphere_position[:, 0, 2]
    scene.set_column_heights(end)
    peak = rest.clone()
    for _ in range(FLIGHT_TICKS):
        scene.step(1)
        peak = torch.maximum(peak, scene.sphere_position[:, 0, 2])
    heights = (peak - rest).tolist()
    return {
        hollow: [h for (name, _), h in zip(cases, heights, strict=True) if name == hollow]
        for hollow in HOLLOWS
    }


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument(
        "--speeds", type=float, nargs="+", default=[0.6, 1.2, 1.8, 2.4, 3.6, 4.8, 6.0, 7.2]
    )
    parser.add_argument("--restitution", type=float, default=TerraShiftConfig.restitution)
    parser.add_argument("--refinement", type=int, default=16, help="substeps of the reference")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/column_throw.json"))
    args = parser.parse_args()

    substeps = TerraShiftConfig.substeps
    coarse = throw_heights(args.speeds, substeps=substeps, restitution=args.restitution)
    fine = throw_heights(
        args.speeds, substeps=args.refinement * substeps, restitution=args.restitution
    )
    rows = []
    print(
        f"restitution {args.restitution}; peak height [m] at {substeps} substeps and "
        f"{args.refinement * substeps}, error of the first"
    )
    print(
        table_header(["speed m/s", *(f"{hollow}: height, reference, error" for hollow in HOLLOWS)])
    )
    for i, speed in enumerate(args.speeds):
        row = {"column_speed": speed}
        cells = []
        for hollow in HOLLOWS:
            error = coarse[hollow][i] / fine[hollow][i] - 1.0
            row[hollow] = {
                "height": coarse[hollow][i],
                "reference": fine[hollow][i],
                "error": error,
            }
            cells.append(f"{coarse[hollow][i]:.4f}, {fine[hollow][i]:.4f}, {error:+.1%}")
        rows.append(row)
        print(table_row([f"{speed:.1f}", *cells]))
    write_results(
        args.out,
        {
            **run_header(torch.device("cpu")),
            "restitution": args.restitution,
            "substeps": substeps,
            "reference_substeps": args.refinement * substeps,
            "rows": rows,
        },
    )


if __name__ == "__main__":
    main()
