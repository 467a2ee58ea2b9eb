"""Save and resume: a loaded simulation continues bit for bit; pickling does too."""

import copy
import os
import pickle

import numpy as np
import pytest
from numba import njit

from fastsdf.fields.grid import GridSDF
from fastsdf.io import load_simulation, save_simulation
from fastsdf.particles import Drag, Gravity, ParticleSimulation
from fastsdf.shapes import Circle, Halfspace

WORLD = Halfspace([0.0, 1.0], -1.0) | Circle([0.3, 0.0], 0.4)


@njit
def swirl(x, y, vx, vy, m, t):
    return -0.5 * y * m, 0.5 * x * m


def wind(p, t):
    """A Python force generator (the slow path), defined at module level so it pickles."""
    f = np.zeros((len(p), 2))
    f[:, 0] = 0.2 * np.sin(3.0 * t)
    return f


def make(world, python_force=False):
    sim = ParticleSimulation(world, n=300, timestep=1 / 30, seed=np.random.default_rng(7), cr=0.7)
    sim.force_generators += [Gravity((0.1, -1.0)), Drag(0.05)]
    if not isinstance(world, GridSDF):  # (a grid world's kernel without it is shared, cached)
        sim.force_generators.append(swirl)
    if python_force:
        sim.force_generators.append(wind)
    return sim


def assert_same(a, b):
    for name in ("x", "v", "m", "r", "cr", "cf"):
        np.testing.assert_array_equal(a.p[name], b.p[name], err_msg=name)
    assert a.t == b.t


@pytest.mark.parametrize("kind", ["grid", "exact", "exact+python"])
def test_resume_is_bit_exact(tmp_path, kind):
    world = (
        GridSDF(WORLD, bounds=[(-2, 2), (-2, 2)], samples=[64j, 64j]) if kind == "grid" else WORLD
    )
    python = kind.endswith("python")
    straight = make(world, python)  # the same calls, without saving between them
    straight.run(15)
    straight.run(25)
    first = make(world, python)
    first.run(15)
    path = save_simulation(first, tmp_path / "sim.npz")
    resumed = load_simulation(path)
    assert type(resumed.sdf) is type(world) and resumed.dt == first.dt
    assert [type(g) for g in resumed.force_generators] == [type(g) for g in first.force_generators]
    resumed.run(25)
    assert_same(resumed, straight)
    # one call of 40 steps gives the same state (the clock differs by the rounding of its sum)
    once = make(world, python)
    once.run(40)
    for name in ("x", "v"):
        np.testing.assert_array_equal(once.p[name], resumed.p[name])
    # the state moved (the comparison is not between two frozen states)
    assert np.abs(straight.p["x"] - make(world).p["x"]).max() > 0.1
    # the saved random generator continues too: a reset draws the same fresh state
    first.run(25)
    first.reset()
    resumed.reset()
    assert_same(first, resumed)


def test_file_is_readable_without_fastsdf(tmp_path):
    sim = make(WORLD)
    sim.run(3)
    path = save_simulation(sim, tmp_path / "sim.npz")
    with np.load(path) as data:  # no pickle needed for the state
        np.testing.assert_array_equal(data["x"], sim.p["x"])
        assert float(data["t"]) == sim.t


def test_pickle_and_deepcopy_continue_bit_exactly():
    sim = make(WORLD, python_force=True)
    sim.run(5)
    copies = [pickle.loads(pickle.dumps(sim)), copy.deepcopy(sim)]
    sim.run(10)
    for c in copies:
        c.run(10)
        assert_same(c, sim)


def test_unsavable_force_is_named_and_nothing_is_written(tmp_path):
    sim = make(WORLD)
    sim.force_generators.append(lambda p, t: np.zeros((len(p), 2)))
    path = tmp_path / "sim.npz"
    path.write_bytes(b"previous")
    with pytest.raises(ValueError, match=r"force_generators\[\d\] \(.*<lambda>\) cannot be saved"):
        save_simulation(sim, path)
    assert path.read_bytes() == b"previous" and os.listdir(tmp_path) == ["sim.npz"]


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    sim = make(WORLD)
    path = tmp_path / "sim.npz"
    save_simulation(sim, path)
    before = path.read_bytes()

    def broken(fh, **arrays):
        fh.write(b"half a file")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken)
    sim.run(2)
    with pytest.raises(OSError, match="disk full"):
        save_simulation(sim, path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["sim.npz"]


def test_bad_files_and_arguments(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a saved fastsdf simulation"):
        load_simulation(junk)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(ValueError, match="not a saved fastsdf simulation"):
        load_simulation(other)
    with pytest.raises(TypeError, match="sim must be a ParticleSimulation"):
        save_simulation(object(), tmp_path / "x.npz")


def test_parameters_and_moving_walls_resume_bit_exactly(tmp_path):
    import fastsdf as sdf

    # the piston of test_moving_walls (the same kernel): its parameters set away from defaults
    piston = sdf.Halfspace(normal=[1, 0], d=sdf.Param("x0", -1.0) + sdf.Param("u", 0.5) * sdf.t)

    def make_piston():
        sim = ParticleSimulation(piston, n=64, timestep=1 / 60, seed=2)
        sim.params.update({"u": 0.8, "x0": -1.5})
        sim.force_generators.append(Gravity((0.0, -0.5)))
        return sim

    straight, first = make_piston(), make_piston()
    straight.run(30)
    straight.run(40)
    first.run(30)
    resumed = load_simulation(save_simulation(first, tmp_path / "piston.npz"))
    assert resumed.params == {"u": 0.8, "x0": -1.5}
    resumed.run(40)
    assert_same(resumed, straight)
    assert np.ptp(straight.p["x"][:, 0]) > 0 and straight.t > 1.0
    # Pickling carries the parameter table too (its values and its name check).
    copied = pickle.loads(pickle.dumps(first))
    assert copied.params == {"u": 0.8, "x0": -1.5}
    with pytest.raises(KeyError, match="unknown parameter"):
        copied.params["v"] = 1.0
    copied.run(40)
    assert_same(copied, straight)


def test_methods_save_and_load(tmp_path):
    sim, straight = make(WORLD), make(WORLD)
    sim.run(10)
    straight.run(10)
    straight.run(15)
    path = sim.save(tmp_path / "sim.npz")
    resumed = ParticleSimulation.load(path)
    resumed.run(15)
    assert_same(resumed, straight)


def test_run_records_through_a_recorder():
    class Frames:
        """A recorder in the shape ParticleSimulation.run expects (run(sim, steps))."""

        every = 4

        def __init__(self):
            self.clock = []

        def run(self, sim, steps):
            for _ in range(steps // self.every):
                sim.run(self.every)
                self.clock.append(sim.t)

    sim, straight = make(WORLD), make(WORLD)
    frames = Frames()
    sim.run(12, record=frames)
    straight.run(12)
    for name in ("x", "v"):  # the same steps, grouped differently: the same bits
        np.testing.assert_array_equal(sim.p[name], straight.p[name])
    assert sim.t == pytest.approx(straight.t, rel=1e-15)
    np.testing.assert_allclose(frames.clock, np.arange(1, 4) * 4 / 30)
    with pytest.raises(TypeError, match="record must be a recorder"):
        sim.run(2, record="frames.h5")


def test_integral_float_particle_count_is_accepted():
    assert ParticleSimulation(WORLD, n=1e3).n == 1000
    with pytest.raises(TypeError, match="n must be an integer"):
        ParticleSimulation(WORLD, n=1.5)
