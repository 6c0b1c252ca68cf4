"""Panoramic RGB camera: vectorised ray casting in a square room (no per-pixel loops).

Geometry. The camera sits on top of the robot (height ``robot_height``) and faces the
robot's heading: north (+y) for the planar robot, which never turns. Columns split the
horizontal field of view evenly from left to right; each column averages
``rays_per_column`` horizontal rays. Rows are evenly spaced in the tangent of the elevation
angle, from ``+vertical_half_extent`` (top row) to its negative, as in
a cylindrical panorama. A ray at horizontal distance ``d`` from the wall it meets sees
the wall for tangents in ``[-h/d, (H - h)/d]`` (camera height h, wall height H), the
floor below and the space above the walls above, so a nearer wall looks taller. Each
pixel is the exact area-weighted mix of what its rows cover, which keeps images smooth
functions of the robot's position.

Distractors (environment ``distractors``) change only the red channel: disks on the
floor and rectangles on the walls whose red is the opposite extreme of their background
(1 where the background red is below 0.5, else 0), the strongest change the red channel
allows; where floor disks overlap the red saturates.
"""

from __future__ import annotations

import numpy as np

from sim_node.config import SimConfig

__all__ = ["FLOOR_COLOUR", "SKY_COLOUR", "WALL_COLOURS", "WALL_NAMES", "Camera"]

WALL_NAMES = ("south", "east", "north", "west")
WALL_COLOURS = np.array(
    [
        [0.20, 0.65, 0.20],  # south (y = 0): green
        [0.75, 0.20, 0.20],  # east (x = L): red
        [0.10, 0.10, 0.55],  # north (y = L): dark blue
        [0.85, 0.80, 0.15],  # west (x = 0): yellow
    ]
)
FLOOR_COLOUR = np.array([0.35, 0.35, 0.35])
SKY_COLOUR = np.array([0.85, 0.85, 0.90])
_SOUTH, _EAST, _NORTH, _WEST = range(4)
_NORTH_HEADING = np.pi / 2


def _distractor_red(red: np.ndarray | float) -> np.ndarray:
    return np.where(np.asarray(red) < 0.5, 1.0, 0.0)


class Camera:
    """Renders ``(N, H, W, 3)`` uint8 images for ``N`` robot positions at once.

    Work arrays are float32 and laid out ``(N, W, H, S)`` (steps, columns, rows, rays) so
    that mixing the wall colours of a column's rays is one batched matrix product.
    """

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        size, rays = config.image_size, config.rays_per_column
        fov = np.deg2rad(config.fov_deg)
        fraction = (np.arange(size * rays) + 0.5) / (size * rays)  # left to right
        self._offset = (fov / 2 - fraction * fov).reshape(size, rays)  # from the heading
        azimuth = _NORTH_HEADING + self._offset
        self._ux, self._uy = np.cos(azimuth), np.sin(azimuth)  # (W, S)
        extent = config.vertical_extent
        edges = extent * (1.0 - 2.0 * np.arange(size + 1) / size)  # top edge first
        self._row_top = edges[:-1, None].astype(np.float32)  # (H, 1)
        self._row_bottom = edges[1:, None].astype(np.float32)
        self._inv_row_height = np.float32(size / (2.0 * extent))
        self._ground_rows = np.flatnonzero(self._row_bottom[:, 0] < 0)  # may show the floor
        self._cam_h = config.robot_height
        self._wall_h = config.wall_height
        self._wall_colours = WALL_COLOURS.astype(np.float32)
        self._wall_red_delta = (_distractor_red(WALL_COLOURS[:, 0]) - WALL_COLOURS[:, 0]).astype(
            np.float32
        )

    def _coverage(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Fraction of each row covered by the tangent band ``[low, high]``.

        ``low`` and ``high`` have shape ``(..., S)``; the result ``(..., H, S)``.
        """
        cover = np.minimum(high[..., None, :], self._row_top)
        cover -= np.maximum(low[..., None, :], self._row_bottom)
        np.clip(cover, 0.0, None, out=cover)
        cover *= self._inv_row_height
        return cover

    def _directions(self, headings: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions: ``(W, S)`` facing north, or ``(N, W, S)`` for ``headings``."""
        if headings is None:
            return self._ux, self._uy
        azimuth = np.asarray(headings, dtype=np.float64).reshape(-1, 1, 1) + self._offset
        return np.cos(azimuth), np.sin(azimuth)

    def _cast(
        self, positions: np.ndarray, ux: np.ndarray, uy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance, wall index and coordinate along that wall for every ray: ``(N, W, S)``."""
        size = self.config.room_size
        px, py = positions[:, 0, None, None], positions[:, 1, None, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.where(ux > 0, (size - px) / ux, np.where(ux < 0, -px / ux, np.inf))
            ty = np.where(uy > 0, (size - py) / uy, np.where(uy < 0, -py / uy, np.inf))
        hits_x = tx < ty
        distance = np.where(hits_x, tx, ty)
        wall = np.where(
            hits_x, np.where(ux > 0, _EAST, _WEST), np.where(uy > 0, _NORTH, _SOUTH)
        )
        along = np.where(hits_x, py + distance * uy, px + distance * ux)
        return distance, wall, along

    def render(
        self,
        positions: np.ndarray,
        floor_disks: np.ndarray | None = None,
        wall_patches: np.ndarray | None = None,
        headings: np.ndarray | None = None,
    ) -> np.ndarray:
        """Images seen from ``positions`` ``(N, 2)``.

        ``floor_disks`` ``(N, F, 2)`` are distractor disk centres and ``wall_patches``
        ``(N, 4)`` the distractor centre along each wall (south, east, north, west); both
        ``None`` renders the plain room. ``headings`` ``(N,)`` (radians from +x) turn the
        camera; None faces north. Returns ``(N, H, W, 3)`` uint8.
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        if headings is not None and (floor_disks is not None or wall_patches is not None):
            raise ValueError("the distractors are drawn for the north-facing camera only")
        ux, uy = self._directions(headings)
        distance, wall, along = self._cast(positions, ux, uy)
        inv_distance = (1.0 / distance).astype(np.float32)
        wall_low = -self._cam_h * inv_distance
        wall_high = (self._wall_h - self._cam_h) * inv_distance
        cover_wall = self._coverage(wall_low, wall_high)  # (N, W, H, S)
        cover_sky = self._coverage(wall_high, np.full_like(wall_high, np.inf))
        rays = self.config.rays_per_column
        wall_share = cover_wall.sum(axis=3) / rays  # (N, W, H)
        sky_share = cover_sky.sum(axis=3) / rays
        floor_share = 1.0 - wall_share - sky_share
        image = np.matmul(cover_wall, self._wall_colours[wall]) / rays  # (N, W, H, 3)
        image += sky_share[..., None] * SKY_COLOUR.astype(np.float32)
        image += floor_share[..., None] * FLOOR_COLOUR.astype(np.float32)
        if floor_disks is not None:
            image[..., 0] += self._floor_distractor_red(positions, distance, floor_disks)
        if wall_patches is not None:
            image[..., 0] += self._wall_distractor_red(inv_distance, wall, along, wall_patches)
        image = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
        return image.transpose(0, 2, 1, 3)

    def _floor_distractor_red(
        self, positions: np.ndarray, distance: np.ndarray, disks: np.ndarray
    ) -> np.ndarray:
        """Red-channel change ``(N, W, H)`` from disks lying on the floor.

        Only the (step, column, disk, ray) combinations whose ray crosses a disk, and only
        the rows below the horizon, get a coverage: the dense ``(N, W, F, H, S)`` tensor
        would be mostly zeros. Coverages are summed per (step, column) with one
        ``reduceat`` over the visible combinations, which come out of ``nonzero`` sorted.
        """
        radius = self.config.distractors.floor_radius
        count, columns = distance.shape[:2]
        out = np.zeros((count * columns, self.config.image_size), dtype=np.float32)
        offset = np.asarray(disks, dtype=np.float64) - positions[:, None, :]  # (N, F, 2)
        # distance along each ray to the disk centre's foot point: (N, W, F, S)
        along_ray = (
            offset[:, None, :, 0, None] * self._ux[None, :, None, :]
            + offset[:, None, :, 1, None] * self._uy[None, :, None, :]
        )
        perp2 = np.sum(offset**2, axis=2)[:, None, :, None] - along_ray**2
        half = np.sqrt(np.clip(radius**2 - perp2, 0.0, None))
        near = np.maximum(along_ray - half, 1e-9)
        far = np.minimum(along_ray + half, distance[:, :, None, :])
        visible = (perp2 < radius**2) & (far > near)
        step, column, _, _ = np.nonzero(visible)
        if step.size:
            low = (-self._cam_h / near[visible]).astype(np.float32)[:, None]  # (K, 1)
            high = (-self._cam_h / far[visible]).astype(np.float32)[:, None]
            rows = self._ground_rows
            cover = np.minimum(high, self._row_top[rows, 0])
            cover -= np.maximum(low, self._row_bottom[rows, 0])
            np.clip(cover, 0.0, None, out=cover)  # (K, rows below the horizon)
            key = step * columns + column  # non-decreasing: nonzero returns C order
            first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
            delta = float(_distractor_red(FLOOR_COLOUR[0]) - FLOOR_COLOUR[0])
            scale = np.float32(delta * self._inv_row_height / self.config.rays_per_column)
            out[key[first, None], rows] = np.add.reduceat(cover, first, axis=0) * scale
        return out.reshape(count, columns, -1)

    def _wall_distractor_red(
        self, inv_distance: np.ndarray, wall: np.ndarray, along: np.ndarray, patches: np.ndarray
    ) -> np.ndarray:
        """Red-channel change ``(N, W, H)`` from one rectangle on each wall."""
        cfg = self.config.distractors
        patches = np.asarray(patches, dtype=np.float64)
        centre = np.take_along_axis(patches, wall.reshape(len(wall), -1), axis=1)
        inside = np.abs(along - centre.reshape(wall.shape)) < cfg.wall_half_width
        low = (cfg.wall_bottom - self._cam_h) * inv_distance
        high = (cfg.wall_top - self._cam_h) * inv_distance
        weight = inside * self._wall_red_delta[wall] / self.config.rays_per_column  # (N, W, S)
        return np.matmul(self._coverage(low, high), weight[..., None].astype(np.float32))[..., 0]
