"""Every reward term is declared task or shaping, and the declaration matches the config and the
reward kernel."""

import ast
import dataclasses
import inspect

from terrashift_rl.sim import REWARD_TERMS, TerraShiftConfig, events

TASK = {"goal_reward", "out_of_bounds_penalty", "distance_scale", "slow_penalty", "time_penalty"}
"""The benchmark's reward terms, written out: a change here is a decision to review."""
SHAPING = {"potential_scale", "alignment_scale", "approach_scale", "sphere_approach_scale"}
"""The training aids that evaluation switches off."""


def model_field(node: ast.expr) -> str | None:
    """The ``model.<field>`` that scales a summand: the summand itself or its leftmost factor."""
    while isinstance(node, ast.BinOp):
        node = node.left
    if isinstance(node, ast.Attribute) and getattr(node.value, "id", None) == "model":
        return node.attr
    return None


def kernel_terms() -> set[str]:
    """The model fields the tick's reward is built from: each ``total += model.<term> ...``,
    and ``model.<term> + total``, the per-tick term added once per environment."""
    tree = ast.parse(inspect.getsource(events))
    kernel = next(
        node
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef) and node.name == "tick_events"
    )
    terms = set()
    for node in ast.walk(kernel):
        if isinstance(node, ast.AugAssign) and getattr(node.target, "id", None) == "total":
            terms.add(model_field(node.value))
        elif isinstance(node, ast.BinOp) and getattr(node.right, "id", None) == "total":
            terms.add(model_field(node.left))
    return terms


def test_every_reward_term_is_declared_task_or_shaping():
    assert {name for name, role in REWARD_TERMS.items() if role == "task"} == TASK
    assert {name for name, role in REWARD_TERMS.items() if role == "shaping"} == SHAPING
    assert set(REWARD_TERMS) == TASK | SHAPING


def test_the_config_has_no_undeclared_reward_term():
    fields = {f.name for f in dataclasses.fields(TerraShiftConfig)}
    named_as_terms = {f for f in fields if f.endswith(("_scale", "_reward", "_penalty"))}
    assert named_as_terms == set(REWARD_TERMS)


def test_the_reward_kernel_uses_exactly_the_declared_terms():
    assert kernel_terms() == set(REWARD_TERMS)


def test_without_shaping_turns_every_shaping_term_off_and_keeps_the_rest():
    scene = TerraShiftConfig(
        **{name: 0.25 * (i + 1) for i, name in enumerate(sorted(TASK | SHAPING))},
        potential_gamma=0.9,
    )
    assert scene.without_shaping() == scene.replace(**dict.fromkeys(SHAPING, 0.0))
