"""Sorting force generators (``fastsdf.particles.forces.fuse``): what is fused, what runs in
Python, and the errors that say what a force must look like."""

import numpy as np
import pytest
from numba import njit

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.particles.forces import fuse


@njit
def _push(x, y, vx, vy, m, t):
    return 0.1 * m, 0.0


@njit
def _three(x, y, t):
    return 0.0, 0.0


def _py_force(p, t):
    return np.zeros((len(p), 2))


def test_fuse_sums_gravity_and_drag_and_sorts_the_rest():
    field = phys.FieldForce(1.0, 0.0)
    forces = fuse(
        [
            phys.Gravity((0.5, -2.0)),
            phys.Gravity((0.25, 0.0)),
            phys.Drag(0.3),
            phys.Drag(0.2),
            _push,
            field,
            _py_force,
        ]
    )
    assert (forces.ax, forces.ay, forces.drag) == (0.75, -2.0, 0.5)
    assert forces.user == (_push, field.dispatcher)
    assert forces.python == [_py_force]


@pytest.mark.parametrize("cls", [phys.Gravity, phys.Drag, phys.FieldForce])
def test_a_force_class_without_parentheses_is_refused(cls):
    name = cls.__name__
    with pytest.raises(
        TypeError,
        match=rf"force_generators\[1\] is the class {name}, not a "
        rf"force; add an instance: {name}\(\)",
    ):
        fuse([phys.Gravity(), cls])


def test_callables_of_the_wrong_arity_are_refused():
    with pytest.raises(
        TypeError,
        match=r"force_generators\[0\]: the force generator "
        r".*<lambda> must take \(p, t\).*\(p\)",
    ):
        fuse([lambda p: p["m"]])
    with pytest.raises(TypeError, match=r"numba force _three must take \(x, y, vx, vy, m, t\)"):
        fuse([_three])
    with pytest.raises(TypeError, match=r"force_generators\[0\] is not a force: got 3.0"):
        fuse([3.0])


def test_the_simulation_refuses_a_bad_force_before_stepping():
    sim = phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=2, seed=0)
    x0 = sim.p["x"].copy()
    sim.force_generators.append(phys.Gravity)
    with pytest.raises(TypeError, match="add an instance: Gravity()"):
        sim.run(1)
    assert sim.t == 0.0
    np.testing.assert_array_equal(sim.p["x"], x0)
