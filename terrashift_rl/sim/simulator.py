"""Host side of the simulator: allocation, seeding, and the launch order of a step and a reset.

On a CUDA device the whole step and the whole reset are captured once as CUDA graphs and
replayed, on a stream ordered after PyTorch's current stream: no host synchronisation happens
inside either. On the CPU the same kernels run eagerly.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
import warp as wp

from terrashift_rl.sim import camera, events, observations, physics
from terrashift_rl.sim.actuators import actuator_for
from terrashift_rl.sim.config import TerraShiftConfig
from terrashift_rl.sim.types import ACTION_DIM, Data, build_model

wp.set_module_options({"enable_backward": False})  # nothing differentiates through it

_INT32_MAX = 2**31 - 1
_RENAMED_ARRAYS = {"env_mask": "reset_mask"}
"""Earlier name -> name of the data arrays renamed since checkpoints were first written."""
_ADDED_ARRAYS = {
    "approach_gap": -1.0,
    "sphere_approach_gap": -1.0,
    "surface_work": 0.0,
    "camera": 0.0,
}
"""Data arrays added since checkpoints were first written -> the value they load as from a
checkpoint that lacks them."""


@wp.kernel
def _seed_streams(seed: int, rng: wp.array(dtype=wp.uint32)):
    e = wp.tid()
    rng[e] = wp.rand_init(seed, e)


class Simulator:
    """A batch of TerraShift scenes stepped together.

    Args:
        config: scene parameters (``TerraShiftConfig()``, the pretraining scene, if None).
        num_envs: number of environments.
        device: ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (a ``torch.device`` works too).
        seed: seed of the per-environment random streams.
        cuda_graph: on CUDA, replay the step and reset as captured graphs (False launches
            every kernel eagerly, for debugging).
        fuse_substeps: advance the spheres through a tick's substeps in one launch, a thread
            per environment (True), or launch each substep, a thread per sphere (False); both
            compute the same. None fuses on the CPU only: on a GPU a launch per substep was
            the faster at every number of environments measured (docs/benchmarks.md).

    Example:
        >>> import torch
        >>> sim = Simulator(num_envs=2, seed=0)
        >>> sim.reset()
        >>> sim.step(torch.zeros(2, 8, 6))
        >>> sim.view("heightmap").shape, sim.view("reward").shape
        (torch.Size([2, 1, 32, 32]), torch.Size([2]))
    """

    def __init__(
        self,
        config: TerraShiftConfig | None = None,
        *,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int = 0,
        cuda_graph: bool = True,
        fuse_substeps: bool | None = None,
    ):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.config = config if config is not None else TerraShiftConfig()
        self.config.validate()
        self.num_envs = num_envs
        self.torch_device = torch.device(device)
        if self.torch_device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {device!r} requested but CUDA is not available")
        if self.torch_device.type == "cuda" and self.torch_device.index is None:
            self.torch_device = torch.device("cuda", torch.cuda.current_device())
        self.device = wp.get_device(str(self.torch_device))
        if fuse_substeps is None:  # the faster of the two on each (docs/benchmarks.md)
            fuse_substeps = self.device.is_cpu
        self.fuse_substeps = fuse_substeps
        """Whether a tick's substeps run as one launch (see the argument)."""
        self.actuator = actuator_for(self.config)
        """The actuator family (``config.actuator``)."""
        self.model = build_model(self.config)
        self.actuator.configure(self.model, self.config)
        self.data = Data(
            self.config,
            num_envs=num_envs,
            device=self.device,
            surface_flow=self.actuator.moves_surface,
        )
        self.actuator.allocate(self.data, self.config, self.device)
        substep, tick_substeps = physics.sphere_kernels(
            self.actuator.moves_surface, self.config.count_surface_work
        )
        self._sphere_kernel = tick_substeps if fuse_substeps else substep
        self._views: dict[str, torch.Tensor] = {}
        self._torch_stream = None
        self._stream = None
        if self.device.is_cuda:
            self._torch_stream = torch.cuda.Stream(device=self.torch_device)
            self._stream = wp.stream_from_torch(self._torch_stream)
        self._step_graph = None
        self._reset_graph = None
        # every module a step or reset launches, and only those, before a graph is captured
        modules = [events, observations, self._sphere_kernel.module]
        if self.config.camera_resolution:
            modules.append(camera)
        for module in modules:
            wp.load_module(module, device=self.device)
        self.actuator.load(self.device)
        self.seed(seed)
        if self.device.is_cuda and cuda_graph:
            self._step_graph = self._capture(self._launch_step)
            self._reset_graph = self._capture(self._launch_reset)

    # --- public API -----------------------------------------------------------------------
    def view(self, name: str) -> torch.Tensor:
        """Zero-copy torch view of a data array (see :class:`~terrashift_rl.sim.types.Data`)."""
        if name not in self._views:
            array = getattr(self.data, name, None)
            if not isinstance(array, wp.array):
                raise KeyError(f"the simulator has no data array named {name!r}")
            self._views[name] = wp.to_torch(array)
        return self._views[name]

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Copies of every data array but the scratch ones: the whole state of every
        environment."""
        return {
            name: self.view(name).clone()
            for name, value in vars(self.data).items()
            if isinstance(value, wp.array) and name not in Data.SCRATCH + self.actuator.scratch
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restores a :meth:`state_dict` (one that holds the scratch arrays too loads as
        well); shapes must match this simulator's. Arrays saved under an earlier name
        (``_RENAMED_ARRAYS``) load into the array that has it now; arrays added since
        (``_ADDED_ARRAYS``) take their start value where the state lacks them."""
        state = {_RENAMED_ARRAYS.get(name, name): value for name, value in state.items()}
        for name, value in _ADDED_ARRAYS.items():
            if name not in state:
                state[name] = torch.full_like(self.view(name), value)
        missing = sorted(set(self.state_dict()) - set(state))
        if missing:
            raise ValueError(f"simulator state lacks {missing}")
        for name, value in state.items():
            target = self.view(name)
            if value.shape != target.shape:
                raise ValueError(
                    f"simulator state {name!r} has shape {tuple(value.shape)}, this simulator "
                    f"needs {tuple(target.shape)} (a different num_envs or scene size?)"
                )
            target.copy_(value)

    def seed(self, seed: int) -> None:
        """Re-seeds every environment's random stream (reset afterwards to use it)."""
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"seed must be an integer, got {seed!r}")
        with self._ordered():
            wp.launch(_seed_streams, dim=self.num_envs, inputs=[seed % _INT32_MAX, self.data.rng])

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Starts new episodes where ``mask`` (bool, [num_envs]) is True; all if None."""
        target = self.view("reset_mask")
        if mask is None:
            target.fill_(True)
        else:
            if mask.shape != (self.num_envs,) or mask.dtype != torch.bool:
                raise ValueError(
                    f"reset mask must be a bool tensor of shape ({self.num_envs},), got "
                    f"{mask.dtype} {tuple(mask.shape)}"
                )
            target.copy_(mask)
        self._run(self._reset_graph, self._launch_reset)

    def step(self, action: torch.Tensor) -> None:
        """Advances every environment by one decision (``action_repeat`` physics ticks).

        ``action`` is a float tensor [num_envs, K, 6] on the simulator's device; values are
        clipped to [-1, 1]. Results are read through :meth:`view`.
        """
        self.view("action").copy_(action)
        self._run(self._step_graph, self._launch_step)

    def physics_tick(self) -> None:
        """Advances the spheres by one physics tick with the columns moving from
        ``column_height_prev`` to ``column_height``; no wave, events or observations."""
        with self._ordered():
            self._launch_physics()

    def events_tick(self) -> None:
        """Runs one physics tick's events on the current state: goals, out-of-bounds,
        respawns and the reward terms (added to ``reward``); no wave or physics."""
        with self._ordered():
            self._launch_events()

    def observe(self) -> None:
        """Recomputes the observations from the current state."""
        with self._ordered():
            self._launch_observations()

    @property
    def action_shape(self) -> tuple[int, int, int]:
        """Shape of :meth:`step`'s action: (num_envs, K agents, action dimension)."""
        return self.num_envs, self.config.num_agents, ACTION_DIM

    # --- launch order ---------------------------------------------------------------------
    def _launch_step(self) -> None:
        d, m = self.data, self.model
        n = self.num_envs
        wp.launch(events.begin_decision, dim=n, inputs=[d.reward])
        for _ in range(self.config.action_repeat):
            self.actuator.launch_update(self)
            self.actuator.launch_surface(self, reset=False)
            self._launch_physics()
            self._launch_events()
        wp.launch(
            events.end_decision,
            dim=n,
            inputs=[m, d.sphere_active, d.spawn_timer, d.step_count, d.terminated, d.truncated],
        )
        self._launch_observations()

    def _launch_reset(self) -> None:
        d, m = self.data, self.model
        n = self.num_envs
        # the family's start is drawn first, then the goals, from the same random stream
        self.actuator.launch_reset(self)
        wp.launch(
            events.reset_episodes,
            dim=n,
            inputs=[
                m,
                d.reset_mask,
                d.rng,
                d.approach_gap,
                d.sphere_approach_gap,
                d.goal_cell,
                d.sphere_active,
                d.spawn_timer,
                d.surface_work,
                d.step_count,
                d.reward,
                d.terminated,
                d.truncated,
                d.episode_goals,
                d.episode_out_of_bounds,
            ],
        )
        self.actuator.launch_surface(self, reset=True)
        wp.launch(
            events.spawn_due,
            dim=n,
            inputs=[
                m,
                d.reset_mask,
                d.rng,
                d.column_height,
                d.goal_cell,
                d.sphere_active,
                d.spawn_timer,
                d.sphere_position,
                d.sphere_velocity,
                d.sphere_angular_velocity,
                d.goal_distance,
            ],
        )
        self._launch_observations()

    def _launch_physics(self) -> None:
        d, m = self.data, self.model
        current = (d.sphere_position, d.sphere_velocity, d.sphere_angular_velocity)
        scratch = (d.sphere_position_next, d.sphere_velocity_next, d.sphere_angular_velocity_next)
        fields = (
            d.column_height_prev,
            d.column_height,
            d.surface_velocity,
            d.surface_work,
            d.sphere_active,
        )
        if self.fuse_substeps:
            wp.launch(
                self._sphere_kernel, dim=self.num_envs, inputs=[m, *fields, *current, *scratch]
            )
            return
        substeps = self.config.substeps
        for s in range(substeps):
            src, dst = (current, scratch) if s % 2 == 0 else (scratch, current)
            wp.launch(
                self._sphere_kernel,
                dim=(self.num_envs, self.config.num_objects),
                inputs=[m, (s + 0.5) / substeps, *fields, *src, *dst],
            )
        if substeps % 2 == 1:
            for dst, src in zip(current, scratch, strict=True):
                wp.copy(dst, src)

    def _launch_events(self) -> None:
        d, m = self.data, self.model
        wp.launch(
            events.tick_events,
            dim=self.num_envs,
            inputs=[
                m,
                d.rng,
                d.column_height,
                d.goal_cell,
                d.sphere_active,
                d.spawn_timer,
                d.sphere_position,
                d.sphere_velocity,
                d.sphere_angular_velocity,
                d.goal_distance,
                d.agent_position,
                d.approach_gap,
                d.sphere_approach_gap,
                d.reward,
                d.episode_goals,
                d.episode_out_of_bounds,
            ],
        )

    def _launch_observations(self) -> None:
        d, m = self.data, self.model
        n, r = self.num_envs, self.config.heightmap_resolution
        wp.launch(
            observations.cast_heightmap,
            dim=(n, r),
            inputs=[m, d.column_height, d.sphere_active, d.sphere_position, d.heightmap],
        )
        wp.launch(
            observations.gather_features,
            dim=(n, self.config.num_objects),
            inputs=[
                m,
                d.column_height,
                d.goal_cell,
                d.sphere_active,
                d.sphere_position,
                d.sphere_velocity,
                d.object_features,
                d.object_mask,
            ],
        )
        self.actuator.launch_observe(self)
        if self.config.camera_resolution:
            camera.render(m, d, self.config, n)

    # --- execution ------------------------------------------------------------------------
    @contextlib.contextmanager
    def _ordered(self) -> Iterator[None]:
        """Runs launches on the simulator's stream, ordered after and before torch's work."""
        if self._stream is None:
            with wp.ScopedDevice(self.device):
                yield
            return
        current = torch.cuda.current_stream(self.torch_device)
        self._torch_stream.wait_stream(current)
        with wp.ScopedDevice(self.device), wp.ScopedStream(self._stream):
            yield
        current.wait_stream(self._torch_stream)

    def _capture(self, launch) -> wp.Graph:
        # launches go to the device's current stream: make it the stream being captured
        with (
            wp.ScopedDevice(self.device),
            wp.ScopedStream(self._stream),
            wp.ScopedCapture(stream=self._stream) as capture,
        ):
            launch()
        return capture.graph

    def _run(self, graph, launch) -> None:
        with self._ordered():
            if graph is not None:
                wp.capture_launch(graph, stream=self._stream)
            else:
                launch()
