"""Headless rendering of TerraShift scenes: frames, videos and recorded rollouts.

Three modules, one job each: :mod:`~terrashift_rl.envs.render.scene` (camera and polygons),
:mod:`~terrashift_rl.envs.render.figure` (the frame's layout) and
:mod:`~terrashift_rl.envs.render.video` (recording and writing videos).

A frame is drawn with Matplotlib's Agg backend on a private :class:`~matplotlib.figure.Figure`
(no display, no OpenGL context, no pyplot state). Its left half is a perspective view of one
environment: this module projects the columns, spheres and goals with its own pinhole camera
and draws them far to near (painter's algorithm) as one polygon collection, which keeps a frame
of the 15 x 15 grid well under a tenth of a second on a CPU. Its right half is the heightmap
observation with a colorbar.

Colours: columns by wave height (``cividis``, from ``-max_column_height`` to
``+max_column_height``), shaded by a fixed light; sphere ``j`` and goal ``j % num_goals`` share
the ``tab10`` colour of that goal; goals are translucent spheres of radius ``goal_radius``
(the region where a sphere centre scores).

Example:
    >>> from terrashift_rl.sim import Simulator
    >>> sim = Simulator(num_envs=1, seed=0)
    >>> sim.reset()
    >>> renderer = Renderer(sim.config, width=480, height=240)
    >>> renderer.frame(sim).shape
    (240, 480, 3)
"""

from terrashift_rl.envs.render.figure import Renderer, render_frame
from terrashift_rl.envs.render.scene import COLUMN_CMAP, GOAL_COLORS, HEIGHTMAP_CMAP
from terrashift_rl.envs.render.video import record_rollout, save_video

__all__ = [
    "COLUMN_CMAP",
    "GOAL_COLORS",
    "HEIGHTMAP_CMAP",
    "Renderer",
    "record_rollout",
    "render_frame",
    "save_video",
]
