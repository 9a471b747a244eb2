"""Several TerraShift scenes stepped as one batch, padded to fixed numbers of agents and
spheres."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from itertools import accumulate

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from terrashift_rl.envs.terrashift import GROUP, PRIVILEGED, TerraShiftEnv, set_specs
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.sim.types import AGENT_FEATURES, OBJECT_FEATURES

# Keys under GROUP that hold the team's value in every agent's slot; a padded agent copies it.
_TEAM_KEYS = ("done", "terminated", "truncated", "reward")


class MixedSceneEnv(EnvBase):
    """Environments of different scenes (grid size, agents, spheres) as one batched env.

    One simulator holds one scene, so each scene keeps its own :class:`TerraShiftEnv`; this env
    steps them all and concatenates their outputs along the batch, in the order of ``scenes``.
    Every scene is padded to ``num_agents`` agents and ``num_objects`` object slots: the extra
    agents are absent (``("agents", "mask")`` False, observation zeros, the team's reward and
    done flags), the extra slots empty (``objects_mask`` False, features zeros), and the actions
    of absent agents are dropped. Networks that attend over agents and objects take the padded
    batch as it is; a loss must leave absent agents out (MA-POCA's does).

    Every scene keeps the first's observations: its heightmap resolution, its camera
    (``camera_resolution``, the same R x R frame whatever the grid) and whether it observes
    the objects or hands them to critics alone (``privileged_objects``). The camera draws the
    colour pairs at grey levels spread over the scene's own number of goals
    (:func:`~terrashift_rl.sim.camera.camera_levels`), so scenes with different numbers of
    goals draw a pair at different levels.

    Args:
        scenes: the scenes, each a :class:`~terrashift_rl.sim.TerraShiftConfig`, all with the
            first's heightmap resolution, camera resolution, ``observe_objects`` and
            ``privileged_objects``.
        num_envs: environments of each scene, each >= 1.

    Keyword Args:
        num_agents: agents every scene is padded to; the scenes' most if None.
        num_objects: object slots every scene is padded to; the scenes' most if None.
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
        num_agents: int | None = None,
        num_objects: int | None = None,
        device: str | torch.device = "cpu",
        seed: int = 0,
    ) -> None:
        if not scenes:
            raise ValueError("MixedSceneEnv needs at least one scene")
        if len(scenes) != len(num_envs):
            raise ValueError(
                f"MixedSceneEnv needs one count of environments per scene, got {len(scenes)} "
                f"scene(s) and num_envs={list(num_envs)}"
            )
        if any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in num_envs):
            raise ValueError(f"num_envs must hold integers >= 1, got {list(num_envs)}")
        self.num_agents = max(s.num_agents for s in scenes) if num_agents is None else num_agents
        self.num_objects = (
            max(s.num_objects for s in scenes) if num_objects is None else num_objects
        )
        self.heightmap_resolution = scenes[0].heightmap_resolution
        self.camera_resolution = scenes[0].camera_resolution
        self.observe_objects = scenes[0].observe_objects
        self.privileged_objects = scenes[0].privileged_objects
        for scene in scenes:
            if (
                scene.num_agents > self.num_agents
                or scene.num_objects > self.num_objects
                or scene.heightmap_resolution != self.heightmap_resolution
            ):
                raise ValueError(
                    f"a scene of {scene.num_agents} agents, {scene.num_objects} spheres and a "
                    f"{scene.heightmap_resolution}-ray heightmap does not fit this env's "
                    f"{self.num_agents} agents, {self.num_objects} object slots and "
                    f"{self.heightmap_resolution}-ray heightmap"
                )
            names = ("camera_resolution", "observe_objects", "privileged_objects")
            if any(getattr(scene, name) != getattr(self, name) for name in names):
                raise ValueError(
                    f"a scene with {_settings(scene, names)} does not observe as this env, "
                    f"{_settings(self, names)}: every scene needs the same"
                )
        super().__init__(device=device, batch_size=torch.Size([sum(num_envs)]))
        self.envs = [
            TerraShiftEnv(scene, num_envs=n, device=self.device, seed=seed + i)
            for i, (scene, n) in enumerate(zip(scenes, num_envs, strict=True))
        ]
        self.scenes = list(scenes)
        self._rows = [
            slice(end - n, end) for n, end in zip(num_envs, accumulate(num_envs), strict=True)
        ]
        set_specs(
            self,
            num_agents=self.num_agents,
            num_objects=self.num_objects,
            heightmap_resolution=self.heightmap_resolution,
            observe_objects=self.observe_objects,
            privileged_objects=self.privileged_objects,
            camera_resolution=self.camera_resolution,
        )

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
    def check_actions(self) -> None:
        """:meth:`TerraShiftEnv.check_actions` in every scene."""
        for env in self.envs:
            env.check_actions()

    def stagger_episodes(self) -> None:
        """:meth:`TerraShiftEnv.stagger_episodes` in every scene."""
        for env in self.envs:
            env.stagger_episodes()

    def simulator_state(self) -> dict[str, dict[str, torch.Tensor]]:
        """The simulator state of every scene (on the CPU), by its index in ``scenes``."""
        return {
            str(i): {name: value.cpu() for name, value in env.sim.state_dict().items()}
            for i, env in enumerate(self.envs)
        }

    def load_simulator_state(self, state: dict[str, dict[str, torch.Tensor]]) -> None:
        """Restores a :meth:`simulator_state` of an env with the same scenes and counts."""
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
        extra_agents = self.num_agents - k
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
        # the object sequence, observed or privileged, or neither
        root = () if self.observe_objects else (PRIVILEGED,)
        objects = out.get((*root, "objects"), None)
        extra_objects = 0 if objects is None else self.num_objects - objects.shape[1]
        if extra_objects:
            mask = out.get((*root, "objects_mask"))
            padding = objects.new_zeros(n, extra_objects, OBJECT_FEATURES)
            out.set((*root, "objects"), torch.cat([objects, padding], 1))
            out.set((*root, "objects_mask"), torch.cat([mask, mask.new_zeros(n, extra_objects)], 1))
        return out


def _settings(owner: object, names: tuple[str, ...]) -> str:
    """``name=value`` of each of ``names`` on ``owner``, joined by commas."""
    return ", ".join(f"{name}={getattr(owner, name)}" for name in names)
