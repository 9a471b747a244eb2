"""A recorded trajectory of the pretraining scene, which the simulator must reproduce.

Four environments of the default scene take 64 decisions of seeded uniform random actions
from a seeded reset; ``tests/sim/data/pretrain_trajectory.npz`` holds what they did. Record it
again (``python tests/sim/test_trajectory.py``) only with a change meant to alter the
simulation, never to make a speed-up pass.

The scene is chaotic: a 1e-7 m nudge to the spheres grows about threefold every four decisions
(to 1e-5 m after 20). A free run of 64 decisions would therefore fail on any change of float
round-off, a reordered sum or a fused multiply-add, however correct. So the recording keeps the
whole state at the start of every segment of ``SEGMENT`` decisions, and each segment is
replayed from its own start: round-off then grows over at most ``SEGMENT`` decisions. The
same tolerances hold both ways of launching the substeps and, on a GPU, the CUDA kernels to
this CPU recording.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

from terrashift_rl.sim import Simulator, TerraShiftConfig

DATA = Path(__file__).parent / "data" / "pretrain_trajectory.npz"
NUM_ENVS = 4
DECISIONS = 64
SEGMENT = 8
SEED = 33
OBSERVED = (
    "sphere_position",
    "sphere_velocity",
    "sphere_angular_velocity",
    "sphere_active",
    "reward",
)
"""Arrays compared after every decision."""
FIELDS = ("column_height", "heightmap")
"""The large arrays, compared after the first decision of each segment."""

TOLERANCES = {
    "sphere_position": 1e-5,
    "sphere_velocity": 3e-4,
    "sphere_angular_velocity": 3e-3,
    "sphere_active": 0,
    "reward": 1e-4,
    "column_height": 1e-6,
    "heightmap": 1e-4,
}
"""Absolute tolerances [m, m/s, rad/s, reward, m, normalised height]: float32 round-off grown
over a segment, with a margin of 10 or more. Emulated round-off, a relative kick of up to 1e-7
to every sphere state and column height before every decision, moved them by at most 5e-7 m,
1.4e-5 m/s, 8e-5 rad/s (slipping contacts turn small differences of slip into spin), 6e-6
(distances times distance_scale = 100) and 3e-6 (a ray grazing a sphere's rim sees a small
shift of the sphere as a large change of height); kicks ten times larger stay within the
tolerances too. Column heights hold no chaos, only the round-off of the wavelet sums (as in
test_wave)."""


def new_simulator(**options) -> Simulator:
    return Simulator(TerraShiftConfig(), num_envs=NUM_ENVS, seed=SEED, **options)


def snapshot(sim: Simulator, names) -> dict[str, np.ndarray]:
    return {name: sim.view(name).cpu().numpy().copy() for name in names}


def record() -> dict[str, np.ndarray]:
    """Runs the trajectory: the recorded arrays, keyed as stored."""
    sim = new_simulator()
    sim.reset()
    rng = np.random.default_rng(SEED)
    actions = rng.uniform(-1.0, 1.0, (DECISIONS, *sim.action_shape)).astype(np.float32)
    states, observed, fields = [], [], []
    for decision in range(DECISIONS):
        if decision % SEGMENT == 0:
            states.append({k: v.numpy().copy() for k, v in sim.state_dict().items()})
        sim.step(torch.from_numpy(actions[decision]))
        observed.append(snapshot(sim, OBSERVED))
        if decision % SEGMENT == 0:
            fields.append(snapshot(sim, FIELDS))
    data = {"action": actions}
    data |= {f"state/{k}": np.stack([s[k] for s in states]) for k in states[0] if k != "heightmap"}
    data |= {name: np.stack([o[name] for o in observed]) for name in OBSERVED}
    data |= {name: np.stack([f[name] for f in fields]) for name in FIELDS}
    return data


def replay(data: dict[str, np.ndarray], segment: int, **options) -> dict[str, np.ndarray]:
    """Replays one segment from its recorded start: the same arrays for its decisions.
    ``options`` go to the :class:`Simulator` (device, fuse_substeps)."""
    sim = new_simulator(**options)
    state = sim.state_dict()
    for name in state:
        if f"state/{name}" in data:
            state[name] = torch.from_numpy(data[f"state/{name}"][segment])
    sim.load_state_dict(state)
    observed, fields = [], {}
    for decision in range(segment * SEGMENT, (segment + 1) * SEGMENT):
        sim.step(torch.from_numpy(data["action"][decision]).to(sim.torch_device))
        observed.append(snapshot(sim, OBSERVED))
        if decision % SEGMENT == 0:
            fields = snapshot(sim, FIELDS)
    return {name: np.stack([o[name] for o in observed]) for name in OBSERVED} | fields


@pytest.fixture(scope="module")
def recorded() -> dict[str, np.ndarray]:
    with np.load(DATA) as file:
        return dict(file)


def test_the_recording_is_a_lively_scene(recorded):
    """The trajectory exercises what it should: spheres spawn, move fast, leave the
    platform, and the columns move."""
    active = recorded["sphere_active"]
    assert active[0].sum() < active[-1].sum()  # staggered spawns
    assert (np.diff(active.astype(int), axis=0) < 0).any()  # resolved spheres
    speed = np.linalg.norm(recorded["sphere_velocity"], axis=-1)
    assert speed.max() > 0.5
    assert np.ptp(recorded["column_height"], axis=0).max() > 0.05  # the columns move


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
@pytest.mark.parametrize("fuse_substeps", [True, False], ids=["fused", "per_substep"])
@pytest.mark.parametrize("segment", range(DECISIONS // SEGMENT))
def test_replay_matches_the_recorded_trajectory(recorded, segment, fuse_substeps, device):
    replayed = replay(recorded, segment, device=device, fuse_substeps=fuse_substeps)
    decisions = slice(segment * SEGMENT, (segment + 1) * SEGMENT)
    for name in OBSERVED:
        np.testing.assert_allclose(
            replayed[name], recorded[name][decisions], rtol=0, atol=TOLERANCES[name], err_msg=name
        )
    for name in FIELDS:
        np.testing.assert_allclose(
            replayed[name], recorded[name][segment], rtol=0, atol=TOLERANCES[name], err_msg=name
        )


if __name__ == "__main__":
    DATA.parent.mkdir(exist_ok=True)
    np.savez_compressed(DATA, **record())
    print(f"wrote {DATA} ({DATA.stat().st_size / 1024:.0f} KiB)")
