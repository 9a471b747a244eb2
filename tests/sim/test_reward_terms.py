"""Every reward term is declared task or shaping, and the declaration matches the config and the
reward kernel."""

import ast
import dataclasses
import inspect

from terrashift_rl.sim import REWARD_TERMS, TerraShiftConfig, events

ROLES = {
    "goal_reward": "task",
    "out_of_bounds_penalty": "task",
    "distance_scale": "task",
    "slow_penalty": "task",
    "time_penalty": "task",
    "potential_scale": "shaping",
    "alignment_scale": "shaping",
    "approach_scale": "shaping",
    "sphere_approach_scale": "shaping",
}
"""The reward terms and their roles, written out: a change to either is a decision to review."""


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
    assert REWARD_TERMS == ROLES
    assert set(REWARD_TERMS.values()) == {"task", "shaping"}


def test_the_config_has_no_undeclared_reward_term():
    fields = {f.name for f in dataclasses.fields(TerraShiftConfig)}
    named_as_terms = {f for f in fields if f.endswith(("_scale", "_reward", "_penalty"))}
    assert named_as_terms == set(REWARD_TERMS)


def test_the_reward_kernel_uses_exactly_the_declared_terms():
    assert kernel_terms() == set(REWARD_TERMS)


def test_without_shaping_turns_every_shaping_term_off_and_keeps_the_rest():
    scene = TerraShiftConfig(
        **{name: 0.25 * (i + 1) for i, name in enumerate(ROLES)}, potential_gamma=0.9
    )
    shaping_off = {name: 0.0 for name, role in ROLES.items() if role == "shaping"}
    assert scene.without_shaping() == scene.replace(**shaping_off)
