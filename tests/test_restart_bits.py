"""A run cut into calls gives the same bits as one call, in every kind of world: query
skipping (free flight) changes no result, so where a call ends (and its budgets restart) does
not matter. Band worlds included, whose far tiles answer lower bounds of the distance."""

import warnings

import numpy as np
import pytest

from fastsdf import GridSDF, NarrowBandGridSDF
from fastsdf.particles import Gravity, ParticleSimulation
from fastsdf.shapes.scenes import seed_world

BOUNDS = [(-2, 2), (-2, 2)]
WORLDS = {
    # the band narrower than the largest radius (0.1): particles reach the far tiles' bounds
    "narrow band": lambda: NarrowBandGridSDF(
        seed_world(), bounds=BOUNDS, band=0.1, samples=[257j, 257j]
    ),
    # the band as its docs advise for particles, (-w, r_max + w)
    "band": lambda: NarrowBandGridSDF(
        seed_world(), bounds=BOUNDS, band=(-0.05, 0.15), samples=[257j, 257j]
    ),
    "grid": lambda: GridSDF(seed_world(), bounds=BOUNDS, samples=[80j, 80j]),
    "exact": seed_world,
}
N = 2000


def make(world, skip=True):
    """Fast particles thrown over the world (as bench.step_bits's cases)."""
    sim = ParticleSimulation(world, n=N, seed=3)
    sim.force_generators.append(Gravity())
    rng = np.random.default_rng(1)
    sim.p["x"] = np.c_[rng.uniform(-1.1, 1.1, N), rng.uniform(-0.9, 1.1, N)]
    sim.p["v"] = rng.normal(scale=3.0, size=(N, 2))
    sim.engine.skip = skip
    return sim


@pytest.fixture(scope="module", params=list(WORLDS))
def world(request):
    return request.param, WORLDS[request.param]()


@pytest.mark.filterwarnings("ignore:particles of radius up to")
def test_calls_cut_anywhere_give_the_same_bits(world, tmp_path):
    name, w = world
    once = make(w)
    once.run(40)
    cut = make(w)
    cut.run(15)
    cut.run(25)
    saved = make(w)
    saved.run(15)
    path = saved.save(tmp_path / "sim.npz")
    resumed = ParticleSimulation.load(path)
    resumed.run(25)
    single = make(w)
    for _ in range(40):
        single.run(1)
    every_query = make(w, skip=False)  # no skipping at all: the reference
    every_query.run(40)
    for other in (cut, resumed, single, every_query):
        np.testing.assert_array_equal(other.p["x"], once.p["x"], err_msg=name)
        np.testing.assert_array_equal(other.p["v"], once.p["v"], err_msg=name)
    assert np.abs(once.p["x"] - make(w).p["x"]).max() > 0.5  # (they moved)


def test_a_band_too_narrow_for_the_particles_warns_once(world):
    name, w = world
    sim = make(w)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        sim.run(2)
        sim.run(2)
    said = [str(r.message) for r in record if "particles of radius up to" in str(r.message)]
    if name != "narrow band":
        assert said == []
        return
    assert len(said) == 1
    assert "band_range=(-0.1, 0.1)" in said[0] and "band=(-w, r_max + w)" in said[0]
    assert record[0].filename == __file__
