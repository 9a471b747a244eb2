"""TerraShiftConfig: presets, validation messages, Hydra structured-config use."""

import dataclasses

import pytest
from omegaconf import OmegaConf

from terrashift_rl.sim import Simulator, TerraShiftConfig


def test_presets_hold_the_paper_settings():
    pretrain = TerraShiftConfig.preset("pretrain")
    assert (pretrain.grid_size, pretrain.num_agents, pretrain.num_objects) == (15, 8, 4)
    assert pretrain.physics_hz == 60 and pretrain.action_repeat == 2
    assert pretrain.max_episode_steps == 512
    finetune = TerraShiftConfig.preset("finetune")
    assert (finetune.grid_size, finetune.num_agents, finetune.num_objects) == (30, 16, 4)
    assert finetune.time_penalty == 0.0
    assert TerraShiftConfig.preset("finetune", grid_size=20).grid_size == 20
    with pytest.raises(ValueError, match="unknown preset"):
        TerraShiftConfig.preset("huge")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"grid_size": 1}, "grid_size must be an integer >= 2"),
        ({"num_agents": 0}, "num_agents must be an integer >= 1"),
        ({"num_objects": 0}, "num_objects"),
        ({"sigma_min": 3.0}, r"sigma_min \(3.0\) must be <= sigma_max"),
        ({"column_shape": "cone"}, "column_shape must be one of"),
        ({"action_mode": "force"}, "action_mode must be one of"),
        ({"position_gain": 0.0}, "position_gain must be in"),
        ({"restitution": 0.0}, "restitution must be in"),
        ({"friction": -0.1}, "friction must be in"),
        ({"sphere_radius": float("nan")}, "sphere_radius must be a finite number"),
        ({"num_objects": 40, "num_goals": 4}, "exceeds the .* spawn places"),
        ({"num_goals": 5}, r"num_goals \(5\) must be <= num_objects"),
        ({"spawn_margin": 8}, "spawn_margin"),
        ({"max_column_height": 0.2}, "column_rest_top"),
        ({"substeps": 2.5}, "substeps must be an integer"),
        ({"wrap_edges": "no"}, "wrap_edges must be true or false, got 'no'"),
        ({"respawn": "false"}, "respawn must be true or false, got 'false'"),
        (
            {"observe_objects": True, "privileged_objects": True},
            "privileged_objects=true hands out the object sequence that observe_objects=true",
        ),
        ({"respawn_fraction": 1.5}, r"respawn_fraction must be in \[0.0, 1.0\], got 1.5"),
        ({"sigma_max": "wide"}, "sigma_max must be a finite number, got 'wide'"),
        ({"approach_radius": -1.0}, "approach_radius must be in"),
        ({"min_amplitude_ratio": -1.5}, r"min_amplitude_ratio must be in \[-1.0, 1.0\], got -1.5"),
        ({"approach_scale": float("inf")}, "approach_scale must be a finite number"),
        ({"sphere_approach_scale": float("nan")}, "sphere_approach_scale must be a finite number"),
    ],
)
def test_validation_names_the_field(overrides, message):
    with pytest.raises(ValueError, match=message):
        TerraShiftConfig(**overrides)


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(TerraShiftConfig)])
def test_a_value_of_the_wrong_type_is_refused_by_name(field):
    with pytest.raises(ValueError, match=f"^{field} .*got 'junk'"):
        TerraShiftConfig(**{field: "junk"})


def test_replace_rejects_unknown_fields():
    with pytest.raises(ValueError, match=r"unknown TerraShiftConfig field\(s\) \['grid'\]"):
        TerraShiftConfig().replace(grid=3)


def test_integration_limits_raise_at_build():
    with pytest.raises(ValueError, match="too stiff"):
        Simulator(TerraShiftConfig(contact_stiffness=1e6))
    with pytest.raises(ValueError, match="out of reach"):
        Simulator(TerraShiftConfig(restitution=0.02, substeps=4))


def test_usable_as_hydra_structured_config():
    schema = OmegaConf.structured(TerraShiftConfig)
    merged = OmegaConf.merge(schema, OmegaConf.create({"grid_size": 20, "column_shape": "box"}))
    config = TerraShiftConfig(**OmegaConf.to_container(merged))
    assert config.grid_size == 20 and config.column_shape == "box"
    assert {f.name for f in dataclasses.fields(config)} == set(schema.keys())


def test_the_large_preset_holds_eight_spheres_and_goals_on_45_columns():
    large = TerraShiftConfig.preset("large")
    assert (large.grid_size, large.num_agents, large.num_objects, large.num_goals) == (45, 24, 8, 8)
    assert large.platform_size == TerraShiftConfig().platform_size
    with pytest.raises(ValueError, match="exceeds the .* spawn places"):
        large.replace(num_objects=20, num_goals=20)
