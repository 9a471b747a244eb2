"""The perspective view's geometry: a pinhole camera and a scene's polygons (columns, spheres,
goals, platform), shaded by a fixed light and sorted far to near (painter's algorithm)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from matplotlib import colormaps

from terrashift_rl.sim import TerraShiftConfig

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
