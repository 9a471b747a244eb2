"""Actuator families: what the agents control and what it does to the surface.

``ACTUATORS`` maps each family's name (``TerraShiftConfig.actuator``) to it; the seam a family
implements is :class:`Actuator`, and its module registers it (:func:`register`).
docs/actuators.md says how to add one.

Example:
    >>> sorted(ACTUATORS)
    ['rotors', 'surface_flow', 'wavelets']
    >>> ACTUATORS["surface_flow"].moves_columns, ACTUATORS["surface_flow"].moves_surface
    (False, True)
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import TYPE_CHECKING

from terrashift_rl.sim.actuators.base import ACTUATORS, Actuator, register

if TYPE_CHECKING:
    from terrashift_rl.sim.config import TerraShiftConfig

# every module of this package, so that each family in it registers itself
for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")


def actuator_for(config: TerraShiftConfig) -> Actuator:
    """The family a (validated) config names."""
    return ACTUATORS[config.actuator]


__all__ = ["ACTUATORS", "Actuator", "actuator_for", "register"]
