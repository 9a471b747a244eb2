"""Pixel probe: can a network read where the spheres are from the images it is given?

Scenes of the pretrain preset with the camera (64 x 64 by default), stepped with random
actions on the CPU; every agent's target is the offset from its wavelet to the nearest sphere
(2 values: needs the spheres' positions), from that sphere to its own goal (2 values: needs
which goal is whose, which only the camera and the object sequence tell) and that sphere's
velocity (2 values: the object sequence holds it; one frame shows it only as far as the
surface under a sphere tells where it rolls). Each network is trained supervised on the same
frames for the same number of steps, on targets scaled to unit variance, and scored on
held-out frames by R^2 (1: exact, 0: no better than the mean):

- ``pixels``: the trunk (``SharedEmbeddingNetwork``) with the heightmap and the camera and no
  object tokens, as ``mapoca_pixels`` trains it, and a linear read-out of each agent's
  embedding;
- ``objects``: the same trunk with the object sequence and no camera (the main job's inputs);
- ``heightmap``: the trunk with the heightmap alone (a floor: spheres show as bumps, goals not);
- ``cnn``: a plain CNN on the same images (three strided convolutions, flattened, an MLP with
  each agent's observation).

Each network's cost is timed too: milliseconds per env-step of a forward pass, and of a forward
and backward pass, on 256 held-out frames (median of 5). Prints a table and writes JSON after
each network.

    python benchmarks/pixel_probe.py --out benchmarks/results/pixel_probe_cpu.json
    python benchmarks/pixel_probe.py --networks pixels --camera-resolution 32 --out /tmp/p32.json
    python benchmarks/pixel_probe.py --steps 100 --envs 64 --networks pixels cnn --out /tmp/p.json
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path

import torch
from common import benchmark_parser, run_header, table_header, table_row, write_results
from omegaconf import OmegaConf
from torch import Tensor, nn

from terrashift_rl.modules import TerraShiftModelConfig
from terrashift_rl.modules.heightmap import stack_camera
from terrashift_rl.modules.trunk import SharedEmbeddingNetwork
from terrashift_rl.sim import Simulator, TerraShiftConfig

MODEL_PRESETS = Path(__file__).resolve().parents[1] / "recipes" / "configs" / "model"
NETWORKS = ("pixels", "objects", "heightmap", "cnn")
TARGETS = ("sphere dx", "sphere dy", "goal dx", "goal dy", "sphere vx", "sphere vy")


def collect_frames(
    *, envs: int, snapshots: int, every: int, camera_resolution: int, seed: int
) -> dict[str, Tensor]:
    """Observations and per-agent targets of ``envs`` scenes at ``snapshots`` moments of a
    random rollout, ``every`` decisions apart; agents of scenes with no sphere are masked."""
    config = TerraShiftConfig.preset("pretrain", camera_resolution=camera_resolution)
    sim = Simulator(config, num_envs=envs, seed=seed)
    sim.reset()
    generator = torch.Generator().manual_seed(seed)
    frames: dict[str, list[Tensor]] = {
        name: [] for name in ("heightmap", "camera", "objects", "objects_mask", "agents")
    }
    targets, valid = [], []
    for _ in range(snapshots):
        for _ in range(every):
            sim.step(torch.rand(sim.action_shape, generator=generator) * 2 - 1)
        objects, mask = sim.view("object_features").clone(), sim.view("object_mask").clone()
        agents = sim.view("agent_features").clone()
        for name, value in (
            ("heightmap", sim.view("heightmap").clone()),
            ("camera", sim.view("camera").clone()),
            ("objects", objects),
            ("objects_mask", mask),
            ("agents", agents),
        ):
            frames[name].append(value)
        offsets = objects[:, None, :, 0:2] - agents[:, :, None, 0:2]  # [N, K, M, 2]
        distance = offsets.norm(dim=-1).masked_fill(~mask[:, None, :], float("inf"))
        nearest = distance.argmin(-1)  # [N, K]
        chosen = objects.gather(1, nearest[..., None].expand(-1, -1, objects.shape[-1]))
        to_sphere = chosen[..., 0:2] - agents[..., 0:2]
        to_goal = chosen[..., 3:5] - chosen[..., 0:2]
        targets.append(torch.cat([to_sphere, to_goal, chosen[..., 6:8]], dim=-1))
        valid.append(mask.any(-1, keepdim=True).expand(-1, agents.shape[1]))
    data = {name: torch.cat(values) for name, values in frames.items()}
    data["targets"] = torch.cat(targets)
    data["valid"] = torch.cat(valid)
    return data


class TrunkProbe(nn.Module):
    """The trunk and a linear read-out of every agent's embedding."""

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.trunk = SharedEmbeddingNetwork(config)
        self.readout = nn.Linear(config.embed_dim, len(TARGETS))

    def forward(self, batch: dict[str, Tensor]) -> Tensor:
        embedding, _ = self.trunk(
            batch["heightmap"],
            batch["objects"] if self.trunk.object_encoder is not None else None,
            batch["agents"],
            objects_mask=batch["objects_mask"],
            camera=batch["camera"] if self.trunk.camera_channels else None,
        )
        return self.readout(embedding)


class PlainCNN(nn.Module):
    """Heightmap and camera stacked with coordinates, three strided convolutions, flattened;
    an MLP reads it beside each agent's observation."""

    def __init__(self, resolution: int, *, width: int = 32, hidden: int = 128) -> None:
        super().__init__()
        self.convolutions = nn.Sequential(
            nn.Conv2d(4, width // 2, 5, stride=2, padding=2),
            nn.GELU(),
            nn.Conv2d(width // 2, width, 3, stride=2, padding=1),
            nn.GELU(),
            nn.Conv2d(width, width, 3, stride=2, padding=1),
            nn.GELU(),
            nn.Flatten(),
            nn.Linear(width * (resolution // 8) ** 2, hidden),
            nn.GELU(),
        )
        self.head = nn.Sequential(
            nn.Linear(hidden + 9, hidden), nn.GELU(), nn.Linear(hidden, len(TARGETS))
        )

    def forward(self, batch: dict[str, Tensor]) -> Tensor:
        images = stack_camera(batch["heightmap"], batch["camera"])
        side = images.shape[-1]
        line = torch.linspace(-1.0, 1.0, side)
        coords = torch.stack(torch.meshgrid(line, line, indexing="ij"))
        scene = self.convolutions(torch.cat([images, coords.expand(len(images), -1, -1, -1)], 1))
        agents = batch["agents"]
        scene = scene[:, None].expand(-1, agents.shape[1], -1)
        return self.head(torch.cat([scene, agents], dim=-1))


def make_network(
    name: str, preset: str, resolution: int, *, cells_per_token: int | None = None
) -> nn.Module:
    """The network ``name`` of :data:`NETWORKS`; a trunk of the recipes' model preset."""
    if name == "cnn":
        return PlainCNN(resolution)
    base = TerraShiftModelConfig.small() if preset == "small" else TerraShiftModelConfig()
    sizes = OmegaConf.to_container(OmegaConf.load(MODEL_PRESETS / f"{preset}.yaml"))
    sizes.pop("defaults")
    if cells_per_token is not None:
        sizes["heightmap_cells_per_token"] = cells_per_token
    config = dataclasses.replace(
        base, **sizes, camera_channels=int(name == "pixels"), object_tokens=name == "objects"
    )
    return TrunkProbe(config)


def r_squared(prediction: Tensor, target: Tensor, valid: Tensor) -> list[float]:
    """R^2 of every target column over the valid agents."""
    prediction, target = prediction[valid], target[valid]
    residual = (prediction - target).pow(2).mean(0)
    variance = (target - target.mean(0)).pow(2).mean(0)
    return (1 - residual / variance).tolist()


def milliseconds_per_env_step(
    network: nn.Module, batch: dict[str, Tensor], *, repeats: int = 5
) -> tuple[float, float]:
    """Median milliseconds per env-step of a forward pass and of a forward and backward pass
    on ``batch``."""
    frames = len(batch["targets"])

    def forward_backward() -> None:
        network(batch).sum().backward()

    medians = []
    for run in (torch.no_grad()(lambda: network(batch)), forward_backward):
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        medians.append(1e3 * statistics.median(times) / frames)
    network.zero_grad()
    return medians[0], medians[1]


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--networks", nargs="+", choices=NETWORKS, default=list(NETWORKS))
    parser.add_argument("--preset", choices=("small", "medium"), default="medium")
    parser.add_argument("--camera-resolution", type=int, default=64)
    parser.add_argument(
        "--cells-per-token",
        type=int,
        default=None,
        help="model.heightmap_cells_per_token of the trunks (8, the preset's, if not given)",
    )
    parser.add_argument("--envs", type=int, default=512, help="scenes per snapshot")
    parser.add_argument("--snapshots", type=int, default=12, help="moments per scene")
    parser.add_argument("--every", type=int, default=8, help="decisions between snapshots")
    parser.add_argument("--test-fraction", type=float, default=0.15)
    parser.add_argument("--steps", type=int, default=1500, help="optimiser steps per network")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.manual_seed(args.seed)

    data = collect_frames(
        envs=args.envs,
        snapshots=args.snapshots,
        every=args.every,
        camera_resolution=args.camera_resolution,
        seed=args.seed,
    )
    frames = len(data["targets"])
    order = torch.randperm(frames)
    test_size = int(frames * args.test_fraction)
    test = {name: value[order[:test_size]] for name, value in data.items()}
    train = {name: value[order[test_size:]] for name, value in data.items()}
    payload = {
        **run_header(torch.device("cpu")),
        "settings": {k: v for k, v in vars(args).items() if k != "out"} | {"frames": frames},
        "targets": list(TARGETS),
        "networks": {},
    }
    # every target counts alike in the loss (a sphere is mostly at rest: its velocity is
    # small); a target constant over the frames (no sphere moved) keeps its own units
    scale = train["targets"][train["valid"]].std(0)
    scale = torch.where(scale > 0, scale, 1.0)
    print(table_header(["network", *TARGETS, "train loss", "s", "fwd ms", "fwd+bwd ms"]))
    for name in args.networks:
        torch.manual_seed(args.seed)
        network = make_network(
            name, args.preset, args.camera_resolution, cells_per_token=args.cells_per_token
        )
        optimiser = torch.optim.Adam(network.parameters(), lr=args.lr)
        start = time.perf_counter()
        losses = []
        for _ in range(args.steps):
            index = torch.randint(len(train["targets"]), (args.batch,))
            batch = {key: value[index] for key, value in train.items()}
            error = ((network(batch) - batch["targets"]) / scale).pow(2).mean(-1)
            loss = error[batch["valid"]].mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
        seconds = time.perf_counter() - start
        network.eval()
        with torch.no_grad():
            prediction = torch.cat(
                [
                    network({key: value[i : i + 256] for key, value in test.items()})
                    for i in range(0, test_size, 256)
                ]
            )
        scores = r_squared(prediction, test["targets"], test["valid"])
        costs = milliseconds_per_env_step(
            network, {key: value[:256] for key, value in test.items()}
        )
        final_loss = sum(losses[-50:]) / len(losses[-50:])
        payload["networks"][name] = {
            "r2": scores,
            "train_loss": final_loss,
            "seconds": seconds,
            "forward_ms_per_env_step": costs[0],
            "forward_backward_ms_per_env_step": costs[1],
        }
        cells = [name, *(f"{s:.3f}" for s in scores), f"{final_loss:.4f}", f"{seconds:.0f}"]
        cells += [f"{cost:.3f}" for cost in costs]
        print(table_row(cells))
        write_results(args.out, payload)


if __name__ == "__main__":
    main()
