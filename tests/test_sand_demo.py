"""The sand demo's pour: a hopper above the disc, filled with grains that start apart."""

import numpy as np


def test_the_hopper_starts_its_grains_clear_of_the_walls_and_of_each_other():
    from fastsdf.apps.demo import (
        HOPPER_OUTLET_Y,
        SAND_RADIUS,
        SAND_RADIUS_SPREAD,
        hopper_fill,
        sand_world,
    )

    rng = np.random.default_rng(1)
    n = 400
    r = SAND_RADIUS * rng.uniform(1 - SAND_RADIUS_SPREAD, 1 + SAND_RADIUS_SPREAD, n)
    pos = hopper_fill(n, r, rng)
    assert pos.shape == (n, 2) and np.all(pos[:, 1] > HOPPER_OUTLET_Y)
    world = sand_world("seed")
    d = np.asarray(world(pos[:, 0], pos[:, 1])).reshape(-1)
    assert np.all(d > r)  # clear of the hopper's walls (and of everything else)
    gap = np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))
    touch = gap < r[:, None] + r[None, :]
    np.fill_diagonal(touch, False)
    assert not touch.any()
    # the outlet is open: straight below it, nothing but air down to the disc
    ys = np.linspace(0.45, HOPPER_OUTLET_Y + 0.1, 50)
    assert np.all(np.asarray(world(np.zeros_like(ys), ys)).reshape(-1) > 0.1)
