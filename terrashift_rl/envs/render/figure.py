"""Frames: the perspective view of one environment beside its heightmap observation, on a
reused Matplotlib figure."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from terrashift_rl.envs.render.scene import (  # the package's own shading constants
    _AMBIENT,
    _BACKGROUND,
    _CIRCLE,
    _DIFFUSE,
    _LIGHT,
    COLUMN_CMAP,
    GOAL_COLORS,
    HEIGHTMAP_CMAP,
    _Scene,
)
from terrashift_rl.sim import Simulator, TerraShiftConfig

__all__ = ["Renderer", "render_frame"]


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
