"""Wave stage against a NumPy reference: wavelet heights and the parameter dynamics."""

import math

import numpy as np
import pytest
import torch

from terrashift_rl.sim import Simulator, TerraShiftConfig

SEED = 0
HEIGHT_TOL = 1e-6
"""Absolute tolerance on column heights [m]: float32 rounding of a sum of a few Gaussians."""
STATE_TOL = 1e-4
"""Absolute tolerance on wavelet parameters after several decisions: float32 rounding
accumulated over a few dozen ticks (positions are up to G = 15 cells)."""


def make_sim(*, num_envs: int = 2, **overrides) -> Simulator:
    config = TerraShiftConfig(num_objects=1, num_goals=1, **overrides)
    sim = Simulator(config, num_envs=num_envs, seed=SEED)
    sim.reset()
    return sim


def reference_heights(
    position: np.ndarray,
    angle: np.ndarray,
    amplitude: np.ndarray,
    sigma: np.ndarray,
    *,
    grid_size: int,
    max_height: float,
    wrap: bool,
) -> np.ndarray:
    """Column heights [G(y), G(x)] of one environment's wavelets (shapes [K, 2], [K], ...)."""
    g = grid_size
    iy, ix = np.meshgrid(
        np.arange(g, dtype=np.float64), np.arange(g, dtype=np.float64), indexing="ij"
    )
    height = np.zeros((g, g))
    for (x, y), theta, amp, (sx, sy) in zip(position, angle, amplitude, sigma, strict=True):
        dx, dy = ix - x, iy - y
        if wrap:
            dx = dx - g * np.floor(dx / g + 0.5)
            dy = dy - g * np.floor(dy / g + 0.5)
        c, s = math.cos(theta), math.sin(theta)
        xr = c * dx + s * dy
        yr = -s * dx + c * dy
        height += amp * np.exp(-0.5 * (xr**2 / sx**2 + yr**2 / sy**2))
    return np.clip(height, -max_height, max_height)


def set_agents(sim: Simulator, position, angle, amplitude, sigma) -> None:
    """Writes the wavelet parameters of every environment, with zero rates."""
    for name, value in (
        ("agent_position", position),
        ("agent_angle", angle),
        ("agent_amplitude", amplitude),
        ("agent_sigma", sigma),
    ):
        view = sim.view(name)
        view.copy_(torch.as_tensor(np.asarray(value), dtype=view.dtype).expand_as(view))
    sim.view("agent_velocity").zero_()
    sim.view("agent_angular_velocity").zero_()


def heights_after_zero_action(sim: Simulator) -> np.ndarray:
    """One decision with zero actions: with zero rates the wavelets stay where they were put."""
    before = {n: sim.view(n).clone() for n in ("agent_position", "agent_angle", "agent_sigma")}
    sim.step(torch.zeros(sim.action_shape))
    for name, value in before.items():
        torch.testing.assert_close(sim.view(name), value, rtol=0.0, atol=1e-6, msg=name)
    return sim.view("column_height").double().numpy()


def reference_for(sim: Simulator, env: int) -> np.ndarray:
    cfg = sim.config
    return reference_heights(
        sim.view("agent_position")[env].double().numpy(),
        sim.view("agent_angle")[env].double().numpy(),
        sim.view("agent_amplitude")[env].double().numpy(),
        sim.view("agent_sigma")[env].double().numpy(),
        grid_size=cfg.grid_size,
        max_height=cfg.max_column_height,
        wrap=cfg.wrap_edges,
    )


# --- heights ------------------------------------------------------------------------------


@pytest.mark.parametrize("wrap_edges", [True, False])
def test_random_wavelets_match_reference(wrap_edges):
    sim = make_sim(num_envs=3, wrap_edges=wrap_edges, num_agents=5)
    rng = np.random.default_rng(SEED)
    cfg, n, k = sim.config, sim.num_envs, sim.config.num_agents
    set_agents(
        sim,
        rng.uniform(0.0, cfg.grid_size - 1.0, (n, k, 2)),
        rng.uniform(0.0, 2 * math.pi, (n, k)),
        rng.uniform(-cfg.max_amplitude, cfg.max_amplitude, (n, k)),
        rng.uniform(cfg.sigma_min, cfg.sigma_max, (n, k, 2)),
    )
    heights = heights_after_zero_action(sim)
    for env in range(n):
        np.testing.assert_allclose(heights[env], reference_for(sim, env), atol=HEIGHT_TOL)
    assert np.abs(heights).max() > 0.01  # the field is not trivially flat


@pytest.mark.parametrize("axis", ["x", "y"])
def test_wavelet_near_an_edge_wraps_across_it_only_on_a_torus(axis):
    g = TerraShiftConfig().grid_size
    centre = [0.2, 7.0] if axis == "x" else [7.0, 0.2]
    fields = {}
    for wrap in (True, False):
        sim = make_sim(num_envs=1, num_agents=1, wrap_edges=wrap)
        set_agents(sim, [[centre]], [[0.0]], [[0.05]], [[[1.0, 1.0]]])
        fields[wrap] = heights_after_zero_action(sim)[0]
        np.testing.assert_allclose(fields[wrap], reference_for(sim, 0), atol=HEIGHT_TOL)
    # column G - 1 sits 1.2 cells from the centre across the edge: exp(-0.72) of the amplitude
    across = (7, g - 1) if axis == "x" else (g - 1, 7)
    assert fields[True][across] == pytest.approx(0.05 * math.exp(-0.5 * 1.2**2), abs=HEIGHT_TOL)
    assert abs(fields[False][across]) < HEIGHT_TOL
    # the near side is the same either way
    near = (7, 1) if axis == "x" else (1, 7)
    assert fields[True][near] == pytest.approx(fields[False][near], abs=HEIGHT_TOL)
    assert fields[True][near] == pytest.approx(0.05 * math.exp(-0.5 * 0.8**2), abs=HEIGHT_TOL)


def test_elongated_wavelet_rotated_by_a_right_angle_transposes():
    fields = []
    for theta in (0.0, math.pi / 2):
        sim = make_sim(num_envs=1, num_agents=1)
        set_agents(sim, [[[7.0, 7.0]]], [[theta]], [[0.05]], [[[2.0, 0.5]]])
        fields.append(heights_after_zero_action(sim)[0])
        np.testing.assert_allclose(fields[-1], reference_for(sim, 0), atol=HEIGHT_TOL)
    flat, turned = fields
    # theta = 0 stretches along x: the row through the centre (iy = 7) is the long axis
    assert flat[7, 9] > 0.03 and flat[9, 7] < 1e-4
    np.testing.assert_allclose(turned, flat.T, atol=HEIGHT_TOL)
    assert not np.allclose(turned, flat, atol=1e-3)


def test_sum_of_wavelets_is_clipped_to_the_column_limit():
    sim = make_sim(num_envs=1, num_agents=4)
    limit = sim.config.max_column_height
    amp = sim.config.max_amplitude
    # two positive wavelets on one cell, two negative ones on another
    set_agents(
        sim,
        [[[4.0, 4.0], [4.0, 4.0], [10.0, 9.0], [10.0, 9.0]]],
        [[0.0, 1.0, 2.0, 3.0]],
        [[amp, amp, -amp, -amp]],
        [[[1.5, 1.5]] * 4],
    )
    heights = heights_after_zero_action(sim)[0]
    np.testing.assert_allclose(heights, reference_for(sim, 0), atol=HEIGHT_TOL)
    assert 2 * amp > limit  # the unclipped peaks exceed the limit
    assert heights[4, 4] == pytest.approx(limit, abs=HEIGHT_TOL)
    assert heights[9, 10] == pytest.approx(-limit, abs=HEIGHT_TOL)
    assert np.abs(heights).max() <= limit
    # clipped on a plateau around the peaks, not just at them
    assert (np.abs(np.abs(heights) - limit) < HEIGHT_TOL).sum() > 2


# --- parameter dynamics -------------------------------------------------------------------


def read_state(sim: Simulator) -> dict[str, np.ndarray]:
    names = (
        "agent_position",
        "agent_velocity",
        "agent_angle",
        "agent_angular_velocity",
        "agent_amplitude",
        "agent_sigma",
    )
    return {name: sim.view(name).double().numpy().copy() for name in names}


def reference_tick(state: dict[str, np.ndarray], action: np.ndarray, cfg: TerraShiftConfig):
    """One physics tick of ``wave.update_agents``: rates and shape first (clamped), then the
    wavelet moves with the clamped rates."""
    a = np.clip(action, -1.0, 1.0)
    h = cfg.wave_step
    if cfg.action_mode == "target":
        a = changes_towards_targets(state, a, cfg)
    elif cfg.action_mode == "shape":
        a = np.concatenate([a[..., 0:3], changes_towards_targets(state, a, cfg)[..., 3:]], -1)
    elif cfg.action_mode == "position":
        a = np.concatenate([changes_towards_position(state, a, cfg), a[..., 2:]], -1)
    g = cfg.grid_size
    v = np.clip(
        state["agent_velocity"] + cfg.velocity_gain * h * a[..., 0:2],
        -cfg.max_velocity,
        cfg.max_velocity,
    )
    omega = np.clip(
        state["agent_angular_velocity"] + cfg.angular_velocity_gain * h * a[..., 2],
        -cfg.max_angular_velocity,
        cfg.max_angular_velocity,
    )
    amplitude = np.clip(
        state["agent_amplitude"] + cfg.amplitude_gain * h * a[..., 3],
        cfg.min_amplitude_ratio * cfg.max_amplitude,
        cfg.max_amplitude,
    )
    sigma = np.clip(
        state["agent_sigma"] + cfg.sigma_gain * h * a[..., 4:6], cfg.sigma_min, cfg.sigma_max
    )
    position = state["agent_position"] + h * v
    position = np.mod(position, g) if cfg.wrap_edges else np.clip(position, 0.0, g - 1.0)
    angle = np.mod(state["agent_angle"] + h * omega, 2 * math.pi)
    return {
        "agent_position": position,
        "agent_velocity": v,
        "agent_angle": angle,
        "agent_angular_velocity": omega,
        "agent_amplitude": amplitude,
        "agent_sigma": sigma,
    }


def changes_towards_targets(state: dict[str, np.ndarray], a: np.ndarray, cfg: TerraShiftConfig):
    """The delta action that moves each quantity towards the target ``a`` sets, by at most a
    full delta action's change."""
    h = cfg.wave_step
    half_range = 0.5 * (cfg.sigma_max - cfg.sigma_min)
    targets = (
        (a[..., 0:2] * cfg.max_velocity, state["agent_velocity"], cfg.velocity_gain),
        (
            a[..., 2:3] * cfg.max_angular_velocity,
            state["agent_angular_velocity"][..., None],
            cfg.angular_velocity_gain,
        ),
        (a[..., 3:4] * cfg.max_amplitude, state["agent_amplitude"][..., None], cfg.amplitude_gain),
        (cfg.sigma_min + (a[..., 4:6] + 1.0) * half_range, state["agent_sigma"], cfg.sigma_gain),
    )
    return np.concatenate(
        [np.clip((target - now) / (gain * h), -1.0, 1.0) for target, now, gain in targets], -1
    )


def changes_towards_position(state: dict[str, np.ndarray], a: np.ndarray, cfg: TerraShiftConfig):
    """The velocity delta action of ``position`` actions: towards ``position_gain`` times the
    offset to cell ``(a + 1) G / 2`` (the short way on a torus), clipped to the speed limit."""
    g = cfg.grid_size
    offset = (a[..., 0:2] + 1.0) * 0.5 * g - state["agent_position"]
    if cfg.wrap_edges:
        offset = offset - g * np.floor(offset / g + 0.5)
    aim = np.clip(cfg.position_gain * offset, -cfg.max_velocity, cfg.max_velocity)
    return np.clip((aim - state["agent_velocity"]) / (cfg.velocity_gain * cfg.wave_step), -1, 1)


def circular_error(actual: np.ndarray, expected: np.ndarray, period: float) -> np.ndarray:
    """|actual - expected| on a circle, so values just either side of the wrap compare equal."""
    d = actual - expected
    return np.abs(d - period * np.round(d / period))


@pytest.mark.parametrize(
    ("wrap_edges", "action_mode", "min_amplitude_ratio"),
    [
        (True, "delta", -1.0),
        (False, "delta", -1.0),
        (True, "delta", 0.0),
        (True, "target", -1.0),
        (True, "position", -1.0),
        (False, "position", -1.0),
        (True, "shape", -1.0),
    ],
)
def test_parameter_dynamics_match_reference_over_several_decisions(
    wrap_edges, action_mode, min_amplitude_ratio
):
    sim = make_sim(
        num_envs=3,
        num_agents=6,
        action_repeat=3,
        wrap_edges=wrap_edges,
        action_mode=action_mode,
        min_amplitude_ratio=min_amplitude_ratio,
    )
    cfg = sim.config
    rng = np.random.default_rng(SEED)
    state = read_state(sim)
    for _ in range(8):
        # a third of the values lie beyond [-1, 1] and must act as +-1
        action = rng.uniform(-1.5, 1.5, sim.action_shape)
        sim.step(torch.as_tensor(action, dtype=torch.float32))
        for _ in range(cfg.action_repeat):
            state = reference_tick(state, action.astype(np.float32).astype(np.float64), cfg)
        actual = read_state(sim)
        for name in ("agent_velocity", "agent_angular_velocity", "agent_amplitude", "agent_sigma"):
            np.testing.assert_allclose(actual[name], state[name], atol=STATE_TOL, err_msg=name)
        if wrap_edges:
            assert (
                circular_error(
                    actual["agent_position"], state["agent_position"], cfg.grid_size
                ).max()
                < STATE_TOL
            )
        else:
            np.testing.assert_allclose(
                actual["agent_position"], state["agent_position"], atol=STATE_TOL
            )
        assert circular_error(actual["agent_angle"], state["agent_angle"], 2 * math.pi).max() < (
            STATE_TOL
        )
        # the stored state always lies in its documented range
        assert (actual["agent_position"] >= 0).all()
        assert (actual["agent_position"] <= cfg.grid_size).all()
        assert (actual["agent_angle"] >= 0).all()
        assert (actual["agent_angle"] <= 2 * math.pi).all()
    if action_mode != "delta":  # random targets rarely hold long enough to reach a limit
        return
    # the run exercised the limits
    assert np.isclose(np.abs(state["agent_velocity"]), cfg.max_velocity).any()
    assert (
        np.isclose(state["agent_sigma"], cfg.sigma_min).any()
        or np.isclose(state["agent_sigma"], cfg.sigma_max).any()
    )


def test_bumps_only_scene_starts_and_stays_at_or_above_zero_amplitude():
    sim = make_sim(num_envs=64, num_agents=8, min_amplitude_ratio=0.0)
    cfg = sim.config
    start = sim.view("agent_amplitude")
    assert (start >= 0).all() and (start <= cfg.max_amplitude).all()
    assert start.min() < 0.1 * cfg.max_amplitude  # drawn over [0, max], not stuck at one end
    down = torch.zeros(sim.action_shape)
    down[..., 3] = -1.0
    for _ in range(12):  # 12 decisions of 2 ticks lower by 1.2 max_amplitude
        sim.step(down)
    assert (sim.view("agent_amplitude") == 0.0).all()
    symmetric = make_sim(num_envs=64, num_agents=8)
    for _ in range(24):
        symmetric.step(down)
    assert (symmetric.view("agent_amplitude") == -cfg.max_amplitude).all()


def test_one_tick_from_rest_moves_by_gain_times_step():
    sim = make_sim(num_envs=1, num_agents=1, action_repeat=1)
    cfg = sim.config
    set_agents(sim, [[[5.0, 6.0]]], [[1.0]], [[0.0]], [[[1.0, 1.0]]])
    sim.step(torch.tensor([[[1.0, -1.0, 1.0, 1.0, -1.0, 1.0]]]))
    h = cfg.wave_step
    assert sim.view("agent_velocity")[0, 0].tolist() == pytest.approx([h, -h], abs=1e-7)
    # the position moves with the updated velocity (semi-implicit)
    assert sim.view("agent_position")[0, 0].tolist() == pytest.approx(
        [5.0 + h * h, 6.0 - h * h], abs=1e-6
    )
    omega = cfg.angular_velocity_gain * h
    assert sim.view("agent_angular_velocity")[0, 0].item() == pytest.approx(omega, abs=1e-7)
    assert sim.view("agent_angle")[0, 0].item() == pytest.approx(1.0 + h * omega, abs=1e-6)
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(
        cfg.amplitude_gain * h, abs=1e-7
    )
    assert sim.view("agent_sigma")[0, 0].tolist() == pytest.approx(
        [1.0 - cfg.sigma_gain * h, 1.0 + cfg.sigma_gain * h], abs=1e-6
    )


def test_target_actions_reach_their_targets_at_the_delta_rate_and_hold_them():
    sim = make_sim(num_envs=1, num_agents=1, action_repeat=1, action_mode="target")
    cfg = sim.config
    set_agents(sim, [[[5.0, 6.0]]], [[1.0]], [[0.0]], [[[1.0, 1.0]]])
    # targets: v = (+max, -max / 2), spin 0, amplitude +max, widths (sigma_min, sigma_max)
    action = torch.tensor([[[1.0, -0.5, 0.0, 1.0, -1.0, 1.0]]])
    h = cfg.wave_step
    sim.step(action)  # one tick from rest: a full delta action's change towards each target
    assert sim.view("agent_velocity")[0, 0].tolist() == pytest.approx([h, -h], abs=1e-7)
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(
        cfg.amplitude_gain * h, abs=1e-7
    )
    for _ in range(60):  # long enough for the slowest (the widths: 1.8 cells at 0.05 a tick)
        sim.step(action)
    assert sim.view("agent_velocity")[0, 0].tolist() == pytest.approx(
        [cfg.max_velocity, -0.5 * cfg.max_velocity], abs=1e-6
    )
    assert sim.view("agent_angular_velocity")[0, 0].item() == pytest.approx(0.0, abs=1e-7)
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(cfg.max_amplitude, abs=1e-7)
    assert sim.view("agent_sigma")[0, 0].tolist() == pytest.approx(
        [cfg.sigma_min, cfg.sigma_max], abs=1e-6
    )


@pytest.mark.parametrize(
    ("start", "target", "first_step"),
    [(5.0, 12.0, +1), (13.5, 1.0, +1), (1.0, 13.5, -1)],  # the last two the short way round
)
def test_position_actions_bring_the_wavelet_to_its_target_within_the_speed_limit(
    start, target, first_step
):
    sim = make_sim(num_envs=1, num_agents=1, action_repeat=1, action_mode="position")
    cfg = sim.config
    g, h = cfg.grid_size, cfg.wave_step
    set_agents(sim, [[[start, 6.0]]], [[0.0]], [[0.0]], [[[1.0, 1.0]]])
    # target cell (target, 6); the shape dims stay deltas: amplitude up at full rate
    action = torch.tensor([[[2.0 * target / g - 1.0, 2.0 * 6.0 / g - 1.0, 0.0, 1.0, 0.0, 0.0]]])
    sim.step(action)  # from rest: a full delta action's change of velocity towards the target
    assert sim.view("agent_velocity")[0, 0].tolist() == pytest.approx([first_step * h, 0.0])
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(cfg.amplitude_gain * h)
    speeds = []
    for _ in range(300):
        sim.step(action)
        speeds.append(sim.view("agent_velocity")[0, 0].abs().max().item())
    assert max(speeds) <= cfg.max_velocity + 1e-6
    distance = abs(target - start) if first_step * (target - start) > 0 else g - abs(target - start)
    if distance > 2.0:  # far enough to reach the speed limit on the way
        assert max(speeds) == pytest.approx(cfg.max_velocity)
    x, y = sim.view("agent_position")[0, 0].tolist()
    assert circular_error(np.array(x), np.array(target), g) < 1e-3 and y == pytest.approx(6.0)
    assert speeds[-1] < 1e-3  # at rest on its target
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(cfg.max_amplitude)


def test_shape_actions_change_the_rates_and_set_the_shape():
    sim = make_sim(num_envs=1, num_agents=1, action_repeat=1, action_mode="shape")
    cfg = sim.config
    set_agents(sim, [[[5.0, 6.0]]], [[1.0]], [[0.0]], [[[1.0, 1.0]]])
    # rates: full acceleration along +x, none along y, full spin-up; shape: a basin half the
    # floor's depth, widths (sigma_min, sigma_max)
    action = torch.tensor([[[1.0, 0.0, 1.0, -0.5, -1.0, 1.0]]])
    for _ in range(60):  # long enough for the slowest target (the widths: 1.8 cells at 0.05)
        sim.step(action)
    assert sim.view("agent_velocity")[0, 0].tolist() == pytest.approx([cfg.max_velocity, 0.0])
    assert sim.view("agent_angular_velocity")[0, 0].item() == pytest.approx(
        cfg.max_angular_velocity
    )
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(-0.5 * cfg.max_amplitude)
    assert sim.view("agent_sigma")[0, 0].tolist() == pytest.approx(
        [cfg.sigma_min, cfg.sigma_max], abs=1e-6
    )
    # a zero action holds the rates and brings the shape to the middle of its ranges
    for _ in range(60):
        sim.step(torch.zeros_like(action))
    assert sim.view("agent_velocity")[0, 0].tolist() == pytest.approx([cfg.max_velocity, 0.0])
    assert sim.view("agent_amplitude")[0, 0].item() == pytest.approx(0.0, abs=1e-7)
    middle = 0.5 * (cfg.sigma_min + cfg.sigma_max)
    assert sim.view("agent_sigma")[0, 0].tolist() == pytest.approx([middle, middle], abs=1e-6)


def test_actions_beyond_the_unit_box_act_as_their_clipped_values():
    rng = np.random.default_rng(SEED)
    action = torch.as_tensor(rng.uniform(-4.0, 4.0, (4, 2, 8, 6)), dtype=torch.float32)
    assert (action.abs() > 1).float().mean() > 0.5
    raw, clipped = make_sim(), make_sim()
    for a in action:
        raw.step(a)
        clipped.step(a.clamp(-1.0, 1.0))
    for name in read_state(raw):
        torch.testing.assert_close(raw.view(name), clipped.view(name), rtol=0.0, atol=0.0)
    torch.testing.assert_close(
        raw.view("column_height"), clipped.view("column_height"), rtol=0.0, atol=0.0
    )


@pytest.mark.parametrize("wrap_edges", [True, False])
def test_wavelet_leaving_the_grid_wraps_or_stops_at_the_edge(wrap_edges):
    sim = make_sim(num_envs=1, num_agents=2, action_repeat=1, wrap_edges=wrap_edges)
    g = sim.config.grid_size
    # one wavelet leaves through x = 0, the other through y = G
    start = [[[0.05, 7.0], [7.0, g - 0.05]]]
    set_agents(sim, start, [[0.0, 0.0]], [[0.0, 0.0]], [[[1.0, 1.0]] * 2])
    sim.view("agent_velocity").copy_(torch.tensor([[[-1.0, 0.0], [0.0, 1.0]]]))
    sim.step(torch.zeros(sim.action_shape))
    position = sim.view("agent_position")[0].tolist()
    if wrap_edges:
        assert position[0] == pytest.approx([g - 0.05, 7.0], abs=1e-5)
        assert position[1] == pytest.approx([7.0, 0.05], abs=1e-5)
    else:
        assert position[0] == pytest.approx([0.0, 7.0], abs=1e-6)
        assert position[1] == pytest.approx([7.0, g - 1.0], abs=1e-6)
