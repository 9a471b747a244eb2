"""The actuator seam: what an actuator family owns and when the simulator calls it.

A family is everything the agents control: its constants in the
:class:`~terrashift_rl.sim.types.Model`, its state arrays in the
:class:`~terrashift_rl.sim.types.Data`, how an action changes that state, what the surface
then does to the spheres, the per-agent observation features and the random start of an
episode. The rest of a scene (the spheres' contacts, goals, reward, the heightmap and the
object observations) is the same for every family, so families are compared on one task.

A family acts on the spheres through the surface only, in one or both of two ways:

* **column heights** (``moves_columns``): it writes ``column_height`` (and ``column_height_prev``);
  the columns move between the two over a tick and their vertical velocity enters every contact;
* **an in-plane surface velocity** (``moves_surface``): it writes ``surface_velocity``, the
  velocity [m/s] with which each column's surface slides along itself; the contacts' friction
  drags the spheres with it.

The sphere kernels are compiled for the family's choice
(:func:`~terrashift_rl.sim.physics.sphere_kernels`), so a family that does not slide the
surface pays nothing for the possibility.

Every family keeps the task template's agent layout: an action of
:data:`~terrashift_rl.sim.types.ACTION_DIM` values in [-1, 1] and an observation of
:data:`~terrashift_rl.sim.types.AGENT_FEATURES` values in [-1, 1] per agent, so environments,
networks and recipes take any family unchanged.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar, TypeVar

if TYPE_CHECKING:
    import warp as wp

    from terrashift_rl.sim.config import TerraShiftConfig
    from terrashift_rl.sim.simulator import Simulator
    from terrashift_rl.sim.types import Data, Model


class Actuator:
    """One actuator family behind the simulator's seam.

    Subclasses set the class attributes and implement every method; each ``launch_*`` method
    only launches Warp kernels (it may be captured in a CUDA graph), reading ``sim.model``,
    ``sim.data`` and ``sim.config``. A family is used once :func:`register` has put it in
    :data:`ACTUATORS`.
    """

    name: ClassVar[str]
    """Registry name, the value of ``TerraShiftConfig.actuator``."""
    moves_columns: ClassVar[bool]
    """Whether the family sets column heights."""
    moves_surface: ClassVar[bool]
    """Whether the family sets an in-plane surface velocity."""
    action_names: ClassVar[tuple[str, ...]]
    """What each of an agent's action dims changes or sets, in order."""
    scratch: ClassVar[tuple[str, ...]] = ()
    """Names of its data arrays that every step and reset writes before reading (not state)."""

    def configure(self, model: Model, config: TerraShiftConfig) -> None:
        """Writes the family's constants into ``model``."""
        raise NotImplementedError

    def allocate(self, data: Data, config: TerraShiftConfig, device: wp.context.Device) -> None:
        """Adds the family's state arrays to ``data`` (leading dimension ``data.num_envs``)."""
        raise NotImplementedError

    def load(self, device: wp.context.Device) -> None:
        """Loads (compiling unless cached) the Warp modules of every kernel the family
        launches, and no others: the simulator calls it when built, before a step can be
        captured in a CUDA graph."""
        raise NotImplementedError

    def launch_reset(self, sim: Simulator) -> None:
        """Draws a random start where ``reset_mask`` is set, from each environment's ``rng``
        (before the goals are drawn)."""
        raise NotImplementedError

    def launch_update(self, sim: Simulator) -> None:
        """Applies one physics tick of the current ``action`` to the family's state."""
        raise NotImplementedError

    def launch_surface(self, sim: Simulator, *, reset: bool) -> None:
        """Writes what the surface does over the next tick: column heights and/or surface
        velocity. After a step's update (``reset`` False) in every environment, the columns
        moving from the previous heights; after a reset (True) only where ``reset_mask`` is
        set, the columns at rest."""
        raise NotImplementedError

    def launch_observe(self, sim: Simulator) -> None:
        """Writes ``agent_features`` [num_envs, K, AGENT_FEATURES] in [-1, 1]."""
        raise NotImplementedError


ACTUATORS: dict[str, Actuator] = {}
"""Every registered actuator family, by name (:func:`register`)."""

Family = TypeVar("Family", bound=type[Actuator])


def register(family: Family) -> Family:
    """Class decorator that registers an instance of ``family`` in :data:`ACTUATORS` under its
    ``name``, which ``TerraShiftConfig.actuator`` then accepts: a family's module registers it,
    wherever that module lives, once imported."""
    if family.name in ACTUATORS:
        raise ValueError(
            f"an actuator family named {family.name!r} is registered already "
            f"({type(ACTUATORS[family.name]).__qualname__})"
        )
    ACTUATORS[family.name] = family()
    return family
