"""TerraShift as a batched TorchRL environment with the multi-agent group ``"agents"``."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from terrashift_rl.sim import Simulator, TerraShiftConfig
from terrashift_rl.sim.types import ACTION_DIM, AGENT_FEATURES, OBJECT_FEATURES

GROUP = "agents"
"""Name of the agent group in every nested key."""
PRIVILEGED = "privileged"
"""Root of the keys that no policy reads: the object sequence for critics
(``TerraShiftConfig.privileged_objects``)."""
EVENT_KEYS = ("episode_goals", "episode_out_of_bounds")
"""Per-environment event counts since the last reset, shape [num_envs, 1]."""


class TerraShiftEnv(EnvBase):
    """K wavelet agents shape a column grid to roll spheres onto colour-matched goals.

    Every environment of the batch steps at once in Warp kernels (a CUDA graph on GPU).
    Keys follow TorchRL's multi-agent conventions, so its MAPPO/IPPO losses work unchanged:

    ==================================  ===================  =======================================
    key                                 shape                meaning
    ==================================  ===================  =======================================
    ``("agents", "observation")``       [N, K, 9]            wavelet parameters in [-1, 1]
    ``("agents", "mask")``              [N, K] bool          agent present (always True here)
    ``"heightmap"``                     [N, 1, R, R]         ray heights in [-1, 1], rows along +y
    ``"objects"``                       [N, M, 9]            sphere and goal positions, velocity
    ``"objects_mask"``                  [N, M] bool          True where the slot holds a sphere
    ``"camera"``                        [N, 1, C, C]         overhead greyscale image in [0, 1]
    ``("privileged", "objects")``       [N, M, 9]            ``"objects"``, for critics alone
    ``("privileged", "objects_mask")``  [N, M] bool          ``"objects_mask"``, for critics alone
    ``"episode_goals"``                 [N, 1] int64         goals reached since the reset
    ``"episode_out_of_bounds"``         [N, 1] int64         spheres lost since the reset
    ``"episode_surface_work"``          [N, 1]               the surface's work on the spheres [J]
    ``("agents", "action")``            [N, K, 6]            deltas or targets in [-1, 1] (clipped)
    ``("agents", "reward")``            [N, K, 1]            the team reward, same for every agent
    ``done/terminated/truncated``       [N, 1], [N, K, 1]    at the root and under ``"agents"``
    ==================================  ===================  =======================================

    ``"camera"`` is there only with ``camera_resolution`` C > 0 (``sim/camera.py`` gives its
    grey levels); ``"objects"`` and ``"objects_mask"`` only with ``observe_objects`` (without
    them no observation but the two images tells where a sphere or a goal is). With
    ``privileged_objects`` (and without ``observe_objects``) the same two tensors come under
    ``"privileged"`` instead: what critics may read in training, and a policy never.

    ``truncated`` marks the step limit; ``terminated`` is only raised where nothing respawns
    (evaluation mode, ``respawn=False``, or the environments that ``respawn_fraction`` leaves
    out) once every sphere is resolved.

    Actions of the wrong shape, dtype or device raise ``ValueError`` naming
    ``("agents", "action")`` before anything is simulated; finite values outside [-1, 1] are
    clipped. Whether an action holds NaN or infinity is only known on the device, and asking at
    every step would stop the host until the device has caught up (a synchronisation per step).
    So a step simulates non-finite values as 0 and counts the step on the device;
    :meth:`check_actions` (once per training iteration) then raises the ``ValueError``, naming
    the key and how many steps since the last check held such values. With
    ``check_every_step=True`` (for debugging) every step checks at once and raises before
    anything is simulated.

    Args:
        config: scene parameters; the pretraining scene if None.
        num_envs: number of environments in the batch.
        device: ``"cpu"`` or a CUDA device.
        seed: seed of the simulator's random streams; drawn from torch's generator if None.
        check_every_step: check every step's action for NaN and infinity before simulating it
            (a host synchronisation per step) instead of at :meth:`check_actions`.
        **overrides: config fields to replace, e.g. ``grid_size=30``.

    Example:
        >>> env = TerraShiftEnv(num_envs=4, seed=0, column_shape="box")
        >>> td = env.rollout(3)
        >>> td["next", "agents", "reward"].shape
        torch.Size([4, 3, 8, 1])
        >>> td["heightmap"].shape
        torch.Size([4, 3, 1, 32, 32])
    """

    batch_locked = True

    def __init__(
        self,
        config: TerraShiftConfig | None = None,
        *,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        check_every_step: bool = False,
        **overrides: Any,
    ):
        config = config if config is not None else TerraShiftConfig()
        if overrides:
            config = config.replace(**overrides)
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.sim = Simulator(config, num_envs=num_envs, device=device, seed=seed)
        super().__init__(device=self.sim.torch_device, batch_size=torch.Size([num_envs]))
        self.config = config
        self.check_every_step = check_every_step
        # steps whose action held NaN or infinity, and steps taken, since the last check
        self._non_finite_steps = torch.zeros((), dtype=torch.int64, device=self.device)
        self._steps_since_check = 0
        set_specs(
            self,
            num_agents=config.num_agents,
            num_objects=config.num_objects,
            heightmap_resolution=config.heightmap_resolution,
            observe_objects=config.observe_objects,
            privileged_objects=config.privileged_objects,
            camera_resolution=config.camera_resolution,
        )

    # --- EnvBase API ----------------------------------------------------------------------
    @property
    def num_envs(self) -> int:
        return self.sim.num_envs

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.sim.seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        self.sim.reset(self._reset_mask(tensordict))
        return self._output(with_reward=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self._checked_action(tensordict)
        finite = action.isfinite()
        self._non_finite_steps += ~finite.all()
        self._steps_since_check += 1
        # a non-finite value must not reach the simulator's state before a check sees it
        self.sim.step(torch.where(finite, action, 0.0))
        return self._output(with_reward=True)

    # --- training helpers -----------------------------------------------------------------
    def check_actions(self) -> None:
        """Raises ``ValueError`` if an action since the last call held NaN or infinity (those
        values were simulated as 0), saying in how many of the steps; one host synchronisation.
        Each call starts a new count."""
        non_finite, steps = int(self._non_finite_steps), self._steps_since_check
        self._non_finite_steps.zero_()
        self._steps_since_check = 0
        if non_finite:
            raise ValueError(
                f"{(GROUP, 'action')} held NaN or infinite values in {non_finite} of the {steps} "
                "steps since the last check (simulated as 0 there); look for non-finite "
                "parameters or inputs of the policy"
            )

    def stagger_episodes(self) -> None:
        """Sets each environment's decision counter to a uniform random value in
        [0, ``max_episode_steps``), drawn from torch's generator.

        Called once after the first reset of a training run, it spreads the step limits of
        environments that started together over a whole episode's length: without it every
        environment truncates and resets at the same decision, and every batch right after
        holds only early-episode states. Only the current episodes are shortened.
        """
        counts = self.sim.view("step_count")
        offsets = torch.randint(self.config.max_episode_steps, counts.shape, device=self.device)
        counts.copy_(offsets.to(counts.dtype))

    # --- helpers --------------------------------------------------------------------------
    def _reset_mask(self, tensordict: TensorDictBase | None) -> torch.Tensor | None:
        if tensordict is None:
            return None
        mask = tensordict.get("_reset", None)
        if mask is not None:
            return mask.reshape(self.num_envs).to(torch.bool)
        mask = tensordict.get((GROUP, "_reset"), None)
        if mask is not None:
            return mask.reshape(self.num_envs, -1).any(-1)
        return None

    def _checked_action(self, tensordict: TensorDictBase) -> torch.Tensor:
        key = (GROUP, "action")
        action = tensordict.get(key, None)
        expected = self.sim.action_shape
        if action is None:
            raise ValueError(f"the input tensordict has no {key} entry")
        if tuple(action.shape) != expected:
            raise ValueError(f"{key} must have shape {expected}, got {tuple(action.shape)}")
        if action.dtype != torch.float32:
            raise ValueError(f"{key} must be float32, got {action.dtype}")
        if action.device != self.device:
            raise ValueError(f"{key} must be on {self.device}, got {action.device}")
        if self.check_every_step and not action.isfinite().all():
            raise ValueError(f"{key} holds NaN or infinite values")
        return action

    def _output(self, *, with_reward: bool) -> TensorDictBase:
        sim, n, k = self.sim, self.num_envs, self.config.num_agents
        terminated = sim.view("terminated").unsqueeze(-1).clone()
        truncated = sim.view("truncated").unsqueeze(-1).clone()
        done = terminated | truncated
        agents = {
            "observation": sim.view("agent_features").clone(),
            "mask": torch.ones(n, k, dtype=torch.bool, device=self.device),
            "done": done.unsqueeze(-1).expand(n, k, 1).clone(),
            "terminated": terminated.unsqueeze(-1).expand(n, k, 1).clone(),
            "truncated": truncated.unsqueeze(-1).expand(n, k, 1).clone(),
        }
        if with_reward:
            agents["reward"] = sim.view("reward").reshape(n, 1, 1).expand(n, k, 1).clone()
        out = {
            GROUP: TensorDict(agents, batch_size=(n, k), device=self.device),
            "heightmap": sim.view("heightmap").clone(),
            "done": done,
            "terminated": terminated,
            "truncated": truncated,
        }
        if self.config.observe_objects or self.config.privileged_objects:
            objects = {
                "objects": sim.view("object_features").clone(),
                "objects_mask": sim.view("object_mask").clone(),
            }
            if self.config.observe_objects:
                out.update(objects)
            else:
                out[PRIVILEGED] = TensorDict(objects, batch_size=(n,), device=self.device)
        if self.config.camera_resolution:
            out["camera"] = sim.view("camera").clone()
        for key in EVENT_KEYS:
            out[key] = sim.view(key).to(torch.int64).unsqueeze(-1)
        # counted with config.count_surface_work, else 0
        out["episode_surface_work"] = sim.view("surface_work").sum(-1, keepdim=True)
        return TensorDict(out, batch_size=(n,), device=self.device)


def set_specs(
    env: EnvBase,
    *,
    num_agents: int,
    num_objects: int,
    heightmap_resolution: int,
    observe_objects: bool = True,
    privileged_objects: bool = False,
    camera_resolution: int = 0,
) -> None:
    """Gives ``env`` (batch ``[N]``) the specs of the table in :class:`TerraShiftEnv`'s
    docstring for ``num_agents`` agents, ``num_objects`` object slots and a heightmap of
    ``heightmap_resolution`` rays per side; the object sequence only if ``observe_objects``
    (under ``"privileged"`` if ``privileged_objects`` instead), and a
    ``camera_resolution``-pixel camera if it is not 0."""
    dev, n = env.device, env.batch_size[0]
    k, m, r = num_agents, num_objects, heightmap_resolution

    def flag(*shape):
        return Categorical(2, shape=torch.Size(shape), dtype=torch.bool, device=dev)

    def unit_box(*shape):
        return Bounded(-1.0, 1.0, shape=torch.Size(shape), dtype=torch.float32, device=dev)

    observations = {
        GROUP: Composite(observation=unit_box(n, k, AGENT_FEATURES), mask=flag(n, k), shape=(n, k)),
        "heightmap": unit_box(n, 1, r, r),
        **{key: Unbounded(shape=(n, 1), dtype=torch.int64, device=dev) for key in EVENT_KEYS},
        "episode_surface_work": Unbounded(shape=(n, 1), device=dev),
    }
    objects = {"objects": unit_box(n, m, OBJECT_FEATURES), "objects_mask": flag(n, m)}
    if observe_objects:
        observations.update(objects)
    elif privileged_objects:
        observations[PRIVILEGED] = Composite(objects, shape=(n,))
    if camera_resolution:
        c = camera_resolution
        observations["camera"] = Bounded(
            0.0, 1.0, shape=(n, 1, c, c), dtype=torch.float32, device=dev
        )
    env.observation_spec = Composite(observations, shape=(n,))
    env.action_spec = Composite(
        {GROUP: Composite(action=unit_box(n, k, ACTION_DIM), shape=(n, k))}, shape=(n,)
    )
    env.reward_spec = Composite(
        {GROUP: Composite(reward=Unbounded(shape=(n, k, 1), device=dev), shape=(n, k))},
        shape=(n,),
    )
    flags = ("done", "terminated", "truncated")
    env.done_spec = Composite(
        {
            **{key: flag(n, 1) for key in flags},
            GROUP: Composite({key: flag(n, k, 1) for key in flags}, shape=(n, k)),
        },
        shape=(n,),
    )
