"""Camera geometry from the pixels: wall heights, visible wall colours, distractors."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from sim_node import RobotEnv, SimConfig, random_rollout
from sim_node.camera import FLOOR_COLOUR, SKY_COLOUR, WALL_COLOURS, Camera

NORTH = 2


def _render(environment: str, position: tuple[float, float]) -> np.ndarray:
    return Camera(SimConfig(environment=environment)).render(np.array([position]))[0]


def _wall_colours_seen(image: np.ndarray, tol: float = 3.0) -> set[int]:
    """Walls whose colour appears in some pixel, pure or mixed with the sky or the floor.

    A pixel shows wall ``w`` when it lies (within ``tol`` levels) on the segment between
    that wall's colour and the sky or floor colour, with at least 10 % wall in the mix.
    """
    pixels = image.reshape(-1, 3).astype(float) / 255.0
    seen = set()
    for w, wall in enumerate(WALL_COLOURS):
        for background in (SKY_COLOUR, FLOOR_COLOUR):
            direction = wall - background
            share = np.clip((pixels - background) @ direction / (direction @ direction), 0, 1)
            nearest = background + share[:, None] * direction
            on_segment = np.abs(pixels - nearest).max(axis=1) * 255.0 <= tol
            if np.any(on_segment & (share >= 0.1)):
                seen.add(w)
    return seen


def test_image_is_16x16_rgb8():
    image = _render("full", (10.0, 20.0))
    assert image.shape == (16, 16, 3) and image.dtype == np.uint8


@pytest.mark.parametrize("environment", ["full", "partial"])
def test_a_nearer_wall_looks_taller(environment):
    def north_wall_rows(y: float) -> float:
        column = _render(environment, (22.5, y))[:, 8].astype(float) / 255.0
        # share of each pixel that is wall, from its mix of sky, wall and floor colours
        sky, wall, floor = SKY_COLOUR, WALL_COLOURS[NORTH], FLOOR_COLOUR
        # the three colours are coplanar (R = G), so add the constraint that shares sum to 1
        basis = np.vstack([np.stack([sky, wall, floor], axis=1), np.ones(3)])
        target = np.vstack([column.T, np.ones(len(column))])
        shares = np.linalg.lstsq(basis, target, rcond=None)[0]
        return float(shares[1].sum())

    config = SimConfig(environment=environment)
    row = 2.0 * config.vertical_extent / config.image_size  # rows are even in tan
    # beyond the distance at which the wall fills the whole column
    heights = [north_wall_rows(y) for y in (3.0, 10.0, 20.0, 25.0, 33.0)]
    assert all(a < b for a, b in itertools.pairwise(heights)), heights
    # perspective: the apparent height in tan of elevation is wall height / distance
    for y, height in zip((3.0, 10.0, 20.0, 25.0, 33.0), heights, strict=True):
        assert height == pytest.approx(config.wall_height / (45.0 - y) / row, rel=0.05)
    close = north_wall_rows(42.0)
    assert close == pytest.approx(config.image_size, abs=0.1)  # fills the column


def test_300_degree_camera_sees_all_four_walls():
    # the 60 degree blind spot faces south: from the southern half of the room all four
    # walls are in view; from the north-centre the south wall can hide in the blind spot
    grid = [(x, y) for x in (3.0, 8.0, 15.0, 22.5, 30.0, 37.0, 42.0) for y in (3.0, 10.0, 20.0)]
    for position in grid:
        assert _wall_colours_seen(_render("full", position)) == {0, 1, 2, 3}, position
    for position in [(x, y) for x in (3.0, 22.5, 42.0) for y in (30.0, 42.0)]:
        assert len(_wall_colours_seen(_render("full", position))) >= 3, position


def test_60_degree_camera_sees_one_or_two_walls():
    rng = np.random.default_rng(0)
    counts = []
    for position in rng.uniform(1.0, 44.0, size=(200, 2)):
        image = _render("partial", tuple(position))
        seen = _wall_colours_seen(image)
        assert 1 <= len(seen) <= 2, (position, seen)
        assert NORTH in seen  # the camera faces north
        counts.append(len(seen))
    assert set(counts) == {1, 2}


def test_distractors_change_only_the_red_channel():
    plain = random_rollout(SimConfig(environment="full"), 300, seed=4).images
    noisy = random_rollout(SimConfig(environment="distractors"), 300, seed=4).images
    assert np.array_equal(plain[..., 1:], noisy[..., 1:])
    differs = (plain[..., 0] != noisy[..., 0]).any(axis=(1, 2))
    assert differs.mean() > 0.9


def test_distractors_move_between_steps():
    env = RobotEnv(SimConfig(environment="distractors"), seed=2)
    env.reset(options={"position": (22.5, 22.5)})
    still = 12  # zero velocity
    frames = [env.step(still)[0] for _ in range(5)]
    assert all(not np.array_equal(a, b) for a, b in itertools.pairwise(frames))
    plain = RobotEnv(SimConfig(environment="full"), seed=2)
    plain.reset(options={"position": (22.5, 22.5)})
    static = [plain.step(still)[0] for _ in range(3)]
    assert all(np.array_equal(static[0], f) for f in static)


def test_images_change_smoothly_with_position():
    # area-weighted rows: a 1 cm move changes pixels by at most one ray's share of a
    # column (a wall corner crossing one of the column's rays), and barely on average
    config = SimConfig(environment="full")
    rng = np.random.default_rng(3)
    for position in rng.uniform(2.0, 43.0, size=(20, 2)):
        a = Camera(config).render(position[None])[0].astype(int)
        b = Camera(config).render(position[None] + [0.01, 0.0])[0].astype(int)
        assert np.abs(a - b).max() <= 255 / config.rays_per_column + 2
        assert np.abs(a - b).mean() < 0.2


def test_distractors_persist_moving_a_few_metres_per_step():
    # the guide's "randomly moving" objects: a slow reflected walk (1.5 m std per coordinate),
    # not positions redrawn every step
    from sim_node.distractors import Distractors

    config = SimConfig(environment="distractors")
    walker = Distractors(config, np.random.default_rng(7))
    floor, walls = walker.positions()
    floor_steps, wall_steps, visited = [], [], []
    for _ in range(2000):
        walker.advance()
        new_floor, new_walls = walker.positions()
        floor_steps.append(np.linalg.norm(new_floor - floor, axis=1))
        wall_steps.append(np.abs(new_walls - walls))
        visited.append(new_floor)
        floor, walls = new_floor, new_walls
    floor_steps, wall_steps = np.array(floor_steps), np.array(wall_steps)
    std = config.distractors.step_std
    assert std <= 2.0
    # reflection only shortens a step, so no step exceeds the free walk's (5 sigma here)
    assert floor_steps.max() < 5 * std * np.sqrt(2) and wall_steps.max() < 5 * std
    # a free 2-D Gaussian step has mean sigma * sqrt(pi / 2); reflections barely change it
    assert floor_steps.mean() == pytest.approx(std * np.sqrt(np.pi / 2), rel=0.1)
    # and over many steps each disk wanders across most of the room: the walk is not stuck
    span = np.ptp(np.array(visited), axis=0)  # (F, 2)
    assert span.min() > 0.5 * (config.room_size - 2 * config.distractors.floor_radius)
