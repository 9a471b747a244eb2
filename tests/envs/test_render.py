"""Headless rendering: frames, what changes where, videos, atomic writes, recorded rollouts."""

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
from PIL import Image

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.envs.render import (
    GOAL_COLORS,
    Renderer,
    record_rollout,
    render_frame,
    save_video,
)
from terrashift_rl.sim import COLUMN_SHAPES, Simulator, TerraShiftConfig

W, H = 640, 320
GOAL_CELLS = ((4, 4), (10, 4), (4, 10), (10, 10))  # (ix, iy) of goals 0..3


def centre(cfg: TerraShiftConfig, i: int) -> float:
    return (i + 0.5) * cfg.cell_size - 0.5 * cfg.platform_size


def staged_sim(shape: str = "box") -> Simulator:
    """Two environments with flat columns, goals on GOAL_CELLS, spheres 0 and 5 at rest."""
    cfg = TerraShiftConfig(column_shape=shape, num_objects=6, num_goals=4)
    sim = Simulator(cfg, num_envs=2, seed=0)
    sim.reset()
    sim.view("column_height").zero_()
    sim.view("column_height_prev").zero_()
    sim.view("goal_cell")[:] = torch.tensor(GOAL_CELLS, dtype=torch.int32)
    sim.view("sphere_active").zero_()
    sim.view("sphere_active")[:, [0, 5]] = 1
    z = cfg.column_rest_top + cfg.sphere_radius
    sim.view("sphere_position")[:, 0] = torch.tensor([centre(cfg, 7), centre(cfg, 12), z])
    sim.view("sphere_position")[:, 5] = torch.tensor([centre(cfg, 7), centre(cfg, 7), z])
    sim.observe()
    return sim


def changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(row, column) of every pixel that differs."""
    return np.argwhere((a != b).any(-1))


def box_of(renderer: Renderer, corners: np.ndarray, margin: float = 3.0) -> tuple:
    """Pixel bounding box (col0, row0, col1, row1) of world points [P, 3], widened by margin."""
    pixels = renderer.to_pixels(corners)
    (c0, r0), (c1, r1) = pixels.min(0) - margin, pixels.max(0) + margin
    return c0, r0, c1, r1


def inside(pixels: np.ndarray, box: tuple) -> np.ndarray:
    c0, r0, c1, r1 = box
    return (pixels[:, 1] >= c0) & (pixels[:, 1] <= c1) & (pixels[:, 0] >= r0) & (pixels[:, 0] <= r1)


def cube(point, half: float) -> np.ndarray:
    offsets = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    return np.asarray(point) + half * offsets


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_render_frame_is_a_busy_rgb_image_for_every_column_shape(shape):
    sim = Simulator(TerraShiftConfig(column_shape=shape), num_envs=2, seed=1)
    sim.reset()
    for _ in range(5):
        sim.step(torch.rand(2, 8, 6) * 2 - 1)
    frame = render_frame(sim, 1, width=400, height=200)
    assert frame.shape == (200, 400, 3) and frame.dtype == np.uint8
    for half in (frame[:, :200], frame[:, 200:]):
        assert len(np.unique(half.reshape(-1, 3), axis=0)) > 200


def test_renderer_keeps_odd_sizes_exact_and_rejects_tiny_ones():
    sim = staged_sim()
    assert Renderer(sim.config, width=641, height=333).frame(sim).shape == (333, 641, 3)
    with pytest.raises(ValueError, match="width"):
        Renderer(width=50)
    with pytest.raises(ValueError, match="env_index"):
        Renderer(sim.config).frame(sim, env_index=2)


def test_raised_column_changes_only_the_scene_around_that_column():
    sim = staged_sim("box")
    cfg, renderer = sim.config, Renderer(sim.config, width=W, height=H)
    before = renderer.frame(sim)
    ix, iy, rise = 12, 2, 0.05  # no goal, no sphere near this column
    sim.view("column_height")[0, iy, ix] = rise  # the heightmap is not recomputed
    after = renderer.frame(sim)
    diff = changed(before, after)
    assert len(diff) > 50
    assert (diff[:, 1] < W // 2).all()  # the heightmap half is untouched
    d = 0.5 * cfg.cell_size
    body = np.array(
        [
            [centre(cfg, ix) + sx * d, centre(cfg, iy) + sy * d, z]
            for sx in (-1, 1)
            for sy in (-1, 1)
            for z in (0.0, cfg.column_rest_top + rise)
        ]
    )
    assert inside(diff, box_of(renderer, body)).all()


def test_moved_sphere_changes_the_scene_where_it_was_and_where_it_is():
    sim = staged_sim("ellipsoid")
    cfg, renderer = sim.config, Renderer(sim.config, width=W, height=H)
    before = renderer.frame(sim)
    old = sim.view("sphere_position")[0, 0].clone().numpy()
    new = old + np.array([0.15, -0.1, 0.05])
    sim.view("sphere_position")[0, 0] = torch.from_numpy(new)
    after = renderer.frame(sim)
    diff = changed(before, after)
    assert (diff[:, 1] < W // 2).all()
    old_box = box_of(renderer, cube(old, cfg.sphere_radius))
    new_box = box_of(renderer, cube(new, cfg.sphere_radius))
    assert (inside(diff, old_box) | inside(diff, new_box)).all()
    assert inside(diff, old_box).sum() > 100 and inside(diff, new_box).sum() > 100


def test_sphere_wears_the_colour_of_its_goal():
    sim = staged_sim("box")
    renderer = Renderer(sim.config, width=W, height=H)
    frame = renderer.frame(sim).astype(int)
    for j in (0, 5):  # sphere 5 belongs to goal 5 % 4 = 1
        col, row = np.round(renderer.to_pixels(sim.view("sphere_position")[0, j].numpy()))
        expected = np.round(255 * np.array(GOAL_COLORS[j % 4]))
        assert np.abs(frame[int(row), int(col)] - expected).max() <= 2
    assert not np.allclose(GOAL_COLORS[0], GOAL_COLORS[1])


def test_heightmap_half_shows_the_observation_of_the_rendered_env_rows_along_plus_y():
    sim = staged_sim("smooth")
    renderer = Renderer(sim.config, width=W, height=H)
    base = renderer.frame(sim)
    heightmap = sim.view("heightmap")
    saved = heightmap.clone()
    heightmap[1] = 1.0  # another environment: env 0's frame must not change
    assert (renderer.frame(sim) == base).all()
    heightmap.copy_(saved)
    heightmap[0, 0, :6, :6] = 1.0  # low y, low x
    low = changed(base, renderer.frame(sim))
    heightmap.copy_(saved)
    heightmap[0, 0, -6:, -6:] = 1.0  # high y, high x
    high = changed(base, renderer.frame(sim))
    for diff in (low, high):
        assert len(diff) > 100 and (diff[:, 1] >= W // 2).all()
    # +x to the right, +y upwards (rows count down in the frame)
    assert low[:, 1].mean() < high[:, 1].mean() and low[:, 0].mean() > high[:, 0].mean()


def test_renderer_follows_a_simulator_with_another_config():
    renderer = Renderer(TerraShiftConfig(column_shape="box"), width=W, height=H)
    sim = Simulator(
        TerraShiftConfig(grid_size=10, column_shape="smooth", num_objects=2, num_goals=2),
        num_envs=1,
        seed=0,
    )
    sim.reset()
    frame = renderer.frame(sim)
    assert (frame == render_frame(sim, width=W, height=H)).all()


def moving_square(count: int, height: int, width: int) -> np.ndarray:
    frames = np.zeros((count, height, width, 3), dtype=np.uint8)
    frames[..., 2] = 60
    for t in range(count):
        frames[t, 8:24, 4 + 6 * t : 20 + 6 * t] = (250, 200, 30)
    return frames


def test_save_video_writes_a_gif_with_every_frame(tmp_path):
    frames = moving_square(5, 48, 64)
    path = save_video(list(frames), tmp_path / "clip.gif", fps=10)
    assert path == tmp_path / "clip.gif"
    with Image.open(path) as gif:
        assert gif.n_frames == 5
        gif.seek(2)
        assert np.abs(np.asarray(gif.convert("RGB")).astype(int) - frames[2]).max() <= 8
        assert gif.info["duration"] == 100


def test_save_video_writes_an_mp4_with_every_frame_padding_odd_sizes(tmp_path):
    frames = moving_square(6, 47, 65)
    path = save_video(frames, tmp_path / "clip.MP4", fps=12)
    with imageio.get_reader(path, format="FFMPEG") as reader:
        decoded = np.stack([frame for frame in reader])  # list() trips on len() == inf
        assert reader.get_meta_data()["fps"] == pytest.approx(12)
    assert decoded.shape == (6, 48, 66, 3)
    assert np.abs(decoded[:, :47, :65].astype(int) - frames).mean() < 6


def test_save_video_rejects_bad_suffixes_and_frames(tmp_path):
    good = moving_square(2, 16, 16)
    bad = (
        ([good[0]], tmp_path / "clip.avi", "suffix"),
        ([], tmp_path / "clip.gif", "no frames"),
        ([good[0], good[1, :8]], tmp_path / "clip.gif", "one shape"),
        (good.astype(np.float32), tmp_path / "clip.mp4", "uint8"),
        (good[..., 0], tmp_path / "clip.mp4", "uint8"),
    )
    for frames, path, message in bad:
        with pytest.raises(ValueError, match=message):
            save_video(frames, path)
    with pytest.raises(ValueError, match="fps"):
        save_video(good, tmp_path / "clip.gif", fps=0)
    assert list(tmp_path.iterdir()) == []


def test_save_video_replaces_atomically_and_cleans_up_after_a_failure(tmp_path, monkeypatch):
    from terrashift_rl.envs.render import video

    target = tmp_path / "out" / "clip.gif"
    save_video(moving_square(3, 32, 32), target)
    save_video(moving_square(4, 32, 32), tmp_path / "out" / "clip.mp4")
    assert sorted(p.name for p in target.parent.iterdir()) == ["clip.gif", "clip.mp4"]
    old = target.read_bytes()

    def crash(frames, path, fps):
        path.write_bytes(b"GIF89a half written")
        raise RuntimeError("killed mid-write")

    monkeypatch.setitem(video._WRITERS, ".gif", crash)
    with pytest.raises(RuntimeError, match="killed"):
        save_video(moving_square(3, 32, 32), target)
    assert target.read_bytes() == old
    assert sorted(p.name for p in target.parent.iterdir()) == ["clip.gif", "clip.mp4"]


def test_record_rollout_renders_the_reset_then_every_kth_step_with_the_policy():
    env = TerraShiftEnv(num_envs=2, seed=0)
    calls = []

    def policy(td):
        calls.append(td["heightmap"].shape)
        td[GROUP, "action"] = torch.zeros(2, 8, 6)
        return td

    frames = record_rollout(env, policy, steps=4, env_index=1, every=2, width=320, height=160)
    assert len(calls) == 4 and len(frames) == 1 + 4 // 2
    assert env.sim.view("step_count").tolist() == [4, 4]
    assert all(frame.shape == (160, 320, 3) for frame in frames)
    # the last frame is env 1 after the 4th step: the state the simulator holds now
    assert (frames[-1] == render_frame(env.sim, 1, width=320, height=160)).all()
    assert not (frames[-1] == render_frame(env.sim, 0, width=320, height=160)).all()
    assert not (frames[0] == frames[-1]).all()
    with pytest.raises(ValueError, match="every"):
        record_rollout(env, steps=2, every=0)


def test_record_rollout_with_random_actions_moves_the_columns():
    env = TerraShiftEnv(num_envs=1, seed=0)
    frames = record_rollout(env, steps=3, width=320, height=160)
    assert len(frames) == 4
    scene = [frame[:, :160] for frame in frames]
    assert not (scene[0] == scene[3]).all()
