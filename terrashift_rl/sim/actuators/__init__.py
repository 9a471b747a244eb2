"""Actuator families: what the agents control and what it does to the surface.

``ACTUATORS`` maps each family's name (``TerraShiftConfig.actuator``) to it; the seam a family
implements is :class:`Actuator` (docs/actuators.md says how to add one).

Example:
    >>> sorted(ACTUATORS)
    ['rotors', 'surface_flow', 'wavelets']
    >>> ACTUATORS["surface_flow"].moves_columns, ACTUATORS["surface_flow"].moves_surface
    (False, True)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from terrashift_rl.sim.actuators.base import Actuator
from terrashift_rl.sim.actuators.rotors import Rotors
from terrashift_rl.sim.actuators.surface_flow import SurfaceFlow
from terrashift_rl.sim.actuators.wavelets import Wavelets

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig

ACTUATORS: dict[str, Actuator] = {
    family.name: family for family in (Wavelets(), SurfaceFlow(), Rotors())
}
"""Every actuator family, by name (the names are the config's ``ACTUATOR_FAMILIES``)."""


def actuator_for(config: TerraShiftConfig) -> Actuator:
    """The family a (validated) config names."""
    return ACTUATORS[config.actuator]


__all__ = ["ACTUATORS", "Actuator", "actuator_for"]
