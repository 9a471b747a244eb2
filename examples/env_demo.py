"""Rolls out random actions in a batch of TerraShift environments and reports what happened.

python examples/env_demo.py                  # CUDA if present, else CPU
python examples/env_demo.py --num-envs 4096 --steps 512
"""

from __future__ import annotations

import argparse
import time

import torch
from tqdm import tqdm

from terrashift_rl.envs import GROUP, TerraShiftEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--num-envs", type=int, default=None, help="default: 4096 GPU, 16 CPU")
    parser.add_argument("--steps", type=int, default=128, help="decisions per environment")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.device == "cpu":
        print("no CUDA device: running on the CPU with a small batch")
    num_envs = args.num_envs or (4096 if args.device.startswith("cuda") else 16)

    env = TerraShiftEnv(num_envs=num_envs, device=args.device, seed=args.seed)
    td = env.reset()
    generator = torch.Generator(device=env.device).manual_seed(args.seed)
    reward = torch.zeros(num_envs, device=env.device)
    goals = lost = 0
    start = time.perf_counter()
    for _ in tqdm(range(args.steps), desc="random policy", unit="step"):
        action = torch.rand(env.sim.action_shape, device=env.device, generator=generator) * 2 - 1
        td[GROUP, "action"] = action
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        reward += nxt[GROUP, "reward"][:, 0, 0]
        done = nxt["done"].squeeze(-1)
        goals += int(nxt["episode_goals"].squeeze(-1)[done].sum())
        lost += int(nxt["episode_out_of_bounds"].squeeze(-1)[done].sum())
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    print(
        f"{num_envs} environments x {args.steps} decisions on {env.device}: "
        f"{num_envs * args.steps / elapsed:,.0f} env-steps/s"
    )
    print(f"mean reward per decision: {reward.mean().item() / args.steps:+.4f}")
    print(f"in finished episodes: {goals} goals, {lost} spheres out of bounds")


if __name__ == "__main__":
    main()
