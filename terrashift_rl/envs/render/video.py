"""Recorded rollouts and video files (MP4 through imageio-ffmpeg, GIF through Pillow), written
atomically."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from PIL import Image
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from tqdm import tqdm

from terrashift_rl.envs.render.figure import Renderer

__all__ = ["record_rollout", "save_video"]


def record_rollout(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None = None,
    *,
    steps: int,
    env_index: int = 0,
    every: int = 1,
    width: int = 960,
    height: int = 480,
) -> list[np.ndarray]:
    """Resets ``env``, steps it ``steps`` times and renders one of its environments.

    Args:
        env: a :class:`~terrashift_rl.envs.TerraShiftEnv`, or a ``TransformedEnv`` around one
            (its ``sim`` and ``config`` are reached through the transformed env).
        policy: any callable that takes the current tensordict and returns it with
            ``("agents", "action")`` written; uniform random actions if None. It runs under
            ``torch.no_grad()``.
        steps: decisions to play, >= 0.
        env_index: which environment of the batch to render.
        every: render after every ``every``-th step, >= 1.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``1 + steps // every`` frames: the state after the reset, then one after every
        ``every``-th step (after ``step_and_maybe_reset``, so a finished episode shows the new
        episode's first state).

    Example:
        >>> from terrashift_rl.envs import TerraShiftEnv
        >>> env = TerraShiftEnv(num_envs=2, seed=0)
        >>> frames = record_rollout(env, steps=4, every=2, width=320, height=160)
        >>> len(frames), frames[0].shape
        (3, (160, 320, 3))
    """
    for name, value, minimum in (("steps", steps, 0), ("every", every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    renderer = Renderer(env.config, width=width, height=height)
    with torch.no_grad():
        td = env.reset()
        frames = [renderer.frame(env.sim, env_index)]
        for t in tqdm(range(steps), desc="recording", unit="step"):
            td = env.rand_action(td) if policy is None else policy(td)
            _, td = env.step_and_maybe_reset(td)
            if (t + 1) % every == 0:
                frames.append(renderer.frame(env.sim, env_index))
    return frames


def save_video(
    frames: Sequence[np.ndarray] | np.ndarray, path: str | Path, *, fps: int = 30
) -> Path:
    """Writes frames to an MP4 (H.264) or GIF file, chosen by the suffix of ``path``.

    The video is written to a hidden temporary file in the same folder and moved over ``path``
    only once complete, so an interrupted write never leaves a partial video at ``path`` (and
    a failed one removes its temporary file). Frames of odd width or height are padded by one
    pixel for H.264. A GIF stores identical consecutive frames as one longer frame.

    Args:
        frames: uint8 RGB frames, each [height, width, 3], all of one size (a list or an array
            [T, height, width, 3]).
        path: output file, ending in ``.mp4`` or ``.gif``; missing folders are created.
        fps: frames per second, > 0.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: for another suffix, no frames, frames of mixed sizes or not uint8 RGB,
            or a non-positive ``fps``.

    Example:
        >>> import tempfile
        >>> frames = np.zeros((3, 32, 48, 3), dtype=np.uint8)
        >>> frames[:, :, :, 0] = np.arange(3)[:, None, None] * 100
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     save_video(frames, Path(folder) / "clip.gif", fps=10).name
        'clip.gif'
    """
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise ValueError(
            f"cannot write a video to {str(path)!r}: the suffix must be one of {sorted(_WRITERS)}"
        )
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not fps > 0:
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    stack = _frame_stack(frames)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.{os.urandom(4).hex()}.tmp{path.suffix}")
    try:
        writer(stack, temporary, fps)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path


def _frame_stack(frames: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    if len(frames) == 0:
        raise ValueError("no frames to save")
    shapes = {np.shape(frame) for frame in frames}
    if len(shapes) > 1:
        raise ValueError(f"frames must all have one shape, got {sorted(shapes)}")
    stack = np.stack([np.asarray(frame) for frame in frames])
    if stack.dtype != np.uint8 or stack.ndim != 4 or stack.shape[-1] != 3:
        raise ValueError(
            f"frames must be uint8 [height, width, 3], got {stack.dtype} {stack.shape[1:]}"
        )
    return stack


def _write_gif(frames: np.ndarray, path: Path, fps: float) -> None:
    images = [Image.fromarray(frame) for frame in frames]
    images[0].save(
        path,
        format="GIF",
        save_all=True,
        append_images=images[1:],
        duration=round(1000.0 / fps),
        loop=0,
    )


def _write_mp4(frames: np.ndarray, path: Path, fps: float) -> None:
    _, height, width, _ = frames.shape
    frames = np.pad(frames, ((0, 0), (0, height % 2), (0, width % 2), (0, 0)), mode="edge")
    with imageio.get_writer(
        path,
        format="FFMPEG",
        mode="I",
        fps=fps,
        codec="libx264",
        pixelformat="yuv420p",
        quality=7,
        macro_block_size=1,
        ffmpeg_log_level="error",
    ) as writer:
        for frame in frames:
            writer.append_data(frame)


_WRITERS = {".gif": _write_gif, ".mp4": _write_mp4}
