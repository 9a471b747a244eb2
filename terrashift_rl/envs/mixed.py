"""Several TerraShift scenes stepped as one batch, padded to the largest scene's agents and
spheres."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from itertools import accumulate

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from terrashift_rl.envs.terrashift import GROUP, TerraShiftEnv
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.sim.types import AGENT_FEATURES, OBJECT_FEATURES

# Keys under GROUP that hold the team's value in every agent's slot; a padded agent copies it.
_TEAM_KEYS = ("done", "terminated", "truncated", "reward")


class MixedSceneEnv(EnvBase):
    """Environments of different scenes (grid size, agents, spheres) as one batched env.

    One simulator holds one scene, so each scene keeps its own :class:`TerraShiftEnv`; this env
    steps them all and concatenates their outputs along the batch, in the order of ``scenes``.
    A scene with fewer agents or spheres than the largest is padded: the extra agents are
    absent (``("agents", "mask")`` False, observation zeros, the team's reward and done flags),
    the extra object slots empty (``objects_mask`` False, features zeros), and the actions
    of absent agents are dropped. Networks that attend over agents and objects take the
    padded batch as it is; a loss must leave absent agents out (MA-POCA's does).

    Every scene must have the same heightmap resolution, and one scene must hold both the most
    agents and the most spheres (the specs are that scene's over every environment).

    Args:
        scenes: the scenes, each a :class:`~terrashift_rl.sim.TerraShiftConfig`.
        num_envs: environments of each scene, each >= 1.
        device: where to simulate.
        seed: scene ``i``'s simulator is seeded with ``seed + i``.

    Example:
        >>> small = TerraShiftConfig(num_agents=2, num_objects=1, num_goals=1, column_shape="box")
        >>> env = MixedSceneEnv([small, small.replace(grid_size=20, num_agents=3)], [2, 1], seed=0)
        >>> td = env.rollout(2)
        >>> td["agents", "mask"][:, 0].tolist()
        [[True, True, False], [True, True, False], [True, True, True]]
    """

    batch_locked = True

    def __init__(
        self,
        scenes: Sequence[TerraShiftConfig],
        num_envs: Sequence[int],
        *,
        device: str | torch.device = "cpu",
        seed: int = 0,
    ) -> None:
        if not scenes or len(scenes) != len(num_envs):
            raise ValueError(
                f"MixedSceneEnv needs one count of environments per scene, got {len(scenes)} "
                f"scene(s) and num_envs={list(num_envs)}"
            )
        if any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in num_envs):
            raise ValueError(f"num_envs must hold integers >= 1, got {list(num_envs)}")
        resolutions = {scene.heightmap_resolution for scene in scenes}
        if len(resolutions) != 1:
            raise ValueError(
                f"every scene needs the same heightmap_resolution, got {sorted(resolutions)}"
            )
        largest = max(range(len(scenes)), key=lambda i: scenes[i].num_agents)
        self.num_agents = scenes[largest].num_agents
        self.num_objects = max(scene.num_objects for scene in scenes)
        if scenes[largest].num_objects != self.num_objects:
            raise ValueError(
                "one scene must hold both the most agents and the most spheres, got "
                f"(num_agents, num_objects) = {[(s.num_agents, s.num_objects) for s in scenes]}"
            )
        self.envs = [
            TerraShiftEnv(scene, num_envs=n, device=device, seed=seed + i)
            for i, (scene, n) in enumerate(zip(scenes, num_envs, strict=True))
        ]
        self.scenes = list(scenes)
        self.counts = list(num_envs)
        total = sum(num_envs)
        self._rows = [
            slice(end - n, end) for n, end in zip(num_envs, accumulate(num_envs), strict=True)
        ]
        super().__init__(device=self.envs[0].device, batch_size=torch.Size([total]))
        template = self.envs[largest]
        self.observation_spec = template.observation_spec[0].expand(total)
        self.action_spec = template.action_spec[0].expand(total)
        self.reward_spec = template.reward_spec[0].expand(total)
        self.done_spec = template.done_spec[0].expand(total)

    # --- EnvBase API ----------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            for i, env in enumerate(self.envs):
                env.set_seed(seed + i)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        parts = self._split(tensordict) if tensordict is not None else [None] * len(self.envs)
        return self._join(env._reset(part) for env, part in zip(self.envs, parts, strict=True))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get((GROUP, "action"))
        outputs = []
        for env, rows in zip(self.envs, self._rows, strict=True):
            own = action[rows, : env.config.num_agents]
            part = TensorDict({GROUP: {"action": own}}, batch_size=own.shape[:1])
            outputs.append(env._step(part))
        return self._join(outputs)

    # --- training helpers -----------------------------------------------------------------
    def stagger_episodes(self) -> None:
        """:meth:`TerraShiftEnv.stagger_episodes` in every scene."""
        for env in self.envs:
            env.stagger_episodes()

    def state_dict(self) -> dict[str, dict[str, torch.Tensor]]:
        """The simulator state of every scene, by its index in ``scenes``."""
        return {str(i): env.sim.state_dict() for i, env in enumerate(self.envs)}

    def load_state_dict(self, state: dict[str, dict[str, torch.Tensor]]) -> None:
        """Restores a :meth:`state_dict` of an env built with the same scenes and counts."""
        if sorted(state) != sorted(str(i) for i in range(len(self.envs))):
            raise ValueError(
                f"the saved state holds scenes {sorted(state)}, this env {len(self.envs)}"
            )
        for i, env in enumerate(self.envs):
            env.sim.load_state_dict(
                {name: value.to(self.device) for name, value in state[str(i)].items()}
            )

    # --- helpers --------------------------------------------------------------------------
    def _split(self, tensordict: TensorDictBase) -> list[TensorDictBase]:
        """The rows of each scene, with the agent dim cut to the scene's agents."""
        parts = []
        for env, rows in zip(self.envs, self._rows, strict=True):
            part = tensordict[rows]
            agents = part.get(GROUP, None)
            if agents is not None:
                part = part.exclude(GROUP).set(GROUP, agents[:, : env.config.num_agents])
            parts.append(part)
        return parts

    def _join(self, outputs: Iterable[TensorDictBase]) -> TensorDictBase:
        return torch.cat([self._pad(out) for out in outputs], dim=0)

    def _pad(self, out: TensorDictBase) -> TensorDictBase:
        n, k = out[GROUP].batch_size
        m = out.get("objects").shape[1]
        extra_agents, extra_objects = self.num_agents - k, self.num_objects - m
        if extra_agents:
            agents = out.get(GROUP)
            padded = {
                "observation": agents.get("observation").new_zeros(n, extra_agents, AGENT_FEATURES),
                "mask": agents.get("mask").new_zeros(n, extra_agents),
            }
            for key in _TEAM_KEYS:
                team = agents.get(key, None)
                if team is not None:
                    padded[key] = team[:, :1].expand(n, extra_agents, *team.shape[2:])
            extra = TensorDict(padded, batch_size=(n, extra_agents), device=out.device)
            out.set(GROUP, torch.cat([agents, extra], dim=1))
        if extra_objects:
            objects, mask = out.get("objects"), out.get("objects_mask")
            out.set(
                "objects",
                torch.cat([objects, objects.new_zeros(n, extra_objects, OBJECT_FEATURES)], 1),
            )
            out.set("objects_mask", torch.cat([mask, mask.new_zeros(n, extra_objects)], 1))
        return out
