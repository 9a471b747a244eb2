"""Actuator families: the registry, each family's surface against a NumPy reference, the
sliding surface's physics against closed forms, and every family under extreme actions."""

import math

import numpy as np
import pytest
import torch

from terrashift_rl.sim import (
    ACTUATORS,
    COLUMN_SHAPES,
    ScriptedScene,
    Simulator,
    TerraShiftConfig,
)
from terrashift_rl.sim.actuators import register

SEED = 0
FLOW_TOL = 1e-5
"""Absolute tolerance on surface velocities [m/s]: float32 rounding of a sum of a few
Gaussians times speeds of order 1 m/s."""


def test_the_default_family_is_the_wavelets_and_unknown_names_are_refused():
    assert TerraShiftConfig().actuator == "wavelets"
    with pytest.raises(
        ValueError, match=r"actuator must be one of \('rotors', 'surface_flow', 'wavelets'\)"
    ):
        TerraShiftConfig(actuator="cilia")


def test_every_family_of_the_package_registers_itself_once():
    assert sorted(ACTUATORS) == ["rotors", "surface_flow", "wavelets"]
    rotors = ACTUATORS["rotors"]
    with pytest.raises(ValueError, match="'rotors' is registered already"):
        register(type(rotors))
    assert ACTUATORS["rotors"] is rotors


def test_every_family_keeps_the_agent_layout():
    for name, family in ACTUATORS.items():
        assert family.name == name
        assert family.moves_columns or family.moves_surface
        assert len(family.action_names) == 6


def test_only_a_sliding_family_takes_surface_velocities():
    scene = ScriptedScene(TerraShiftConfig(num_objects=1, num_goals=1))
    with pytest.raises(ValueError, match="does not slide the surface"):
        scene.set_surface_velocity(torch.zeros(2))


# --- the surface of each sliding family against NumPy --------------------------------------


def reference_flow(
    family: str,
    position: np.ndarray,
    angle: np.ndarray,
    amplitude: np.ndarray,
    sigma: np.ndarray,
    cfg: TerraShiftConfig,
) -> np.ndarray:
    """Surface velocity [G(y), G(x), 2] of one environment's patches, in float64."""
    g = cfg.grid_size
    iy, ix = np.meshgrid(np.arange(g, dtype=float), np.arange(g, dtype=float), indexing="ij")
    flow = np.zeros((g, g, 2))
    for (x, y), theta, amp, (sx, sy) in zip(position, angle, amplitude, sigma, strict=True):
        dx, dy = ix - x, iy - y
        if cfg.wrap_edges:
            dx = dx - g * np.floor(dx / g + 0.5)
            dy = dy - g * np.floor(dy / g + 0.5)
        c, s = math.cos(theta), math.sin(theta)
        xr, yr = c * dx + s * dy, -s * dx + c * dy
        weight = amp * np.exp(-0.5 * (xr**2 / sx**2 + yr**2 / sy**2))
        if family == "surface_flow":
            flow += weight[..., None] * np.array([c, s])
        else:  # rotors: z x offset, in metres
            flow += (weight * cfg.cell_size)[..., None] * np.stack([-dy, dx], axis=-1)
    speed = np.linalg.norm(flow, axis=-1, keepdims=True)
    return flow * np.minimum(1.0, cfg.max_surface_speed / np.maximum(speed, 1e-30))


@pytest.mark.parametrize("wrap_edges", [True, False])
@pytest.mark.parametrize("family", ["surface_flow", "rotors"])
def test_surface_velocity_matches_reference(family, wrap_edges):
    cfg = TerraShiftConfig(
        actuator=family, grid_size=7, num_agents=3, num_objects=1, num_goals=1, spawn_margin=1,
        wrap_edges=wrap_edges, max_surface_speed=0.6,
    )  # fmt: skip
    sim = Simulator(cfg, num_envs=2, seed=SEED)
    sim.reset()
    rng = np.random.default_rng(SEED)
    high = ACTUATORS[family].amplitude_limits(cfg)[1]
    state = {
        "agent_position": rng.uniform(0, cfg.grid_size - 1, (2, 3, 2)),
        "agent_angle": rng.uniform(0, 2 * math.pi, (2, 3)),
        "agent_amplitude": rng.uniform(-high, high, (2, 3)),
        "agent_sigma": rng.uniform(cfg.sigma_min, cfg.sigma_max, (2, 3, 2)),
    }
    for name, value in state.items():
        sim.view(name).copy_(torch.as_tensor(value, dtype=torch.float32))
    sim.view("agent_velocity").zero_()
    sim.view("agent_angular_velocity").zero_()
    sim.step(torch.zeros(sim.action_shape))  # zero rates and actions: the patches stay put
    flow = sim.view("surface_velocity").double().numpy()
    assert np.abs(flow).max() > 0.1  # a surface that moves
    assert (np.linalg.norm(flow, axis=-1) <= cfg.max_surface_speed + 1e-6).all()
    for e in range(2):
        expected = reference_flow(
            family, *(sim.view(n)[e].double().numpy() for n in state), cfg=cfg
        )
        np.testing.assert_allclose(flow[e], expected, atol=FLOW_TOL, rtol=0)
    assert (sim.view("column_height") == 0).all()  # the columns stay at rest


# --- a sphere on a sliding surface ----------------------------------------------------------


def flow_scene(shape: str = "box", **overrides) -> ScriptedScene:
    cfg = TerraShiftConfig(
        actuator="surface_flow", column_shape=shape, num_objects=1, num_goals=1, **overrides
    )
    return ScriptedScene(cfg)


def resting_height(cfg: TerraShiftConfig) -> float:
    """Centre height [m] of a sphere resting on flat box tops: the static sag m g / k below
    touching."""
    sag = cfg.sphere_mass * cfg.gravity / cfg.contact_stiffness
    return cfg.column_rest_top + cfg.sphere_radius - sag


def energy(sc: ScriptedScene) -> float:
    """Kinetic (translation + rotation) energy of the sphere [J]."""
    cfg = sc.config
    inertia = 0.4 * cfg.sphere_mass * cfg.sphere_radius**2
    v, w = sc.sphere_velocity[0, 0], sc.sphere_angular_velocity[0, 0]
    return (0.5 * cfg.sphere_mass * v.dot(v) + 0.5 * inertia * w.dot(w)).item()


@pytest.mark.parametrize(("shape", "u"), [("box", 0.3), ("smooth", -0.8)])
def test_sphere_put_on_a_sliding_surface_slips_then_rolls_at_two_sevenths(shape, u):
    """A solid sphere at rest on a surface sliding at u along x: kinetic friction mu m g
    accelerates it (v = mu g t) and spins it backwards until its contact point moves with the
    surface, at t* = 2u / (7 mu g); from then on it rolls at v = 2u/7 with omega_y = -5u / (7r),
    the contact point riding the surface. The surface's work (u times the sphere's momentum)
    is twice the kinetic energy it ends with: half is lost to slip. On box tops the sphere
    stays within one top (the seams between flush tops are edges that bump a passing sphere);
    the smooth surface is one plane."""
    mu = 0.1
    sc = flow_scene(shape, friction=mu, linear_damping=0.0, count_surface_work=True)
    cfg = sc.config
    x0 = 0.0  # the centre of a column
    sc.place_spheres(torch.tensor([[x0, x0, resting_height(cfg)]]))
    sc.set_surface_velocity(torch.tensor([u, 0.0]))
    slip_time = 2 * abs(u) / (7 * mu * cfg.gravity)
    times, speeds, energies, works = [], [], [], []
    while sc.time < 2.0 * slip_time:
        sc.step()
        v = sc.sphere_velocity[0, 0]
        times.append(sc.time)
        speeds.append(v[0].item())
        energies.append(energy(sc))
        works.append(u * cfg.sphere_mass * v[0].item())
        counted = sc.sim.view("surface_work")[0, 0].item()
        assert counted == pytest.approx(works[-1], rel=0.01, abs=1e-6)
    times, speeds = np.array(times), np.array(speeds)
    slipping = times < 0.9 * slip_time
    acceleration = np.polyfit(times[slipping], speeds[slipping], 1)[0]
    assert acceleration == pytest.approx(np.sign(u) * mu * cfg.gravity, rel=0.02)
    rolling = times > 1.1 * slip_time
    np.testing.assert_allclose(speeds[rolling], 2 * u / 7, rtol=0.01)
    w = sc.sphere_angular_velocity[0, 0]
    assert w[1].item() == pytest.approx(-5 * u / (7 * cfg.sphere_radius), rel=0.01)
    assert abs(sc.sphere_velocity[0, 0, 1].item()) < 1e-4  # nothing across the flow
    # energy never above the surface's work; half of it kept
    assert (np.array(energies) <= np.array(works) + 1e-7).all()
    assert energies[-1] == pytest.approx(0.5 * works[-1], rel=0.02)
    assert energies[-1] == pytest.approx(cfg.sphere_mass * u**2 / 7, rel=0.02)


@pytest.mark.parametrize(
    ("shape", "u", "v0", "spin"),
    [("box", 1.0, 0.0, -1.0 / 0.075), ("smooth", -0.4, 0.3, 0.0), ("smooth", 0.5, 0.0, 4.0)],
)
def test_a_sphere_on_a_sliding_surface_ends_rolling_at_two_u_plus_five_c_over_seven(
    shape, u, v0, spin
):
    """Friction acts at the contact point, so on a flat top it leaves C = v + (2/5) r (w x z),
    the angular momentum about the contact point over m r, as it was: once its slip has
    stopped, a sphere rolls at v = (2u + 5C)/7 on a surface sliding at u, whatever it did
    before (2u/7 from rest). A sphere that spins in place (w_y = -u/r: C = -2u/5, the first
    case) stays where it is: a steady flow exerts no force on a rolling sphere. The other two:
    thrown against the flow, and spun forwards from rest."""
    sc = flow_scene(shape, linear_damping=0.0)
    cfg = sc.config
    sc.place_spheres(
        torch.tensor([[0.0, 0.0, resting_height(cfg)]]),
        velocities=torch.tensor([[v0, 0.0, 0.0]]),
        angular_velocities=torch.tensor([[0.0, spin, 0.0]]),
    )
    sc.set_surface_velocity(torch.tensor([u, 0.0]))
    stored = v0 + 0.4 * cfg.sphere_radius * spin
    rolling = (2 * u + 5 * stored) / 7
    sc.step(30)  # the slip ends within 0.05 s at mu = 0.7
    start = sc.sphere_position[0, 0, 0].item()
    for _ in range(10):
        sc.step()
        v = sc.sphere_velocity[0, 0]
        assert v[0].item() == pytest.approx(rolling, rel=0.01, abs=2e-3)
        assert abs(v[1].item()) < 1e-4
        w = sc.sphere_angular_velocity[0, 0]  # the contact point rides the surface
        assert v[0].item() - cfg.sphere_radius * w[1].item() == pytest.approx(u, abs=2e-3)
    travelled = sc.sphere_position[0, 0, 0].item() - start
    assert travelled == pytest.approx(rolling * 10 * cfg.tick_dt, abs=5e-4)


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
def test_a_rolling_sphere_on_a_stopped_surface_never_gains_energy(shape):
    """Without input (the surface stopped) a sphere thrown spinning onto it never has more
    kinetic and gravitational energy than at the start, in the air (contacts store some as
    spring energy while they last), and ends with less."""
    sc = flow_scene(shape)
    cfg = sc.config
    sc.place_spheres(
        torch.tensor([[0.0, 0.0, resting_height(cfg) + 0.01]]),
        velocities=torch.tensor([[0.4, -0.2, 0.0]]),
        angular_velocities=torch.tensor([[3.0, 8.0, -5.0]]),
    )
    sc.set_surface_velocity(torch.zeros(2))
    totals = []
    for _ in range(61):
        weight = cfg.sphere_mass * cfg.gravity * sc.sphere_position[0, 0, 2].item()
        totals.append(energy(sc) + weight)
        sc.step()
    assert max(totals) <= totals[0] + 1e-4
    assert totals[-1] < totals[0]


def test_sphere_on_a_turntable_circles_at_two_sevenths_of_its_spin():
    """A sphere rolling on a flat surface turning at Omega about the origin: its velocity
    turns at 2 Omega / 7 at constant speed (the classic ball on a turntable), so it rolls on a
    circle rather than being flung off. The smooth surface interpolates the columns' velocities
    bilinearly, which is exact for a rotation."""
    spin = 3.0
    sc = flow_scene("smooth", linear_damping=0.0)
    cfg = sc.config
    centres = (np.arange(cfg.grid_size) - 0.5 * (cfg.grid_size - 1)) * cfg.cell_size
    y, x = np.meshgrid(centres, centres, indexing="ij")
    sc.set_surface_velocity(torch.tensor(np.stack([-spin * y, spin * x], -1), dtype=torch.float32))
    sc.place_spheres(torch.tensor([[0.1, 0.0, resting_height(cfg)]]))
    sc.step(12)  # the slip phase: under 0.1 s at mu = 0.7
    headings, speeds = [], []
    for _ in range(60):
        sc.step()
        v = sc.sphere_velocity[0, 0].double().numpy()
        headings.append(math.atan2(v[1], v[0]))
        speeds.append(math.hypot(v[0], v[1]))
    turn = np.unwrap(headings)
    rate = np.polyfit(np.arange(len(turn)) * cfg.tick_dt, turn, 1)[0]
    assert rate == pytest.approx(2 * spin / 7, rel=0.02)
    assert np.ptp(speeds) < 0.02 * np.mean(speeds)
    assert np.mean(speeds) > 0.01


# --- every family, every column shape ------------------------------------------------------


@pytest.mark.parametrize("shape", COLUMN_SHAPES)
@pytest.mark.parametrize("family", sorted(ACTUATORS))
def test_extreme_actions_keep_every_family_finite(family, shape):
    """Actions far outside [-1, 1] (clipped) and alternating full swings, 40 decisions."""
    cfg = TerraShiftConfig(actuator=family, column_shape=shape, max_episode_steps=20)
    sim = Simulator(cfg, num_envs=3, seed=SEED)
    sim.reset()
    generator = torch.Generator().manual_seed(SEED)
    for decision in range(40):
        action = torch.randn(sim.action_shape, generator=generator) * 1e6
        if decision % 2:
            action = torch.full(sim.action_shape, (-1.0) ** (decision // 2) * 1e30)
        sim.step(action)
        sim.reset(sim.view("truncated") | sim.view("terminated"))
        for name in ("sphere_position", "sphere_velocity", "agent_features", "heightmap"):
            assert torch.isfinite(sim.view(name)).all(), (name, decision)
        assert sim.view("agent_features").abs().max() <= 1.0 + 1e-6
        if ACTUATORS[family].moves_surface:
            speed = sim.view("surface_velocity").norm(dim=-1)
            assert speed.max() <= cfg.max_surface_speed + 1e-5
            assert speed.max() > 0.0
    assert sim.view("sphere_active").any()


def test_a_lifted_sphere_costs_the_columns_at_least_its_rise():
    """Box columns under a resting sphere rise 5 cm in one tick and hold: the positive work
    the columns did is at least the potential energy of the throw's peak over the start
    (the rest went into the contact's dashpot); columns at rest do none."""
    cfg = TerraShiftConfig(column_shape="box", num_objects=1, num_goals=1, count_surface_work=True)
    sc = ScriptedScene(cfg)
    sc.place_spheres(torch.tensor([[0.0, 0.0, resting_height(cfg)]]))
    sc.step(30)
    assert sc.sim.view("surface_work").item() < 1e-6
    start = sc.sphere_position[0, 0, 2].item()
    sc.set_column_heights(0.05)
    peak = start
    for _ in range(60):
        sc.step()
        peak = max(peak, sc.sphere_position[0, 0, 2].item())
    work = sc.sim.view("surface_work").item()
    assert peak > start + 0.1  # thrown well above the raised tops
    assert (
        cfg.sphere_mass * cfg.gravity * (peak - start)
        <= work
        < 3 * cfg.sphere_mass * cfg.gravity * (peak - start)
    )


@pytest.mark.parametrize("family", ["surface_flow", "rotors"])
def test_both_ways_of_launching_the_substeps_agree(family):
    """A tick's substeps in one launch or a launch each: the same sliding-surface physics and
    work count (the recorded trajectory checks this for the wavelets)."""
    cfg = TerraShiftConfig(actuator=family, column_shape="box", count_surface_work=True)
    sims = [Simulator(cfg, num_envs=2, seed=SEED, fuse_substeps=fused) for fused in (True, False)]
    generator = torch.Generator().manual_seed(SEED)
    actions = torch.rand(8, *sims[0].action_shape, generator=generator) * 2 - 1
    for sim in sims:
        sim.reset()
        for action in actions:
            sim.step(action)
    assert sims[0].view("surface_work").sum() > 0
    for name in ("sphere_position", "sphere_velocity", "surface_velocity", "surface_work"):
        torch.testing.assert_close(sims[0].view(name), sims[1].view(name), rtol=0, atol=1e-5)
