"""A starting state the springs would blow apart (grains deep in each other or in the world)
warns once, naming how many grains and the worst case; a sound pile does not warn."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fastsdf as fs
from fastsdf.granular import GranularSimulation, brute_force_pairs
from fastsdf.granular.checks import (
    StartingStateWarning,
    grain_overlaps,
    wall_overlaps,
)
from fastsdf.particles import ContactLaw, ParticleSimulation

FLOOR = fs.Halfspace(normal=[0, 1], d=0.0)  # solid below y = 0


def _only_warning(record):
    found = [w for w in record if issubclass(w.category, StartingStateWarning)]
    assert len(found) == 1, [str(w.message) for w in record]
    return str(found[0].message)


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_three_grains_at_one_point_warn_naming_three(device):
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        GranularSimulation(
            None, positions=[[0, 0], [0, 0], [0, 0], [5, 5]], radius=0.5, device=device
        )
    message = _only_warning(record)
    assert message.startswith("3 grains overlap another by more than 10%")
    assert "the worst: grains 0 and 1, by 1, 200% of radius 0.5" in message
    assert "spread them out" in message
    assert record[0].filename == __file__  # the user's line, not the library's


def test_a_grain_inside_a_wall_warns():
    positions = [[0.0, 1.0], [2.0, -3.5], [4.0, 1.0]]  # grain 1: 4 units inside the floor
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        GranularSimulation(FLOOR, positions=positions, radius=0.5)
    message = _only_warning(record)
    assert message.startswith("1 grain starts inside the world")
    assert "grain 1, its centre 3.5 inside the world, radius 0.5" in message
    assert "give positions outside the world" in message


def test_both_in_one_warning_through_the_particle_family():
    positions = [[0.0, 0.3], [0.0, 0.3], [3.0, 0.1]]  # two at one point, one half in the floor
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        ParticleSimulation(FLOOR, positions=positions, radius=0.2, contacts=ContactLaw())
    message = _only_warning(record)
    assert "2 grains overlap another" in message
    assert "1 grain starts inside the world or overlapping it" in message
    assert "grain 2, its centre 0.1 from it, radius 0.2" in message
    assert record[0].filename == __file__


def test_set_state_checks_the_new_positions():
    sim = GranularSimulation(FLOOR, positions=[[0.0, 1.0], [2.0, 1.0]], radius=0.5)
    with pytest.warns(StartingStateWarning, match="2 grains overlap another"):
        sim.set_state(positions=[[0.0, 1.0], [0.5, 1.0]])
    with pytest.warns(StartingStateWarning, match="1 grain starts inside"):
        sim.set_state(positions=[[0.0, 1.0], [2.0, 0.0]])


def test_a_sound_pile_does_not_warn():
    """The README's grain block, a touching square packing on the floor, a grain overlapping
    its neighbour or the floor by 9% of its radius: no warning."""
    f = fs.Halfspace(normal=[0, 1], d=-1.8) | fs.Halfspace(normal=[1, 1], d=-1.8)
    f |= fs.Halfspace(normal=[-1, 1], d=-1.8)
    with fs.smoothness(10):
        f |= fs.Circle(center=[0, 0], radius=0.5) & fs.Halfspace(normal=[0.1, 1], d=0.3)
    gx, gy = np.meshgrid(np.linspace(-0.2, 0.2, 10), np.linspace(0.5, 1.0, 12))
    column = np.column_stack([gx.ravel(), gy.ravel()])
    law = ContactLaw(history=True, rolling_friction=0.3)
    gx, gy = np.meshgrid(np.arange(20) * 0.1, 0.05 + np.arange(10) * 0.1)
    bed = np.column_stack([gx.ravel(), gy.ravel()])
    with warnings.catch_warnings():
        warnings.simplefilter("error", StartingStateWarning)
        ParticleSimulation(f, positions=column, radius=0.02, contacts=law)
        GranularSimulation(FLOOR, positions=bed, radius=0.05)
        GranularSimulation(FLOOR, positions=[[0.0, 0.5], [0.955, 0.5], [3.0, 0.455]], radius=0.5)
        GranularSimulation(
            None, positions=[[0.1, 0.0], [9.0, 0.0]], radius=0.5, periodic_x=(0.0, 10.0)
        )


def test_periodic_neighbours_across_the_seam_warn():
    with pytest.warns(StartingStateWarning, match="grains 0 and 1, by 0.4, 80%"):
        GranularSimulation(
            None, positions=[[0.1, 0.0], [9.5, 0.0]], radius=0.5, periodic_x=(0.0, 10.0)
        )


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 60),
    spread=st.floats(0.5, 6.0),
)
def test_grain_overlaps_agree_with_all_pairs(seed, n, spread):
    """Given the pairs of a cell list (every pair closer than the sum of radii, here all of
    them by brute force), the count and the worst pair agree with a check of every pair."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, spread, (2, n))
    r = rng.uniform(0.1, 0.4, n)
    pairs = brute_force_pairs(x, y, r, 0.0)
    found = grain_overlaps(x, y, r, pairs)
    i, j = np.triu_indices(n, 1)
    depth = r[i] + r[j] - np.hypot(x[i] - x[j], y[i] - y[j])
    share = depth / np.minimum(r[i], r[j])
    bad = share > 0.1
    if not bad.any():
        assert found is None
        return
    assert found is not None
    assert found.grains == np.unique(np.concatenate([i[bad], j[bad]])).shape[0]
    k = int(np.argmax(np.where(bad, share, -np.inf)))
    assert found.depth / found.radius == pytest.approx(share[k], rel=1e-12)


def test_wall_overlaps_by_distance():
    r = np.array([0.5, 0.5, 0.5, 0.5, 1.0])
    d = np.array([1.0, 0.46, 0.44, -4.0, np.nan])  # 8%, 12% of the radius; inside; unknown
    found = wall_overlaps(d, r)
    assert found is not None
    assert (found.grains, found.worst, found.other) == (2, 3, -1)
    assert found.depth == pytest.approx(4.5)
    assert wall_overlaps(d[:2], r[:2]) is None
