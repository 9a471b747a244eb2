"""Headless rendering of TerraShift scenes: frames, videos and recorded rollouts.

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

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from PIL import Image
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from tqdm import tqdm

from terrashift_rl.sim import Simulator, TerraShiftConfig

__all__ = ["Renderer", "record_rollout", "render_frame", "save_video"]

COLUMN_CMAP = "cividis"
"""Colormap of the columns, over wave heights in [-max_column_height, max_column_height]."""
HEIGHTMAP_CMAP = "viridis"
"""Colormap of the heightmap observation, over [-1, 1]."""
GOAL_COLORS = colormaps["tab10"].colors
"""Colour of goal ``g`` (and of every sphere assigned to it): ``GOAL_COLORS[g % 10]``."""

_LIGHT = np.array([-0.35, -0.5, 1.0]) / np.linalg.norm([-0.35, -0.5, 1.0])
_AMBIENT, _DIFFUSE = 0.45, 0.55
_CIRCLE = np.stack(
    [
        np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
        np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
    ],
    axis=-1,
)
_PLATFORM_THICKNESS = 0.03  # [m], drawn below z = 0
_BACKGROUND = "#f4f4f2"


class _Camera:
    """Pinhole camera looking at ``target`` from ``distance`` along (elevation, azimuth)."""

    def __init__(self, target: np.ndarray, *, elevation: float, azimuth: float, distance: float):
        el, az = math.radians(elevation), math.radians(azimuth)
        back = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        self.eye = target + distance * back
        self.forward = -back
        right = np.cross(self.forward, [0.0, 0.0, 1.0])
        self.right = right / np.linalg.norm(right)
        self.up = np.cross(self.right, self.forward)

    def depth(self, points: np.ndarray) -> np.ndarray:
        """Distance along the view axis of points [..., 3]."""
        return (points - self.eye) @ self.forward

    def project(self, points: np.ndarray) -> np.ndarray:
        """Image-plane coordinates [..., 2] of points [..., 3] (focal length 1)."""
        d = points - self.eye
        depth = d @ self.forward
        return np.stack([d @ self.right / depth, d @ self.up / depth], axis=-1)


class _Scene:
    """Static geometry of one config: the camera, the columns' faces and the platform."""

    def __init__(self, config: TerraShiftConfig, *, elevation: float, azimuth: float):
        self.config = dataclasses.replace(config)
        g, cell = config.grid_size, config.cell_size
        half = 0.5 * config.platform_size
        self.centres = (np.arange(g) + 0.5) * cell - half
        top = config.column_rest_top + config.max_column_height
        self.camera = _Camera(
            np.array([0.0, 0.0, 0.4 * top]),
            elevation=elevation,
            azimuth=azimuth,
            distance=2.3 * config.platform_size,
        )
        # the view box: the platform up to the highest column plus a sphere on top
        box = np.array(
            [
                [sx * half, sy * half, z]
                for sx in (-1, 1)
                for sy in (-1, 1)
                for z in (-_PLATFORM_THICKNESS, top + 2.0 * config.sphere_radius)
            ]
        )
        self.bounds = self.camera.project(box)
        self.platform = self._platform_faces(half)
        if config.column_shape == "box":
            self._box_sides()
        elif config.column_shape == "ellipsoid":
            self._dome_mesh(longitudes=8 if g <= 20 else 6)
        else:
            self._smooth_lattice(subdivisions=2 if g <= 20 else 1)

    # --- static parts -----------------------------------------------------------------------
    def faces_towards_camera(self, centres: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """True where a face with this centre [..., 3] and outward normal [..., 3] faces the
        camera; the other faces of a closed solid are hidden behind it."""
        return np.einsum("...k,...k->...", self.camera.eye - centres, normals) > 0.0

    def _platform_faces(self, half: float) -> list[np.ndarray]:
        z0, z1 = -_PLATFORM_THICKNESS, 0.0
        faces = [
            np.array([[-half, -half, z1], [half, -half, z1], [half, half, z1], [-half, half, z1]])
        ]
        for axis in (0, 1):
            for sign in (-1.0, 1.0):
                normal = np.zeros(3)
                normal[axis] = sign
                if self.faces_towards_camera(normal * half, normal):
                    a, b = np.array([-half, half]), np.full(2, sign * half)
                    xy = np.stack([b, a], -1) if axis == 0 else np.stack([a, b], -1)
                    faces.append(np.array([[*xy[0], z0], [*xy[1], z0], [*xy[1], z1], [*xy[0], z1]]))
        return faces

    def _box_sides(self) -> None:
        """The two side faces of each column that face the camera, as index arrays."""
        g, cell = self.config.grid_size, self.config.cell_size
        iy, ix = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
        cols, neighbours, corners, normals = [], [], [], []
        for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            normal = np.array([dx, dy, 0.0])
            face_centre = np.stack(
                [self.centres[ix] + 0.5 * cell * dx, self.centres[iy] + 0.5 * cell * dy, 0 * ix],
                axis=-1,
            )
            visible = self.faces_towards_camera(face_centre, normal)
            nx, ny = ix + dx, iy + dy
            inside = (nx >= 0) & (nx < g) & (ny >= 0) & (ny < g)
            flat = (iy * g + ix)[visible]
            cols.append(flat)
            neighbours.append(np.where(inside, ny * g + nx, -1)[visible])
            tangent = 0.5 * cell * np.array([-dy, dx])
            c = face_centre[visible][:, :2]
            corners.append(np.stack([c - tangent, c + tangent], axis=1))
            normals.append(np.broadcast_to(normal, (flat.size, 3)))
        self.side_column = np.concatenate(cols)
        self.side_neighbour = np.concatenate(neighbours)
        self.side_corners = np.concatenate(corners)  # [S, 2 (ends), 2 (xy)]
        self.side_normals = np.concatenate(normals)

    def _dome_mesh(self, *, longitudes: int) -> None:
        """Facets of a spheroid column relative to its top centre: the upper half and a band
        below the equator (the rest is hidden by the neighbours)."""
        a = 0.5 * self.config.cell_size
        c = 0.5 * self.config.column_aspect * self.config.cell_size
        theta = np.array([0.0, np.pi / 6, np.pi / 3, np.pi / 2, 3 * np.pi / 4])
        phi = np.linspace(0.0, 2 * np.pi, longitudes + 1)
        t0, p0 = np.meshgrid(theta[:-1], phi[:-1], indexing="ij")
        t1, p1 = np.meshgrid(theta[1:], phi[1:], indexing="ij")

        def point(t, p):
            return np.stack(
                [a * np.sin(t) * np.cos(p), a * np.sin(t) * np.sin(p), -c * (1 - np.cos(t))], -1
            )

        quads = np.stack([point(t0, p0), point(t0, p1), point(t1, p1), point(t1, p0)], axis=-2)
        tm, pm = 0.5 * (t0 + t1), 0.5 * (p0 + p1)
        normals = np.stack(
            [np.sin(tm) * np.cos(pm) / a, np.sin(tm) * np.sin(pm) / a, np.cos(tm) / c], -1
        )
        self.dome_offsets = quads.reshape(-1, 4, 3)
        self.dome_normals = (normals / np.linalg.norm(normals, axis=-1, keepdims=True)).reshape(
            -1, 3
        )

    def _smooth_lattice(self, *, subdivisions: int) -> None:
        """Bilinear interpolation weights from the column tops to a lattice over the platform."""
        g, half = self.config.grid_size, 0.5 * self.config.platform_size
        inner = np.linspace(self.centres[0], self.centres[-1], (g - 1) * subdivisions + 1)
        self.lattice = np.concatenate([[-half], inner, [half]])
        # np.interp is linear and clamps outside the centres: flat out to the platform edge
        self.weights = np.stack(
            [np.interp(self.lattice, self.centres, np.eye(g)[i]) for i in range(g)], axis=-1
        )

    # --- per-frame terrain ------------------------------------------------------------------
    def terrain(self, h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Faces of the columns for wave heights ``h`` [G(y), G(x)].

        Returns:
            Quads [F, 4, 3], the wave height that colours each [F], their normals [F, 3].
        """
        top = self.config.column_rest_top + h
        shape = self.config.column_shape
        if shape == "box":
            return self._box_terrain(h, top)
        if shape == "ellipsoid":
            return self._dome_terrain(h, top)
        return self._smooth_terrain(top)

    def _box_terrain(
        self, h: np.ndarray, top: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g, cell = self.config.grid_size, self.config.cell_size
        x, y = np.meshgrid(self.centres, self.centres)
        d = 0.5 * cell
        corners = np.array([[-d, -d], [d, -d], [d, d], [-d, d]])
        tops = np.empty((g * g, 4, 3))
        tops[..., 0] = x.reshape(-1, 1) + corners[:, 0]
        tops[..., 1] = y.reshape(-1, 1) + corners[:, 1]
        tops[..., 2] = top.reshape(-1, 1)
        flat_top = top.reshape(-1)
        upper = flat_top[self.side_column]
        lower = np.where(self.side_neighbour >= 0, flat_top[self.side_neighbour], 0.0)
        keep = upper > lower
        ends, n = self.side_corners[keep], int(keep.sum())
        sides = np.empty((n, 4, 3))
        sides[:, :, :2] = ends[:, [0, 1, 1, 0]]
        sides[:, :, 2] = np.stack([lower[keep], lower[keep], upper[keep], upper[keep]], -1)
        quads = np.concatenate([tops, sides])
        heights = np.concatenate([h.reshape(-1), h.reshape(-1)[self.side_column[keep]]])
        up = np.broadcast_to([0.0, 0.0, 1.0], (g * g, 3))
        return quads, heights, np.concatenate([up, self.side_normals[keep]])

    def _dome_terrain(
        self, h: np.ndarray, top: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x, y = np.meshgrid(self.centres, self.centres)
        apex = np.stack([x, y, top], -1).reshape(-1, 1, 1, 3)
        quads = apex + self.dome_offsets  # [G*G, F, 4, 3]
        quads[..., 2] = np.maximum(quads[..., 2], 0.0)
        f = self.dome_offsets.shape[0]
        heights = np.repeat(h.reshape(-1), f)
        normals = np.broadcast_to(self.dome_normals, quads.shape[:2] + (3,))
        return quads.reshape(-1, 4, 3), heights, normals.reshape(-1, 3)

    def _smooth_terrain(self, top: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rest = self.config.column_rest_top
        z = self.weights @ top @ self.weights.T  # [Y, X] over the lattice
        x, y = np.meshgrid(self.lattice, self.lattice)
        grid = np.stack([x, y, z], -1)
        quads = np.stack(
            [grid[:-1, :-1], grid[:-1, 1:], grid[1:, 1:], grid[1:, :-1]], axis=-2
        ).reshape(-1, 4, 3)
        normals = np.cross(quads[:, 2] - quads[:, 0], quads[:, 3] - quads[:, 1])
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        heights = quads[..., 2].mean(-1) - rest
        # skirts: the solid's walls along the platform edges
        walls, wall_normals = [], []
        for edge, normal in (
            (grid[:, 0], (-1.0, 0.0, 0.0)),
            (grid[:, -1], (1.0, 0.0, 0.0)),
            (grid[0], (0.0, -1.0, 0.0)),
            (grid[-1], (0.0, 1.0, 0.0)),
        ):
            floor = edge.copy()
            floor[:, 2] = 0.0
            wall = np.stack([floor[:-1], floor[1:], edge[1:], edge[:-1]], axis=-2)
            walls.append(wall)
            wall_normals.append(np.broadcast_to(normal, (wall.shape[0], 3)))
        walls = np.concatenate(walls)
        quads = np.concatenate([quads, walls])
        heights = np.concatenate([heights, walls[:, 2:, 2].mean(-1) - rest])
        return quads, heights, np.concatenate([normals, *wall_normals])


class Renderer:
    """Draws frames of TerraShift environments on one figure that is reused for every frame.

    Args:
        config: the scene to prepare the geometry for (the pretraining scene if None); a frame
            of a simulator with another config prepares that one's geometry instead.
        width: frame width in pixels, >= 200.
        height: frame height in pixels, >= 120.
        elevation: camera elevation above the platform plane [degrees].
        azimuth: direction of the camera seen from the platform centre, from +x towards +y
            [degrees]; the default looks from the -y side, slightly from -x.

    Example:
        >>> from terrashift_rl.sim import Simulator, TerraShiftConfig
        >>> sim = Simulator(TerraShiftConfig(column_shape="box"), num_envs=2, seed=0)
        >>> sim.reset()
        >>> renderer = Renderer(sim.config, width=320, height=160)
        >>> frames = [renderer.frame(sim, env_index=e) for e in range(2)]
        >>> frames[1].shape, frames[1].dtype.name
        ((160, 320, 3), 'uint8')
    """

    def __init__(
        self,
        config: TerraShiftConfig | None = None,
        *,
        width: int = 960,
        height: int = 480,
        elevation: float = 38.0,
        azimuth: float = -115.0,
    ):
        for name, value, minimum in (("width", width, 200), ("height", height, 120)):
            if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
                raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
        self.width, self.height = width, height
        self._elevation, self._azimuth = elevation, azimuth
        dpi = 100.0
        # Agg truncates the figure size in pixels: a hair over the size keeps it exact
        self._figure = Figure(
            figsize=((width + 0.01) / dpi, (height + 0.01) / dpi), dpi=dpi, facecolor=_BACKGROUND
        )
        self._canvas = FigureCanvasAgg(self._figure)
        font = max(6.0, 9.0 * min(height / 480, width / 960))
        title_px = 3.2 * font
        # left half: the scene, projected by _Camera, in image-plane coordinates
        self._scene_axes = self._figure.add_axes((0.0, 0.0, 0.5, 1.0 - title_px / height))
        self._scene_axes.set_axis_off()
        self._collection = PolyCollection([], closed=True)
        self._scene_axes.add_collection(self._collection)
        self._scene_title = self._figure.text(
            0.25, 1.0 - 0.4 * title_px / height, "", ha="center", va="top", fontsize=font
        )
        self._scene_label = self._figure.text(
            0.01, 0.01, "", ha="left", va="bottom", fontsize=0.85 * font, color="0.35"
        )
        # right half: the heightmap, a square image with its colorbar
        left, bottom, bar, labels = 5.0 * font, 4.0 * font, 1.6 * font, 7.0 * font
        side = min(height - title_px - bottom, 0.5 * width - left - 2 * bar - labels)
        x0 = 0.5 * width + 0.5 * (0.5 * width - (left + side + 2 * bar + labels)) + left
        y0 = bottom + 0.5 * (height - title_px - bottom - side)
        image_axes = self._figure.add_axes((x0 / width, y0 / height, side / width, side / height))
        bar_axes = self._figure.add_axes(
            ((x0 + side + bar) / width, y0 / height, bar / width, side / height)
        )
        self._image = image_axes.imshow(
            np.zeros((2, 2)),
            origin="lower",
            cmap=HEIGHTMAP_CMAP,
            vmin=-1.0,
            vmax=1.0,
            interpolation="nearest",
            aspect="auto",
        )
        image_axes.set_xlabel("x [m]", fontsize=font, labelpad=1)
        image_axes.set_ylabel("y [m]", fontsize=font, labelpad=1)
        image_axes.tick_params(labelsize=0.85 * font, pad=1, length=2)
        self._image_title = image_axes.set_title("", fontsize=font, pad=0.5 * font)
        colorbar = self._figure.colorbar(self._image, cax=bar_axes)
        colorbar.set_label("ray height, mapped to [-1, 1]", fontsize=0.85 * font, labelpad=2)
        colorbar.ax.tick_params(labelsize=0.85 * font, length=2, pad=1)
        self._column_cmap = colormaps[COLUMN_CMAP]
        self._set_scene(config if config is not None else TerraShiftConfig())

    # --- public API ---------------------------------------------------------------------------
    def frame(self, sim: Simulator, env_index: int = 0) -> np.ndarray:
        """Renders environment ``env_index`` of ``sim`` as it is now.

        Args:
            sim: the simulator; any device (the few arrays drawn are copied to the host).
            env_index: which environment of the batch, in [0, num_envs).

        Returns:
            The frame, uint8 [height, width, 3] (RGB).
        """
        if isinstance(env_index, bool) or not isinstance(env_index, int):
            raise ValueError(f"env_index must be an integer, got {env_index!r}")
        if not 0 <= env_index < sim.num_envs:
            raise ValueError(f"env_index {env_index} is out of range for {sim.num_envs} envs")
        if sim.config != self._scene.config:
            self._set_scene(sim.config)

        def read(name: str) -> np.ndarray:
            return sim.view(name)[env_index].detach().cpu().numpy()

        h = read("column_height").astype(np.float64)
        self._draw_scene(
            h,
            sphere_position=read("sphere_position").astype(np.float64),
            sphere_active=read("sphere_active") != 0,
            goal_cell=read("goal_cell"),
        )
        heightmap = read("heightmap")[0]
        self._image.set_data(heightmap)
        self._image_title.set_text(
            f"heightmap observation ({heightmap.shape[0]}\N{MULTIPLICATION SIGN}"
            f"{heightmap.shape[1]})"
        )
        self._scene_title.set_text(
            f"env {env_index}  \N{MIDDLE DOT}  step {int(read('step_count'))}"
            f"  \N{MIDDLE DOT}  goals {int(read('episode_goals'))}"
            f"  \N{MIDDLE DOT}  lost {int(read('episode_out_of_bounds'))}"
        )
        self._canvas.draw()
        return np.asarray(self._canvas.buffer_rgba())[..., :3].copy()

    def to_pixels(self, points: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Where world points [..., 3] (metres) land in a frame of the current geometry.

        Returns:
            Pixel coordinates [..., 2] as (column, row) floats, row 0 at the top.

        Example:
            >>> renderer = Renderer(width=480, height=240)
            >>> col, row = renderer.to_pixels([0.0, 0.0, 0.0])
            >>> bool(0 < col < 240 and 0 < row < 240)  # the platform centre, in the left half
            True
        """
        xy = self._scene.camera.project(np.asarray(points, dtype=np.float64))
        pixels = self._scene_axes.transData.transform(xy.reshape(-1, 2)).reshape(xy.shape)
        pixels[..., 1] = self.height - pixels[..., 1]
        return pixels

    # --- internals ----------------------------------------------------------------------------
    def _set_scene(self, config: TerraShiftConfig) -> None:
        self._scene = _Scene(config, elevation=self._elevation, azimuth=self._azimuth)
        self._column_norm = Normalize(-config.max_column_height, config.max_column_height)
        half = 0.5 * config.platform_size
        self._image.set_extent((-half, half, -half, half))
        self._scene_label.set_text(
            f"{config.column_shape} columns, {config.grid_size}\N{MULTIPLICATION SIGN}"
            f"{config.grid_size}"
        )
        # fit the view box, then widen one side so one unit is as many pixels on both axes
        (x0, y0), (x1, y1) = self._scene.bounds.min(0), self._scene.bounds.max(0)
        box = self._scene_axes.get_position()
        pixel_aspect = (box.height * self.height) / (box.width * self.width)
        cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        w = 1.06 * max(x1 - x0, (y1 - y0) / pixel_aspect)
        self._scene_axes.set_xlim(cx - 0.5 * w, cx + 0.5 * w)
        self._scene_axes.set_ylim(cy - 0.5 * w * pixel_aspect, cy + 0.5 * w * pixel_aspect)
        camera = self._scene.camera
        platform = np.stack(self._scene.platform)
        normals = np.cross(platform[:, 2] - platform[:, 0], platform[:, 3] - platform[:, 1])
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        shade = _AMBIENT + _DIFFUSE * np.abs(normals @ _LIGHT)
        grey = np.array([0.42, 0.42, 0.45, 1.0])
        self._platform_polys = list(camera.project(platform))
        self._platform_colors = np.concatenate(
            [grey[:3] * shade[:, None], np.ones((len(platform), 1))], axis=1
        )

    def _draw_scene(
        self,
        h: np.ndarray,
        *,
        sphere_position: np.ndarray,
        sphere_active: np.ndarray,
        goal_cell: np.ndarray,
    ) -> None:
        scene, camera, cfg = self._scene, self._scene.camera, self._scene.config
        quads, heights, normals = scene.terrain(h)
        centroids = quads.mean(axis=1)
        seen = scene.faces_towards_camera(centroids, normals)
        quads, heights, normals, centroids = (
            quads[seen],
            heights[seen],
            normals[seen],
            centroids[seen],
        )
        colors = self._column_cmap(self._column_norm(heights))
        colors[:, :3] *= (_AMBIENT + _DIFFUSE * np.clip(normals @ _LIGHT, 0.0, None))[:, None]
        polys = self._platform_polys + list(camera.project(quads))
        keys = [np.full(len(self._platform_polys), np.inf), camera.depth(centroids)]
        faces = [self._platform_colors, colors]
        edges = [self._platform_colors, colors]  # edges in the face colour hide the AA seams
        widths = [np.full(len(polys), 0.4)]

        def disc(centre: np.ndarray, radius: float, key: float, face, edge, width: float) -> None:
            rho = radius / camera.depth(centre)
            polys.append(camera.project(centre) + rho * _CIRCLE)
            keys.append(np.array([key]))
            faces.append(np.asarray([face]))
            edges.append(np.asarray([edge]))
            widths.append(np.array([width]))

        rest, r = cfg.column_rest_top, cfg.sphere_radius
        for g, (ix, iy) in enumerate(goal_cell):
            rgb = np.array(GOAL_COLORS[g % len(GOAL_COLORS)])
            centre = np.array([scene.centres[ix], scene.centres[iy], rest + h[iy, ix] + r])
            depth = camera.depth(centre) - cfg.goal_radius
            disc(centre, cfg.goal_radius, depth, (*rgb, 0.28), (*rgb, 0.9), 1.2)
        for j in np.flatnonzero(sphere_active):
            rgb = np.array(GOAL_COLORS[(j % cfg.num_goals) % len(GOAL_COLORS)])
            centre = sphere_position[j]
            depth = camera.depth(centre) - r
            disc(centre, r, depth, (*(0.7 * rgb), 1.0), (*(0.4 * rgb), 1.0), 0.8)
            # a lit cap and a highlight, offset towards the light, drawn right after the ball
            lit = centre + r * (0.3 * _LIGHT - 0.1 * camera.forward)
            disc(lit, 0.72 * r, depth - 1e-9, (*rgb, 1.0), (*rgb, 1.0), 0.0)
            spot = centre + r * (0.6 * _LIGHT - 0.2 * camera.forward)
            shine = (*(0.35 * rgb + 0.65), 1.0)
            disc(spot, 0.22 * r, depth - 2e-9, shine, shine, 0.0)
        order = np.argsort(-np.concatenate(keys), kind="stable")
        self._collection.set_verts([polys[i] for i in order])
        self._collection.set_facecolor(np.concatenate(faces)[order])
        self._collection.set_edgecolor(np.concatenate(edges)[order])
        self._collection.set_linewidth(np.concatenate(widths)[order])


def render_frame(
    sim: Simulator, env_index: int = 0, *, width: int = 960, height: int = 480
) -> np.ndarray:
    """Renders one environment of ``sim``: the scene on the left, the heightmap on the right.

    Builds a fresh :class:`Renderer` each call; keep one :class:`Renderer` to draw many frames.

    Args:
        sim: the simulator.
        env_index: which environment of the batch.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        The frame, uint8 [height, width, 3] (RGB).

    Example:
        >>> from terrashift_rl.sim import Simulator
        >>> sim = Simulator(num_envs=1, seed=0)
        >>> sim.reset()
        >>> render_frame(sim, width=480, height=240).shape
        (240, 480, 3)
    """
    return Renderer(sim.config, width=width, height=height).frame(sim, env_index)


def record_rollout(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None = None,
    *,
    steps: int,
    env_index: int = 0,
    every: int = 1,
    width: int = 960,
    height: int = 480,
) -> list[np.ndarray]:
    """Resets ``env``, steps it ``steps`` times and renders one of its environments.

    Args:
        env: a :class:`~terrashift_rl.envs.TerraShiftEnv`, or a ``TransformedEnv`` around one
            (its ``sim`` and ``config`` are reached through the transformed env).
        policy: any callable that takes the current tensordict and returns it with
            ``("agents", "action")`` written; uniform random actions if None. It runs under
            ``torch.no_grad()``.
        steps: decisions to play, >= 0.
        env_index: which environment of the batch to render.
        every: render after every ``every``-th step, >= 1.
        width: frame width in pixels.
        height: frame height in pixels.

    Returns:
        ``1 + steps // every`` frames: the state after the reset, then one after every
        ``every``-th step (after ``step_and_maybe_reset``, so a finished episode shows the new
        episode's first state).

    Example:
        >>> from terrashift_rl.envs import TerraShiftEnv
        >>> env = TerraShiftEnv(num_envs=2, seed=0)
        >>> frames = record_rollout(env, steps=4, every=2, width=320, height=160)
        >>> len(frames), frames[0].shape
        (3, (160, 320, 3))
    """
    for name, value, minimum in (("steps", steps, 0), ("every", every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    renderer = Renderer(env.config, width=width, height=height)
    with torch.no_grad():
        td = env.reset()
        frames = [renderer.frame(env.sim, env_index)]
        for t in tqdm(range(steps), desc="recording", unit="step"):
            td = env.rand_action(td) if policy is None else policy(td)
            _, td = env.step_and_maybe_reset(td)
            if (t + 1) % every == 0:
                frames.append(renderer.frame(env.sim, env_index))
    return frames


def save_video(
    frames: Sequence[np.ndarray] | np.ndarray, path: str | Path, *, fps: int = 30
) -> Path:
    """Writes frames to an MP4 (H.264) or GIF file, chosen by the suffix of ``path``.

    The video is written to a hidden temporary file in the same folder and moved over ``path``
    only once complete, so an interrupted write never leaves a partial video at ``path`` (and
    a failed one removes its temporary file). Frames of odd width or height are padded by one
    pixel for H.264. A GIF stores identical consecutive frames as one longer frame.

    Args:
        frames: uint8 RGB frames, each [height, width, 3], all of one size (a list or an array
            [T, height, width, 3]).
        path: output file, ending in ``.mp4`` or ``.gif``; missing folders are created.
        fps: frames per second, > 0.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: for another suffix, no frames, frames of mixed sizes or not uint8 RGB,
            or a non-positive ``fps``.

    Example:
        >>> import tempfile
        >>> frames = np.zeros((3, 32, 48, 3), dtype=np.uint8)
        >>> frames[:, :, :, 0] = np.arange(3)[:, None, None] * 100
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     save_video(frames, Path(folder) / "clip.gif", fps=10).name
        'clip.gif'
    """
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise ValueError(
            f"cannot write a video to {str(path)!r}: the suffix must be one of {sorted(_WRITERS)}"
        )
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not fps > 0:
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    stack = _frame_stack(frames)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.{os.urandom(4).hex()}.tmp{path.suffix}")
    try:
        writer(stack, temporary, fps)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path


def _frame_stack(frames: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    if len(frames) == 0:
        raise ValueError("no frames to save")
    shapes = {np.shape(frame) for frame in frames}
    if len(shapes) > 1:
        raise ValueError(f"frames must all have one shape, got {sorted(shapes)}")
    stack = np.stack([np.asarray(frame) for frame in frames])
    if stack.dtype != np.uint8 or stack.ndim != 4 or stack.shape[-1] != 3:
        raise ValueError(
            f"frames must be uint8 [height, width, 3], got {stack.dtype} {stack.shape[1:]}"
        )
    return stack


def _write_gif(frames: np.ndarray, path: Path, fps: float) -> None:
    images = [Image.fromarray(frame) for frame in frames]
    images[0].save(
        path,
        format="GIF",
        save_all=True,
        append_images=images[1:],
        duration=round(1000.0 / fps),
        loop=0,
    )


def _write_mp4(frames: np.ndarray, path: Path, fps: float) -> None:
    _, height, width, _ = frames.shape
    frames = np.pad(frames, ((0, 0), (0, height % 2), (0, width % 2), (0, 0)), mode="edge")
    with imageio.get_writer(
        path,
        format="FFMPEG",
        mode="I",
        fps=fps,
        codec="libx264",
        pixelformat="yuv420p",
        quality=7,
        macro_block_size=1,
        ffmpeg_log_level="error",
    ) as writer:
        for frame in frames:
            writer.append_data(frame)


_WRITERS = {".gif": _write_gif, ".mp4": _write_mp4}
