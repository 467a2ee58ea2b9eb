"""Moving walls in the particle step: the world evaluated at the simulation's time, the response
relative to the wall's velocity (v_wall . n = -dd/dt / |grad d|), sweeps that see the walls move."""

import numpy as np
import pytest

import fastsdf as sdf
import fastsdf.particles as phys


def _sim(world, x, v, r, cr, cf=0.0, dt=1 / 60, params=None, **kw):
    n = len(x)
    sim = phys.ParticleSimulation(world, n=n, timestep=dt, seed=0, **kw)
    sim.params.update(params or {})
    sim.p["x"] = x
    sim.p["v"] = v
    sim.p["r"] = r
    sim.p["m"] = 1.0
    sim.p["cr"] = cr
    sim.p["cf"] = cf
    return sim


# The walls' positions and speeds are parameters: every test shares one kernel per world.
PISTON = sdf.Halfspace(normal=[1, 0], d=sdf.Param("x0", -1.0) + sdf.Param("u", 0.5) * sdf.t)
FLOOR = sdf.Halfspace(normal=[0, 1], d=sdf.Param("y0", -1.0) + sdf.Param("u", 0.5) * sdf.t)


@pytest.mark.parametrize("cr, factor", [(0.0, 1.0), (1.0, 2.0)])
def test_piston_pushes_a_resting_particle_at_its_speed(cr, factor):
    # cr = 0: pushed along at the piston's speed; cr = 1: an elastic kick to twice that speed
    # (the reflection of the relative velocity off an infinitely heavy wall).
    u, r = 0.6, 0.05
    x = np.array([[-1.0 + r + 0.1, 0.0], [-1.0 + r + 0.3, 0.5]])
    sim = _sim(PISTON, x, np.zeros((2, 2)), r, cr, params={"u": u, "x0": -1.0})
    assert sim.engine.moving and sim.params == {"u": u, "x0": -1.0}
    sim.run(120)  # 2 s: the piston has moved 1.2, past both starting points
    v = np.asarray(sim.p["v"])
    np.testing.assert_allclose(v[:, 0], factor * u, rtol=1e-9)
    np.testing.assert_allclose(v[:, 1], 0.0, atol=1e-12)
    d, _ = sim.query(sim.p["x"][:, 0], sim.p["x"][:, 1])
    assert np.all(d - r >= -1e-9)
    if cr == 0.0:  # riding on the piston's face
        np.testing.assert_allclose(sim.p["x"][:, 0], -1.0 + u * sim.t + r, atol=1e-9)


@pytest.mark.parametrize("u, n", [pytest.param(0.3, 4096, marks=pytest.mark.slow), (3.0, 64)])
def test_rising_floor_lifts_a_resting_particle_without_penetrating(u, n):
    # u = 3: the floor moves 5 radii per step, the sweep must see it coming. n = 4096: the
    # parallel kernel.
    r, dt = 0.01, 1 / 60
    x = np.stack([np.linspace(-1, 1, n), np.full(n, -1.0 + r)], axis=1)
    sim = _sim(
        FLOOR,
        x,
        np.zeros((n, 2)),
        r,
        cr=np.linspace(0, 1, n),
        cf=0.3,
        dt=dt,
        params={"u": u, "y0": -1.0},
    )
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    worst = 0.0
    for _ in range(90):
        sim.run(1)
        floor = -1.0 + u * sim.t
        worst = min(worst, float(np.min(sim.p["x"][:, 1] - r - floor)))
    assert worst >= -0.01 * r
    # Lifted with the floor: everyone is above it and has risen by at least u * t (minus a
    # bounce's worth for the springy ones, which fly above it).
    assert np.all(sim.p["x"][:, 1] >= -1.0 + u * sim.t + r - 0.01 * r)
    assert np.all(np.abs(sim.p["x"][:, 0] - x[:, 0]) < 1e-12)


def test_energy_bookkeeping_against_a_wall_moving_into_particles():
    # One collision each with a wall moving at u toward particles moving at -w: the kinetic
    # energy gained is the wall's work J u minus the loss in the wall's frame,
    # (1 - cr^2) m vr^2 / 2, with J = m (v' - v) the impulse and vr the relative speed.
    rng = np.random.default_rng(3)
    n, u, r = 400, 0.8, 0.02
    w = rng.uniform(0.1, 30.0, n)  # up to 1.5 radii ... 25 radii per step
    cr = rng.uniform(0.2, 1.0, n)
    dt = 1 / 30
    gap = rng.uniform(0.0, 0.95, n) * (w + u) * dt  # contact during the first step
    x = np.stack([-1.0 + r + gap, rng.uniform(-1, 1, n)], axis=1)
    v = np.stack([-w, np.zeros(n)], axis=1)
    m = rng.uniform(1, 5, n)
    sim = _sim(PISTON, x, v, r, cr, dt=dt, params={"u": u, "x0": -1.0})
    sim.p["m"] = m
    sim.run(3)  # everyone has hit the wall once and left it faster than it moves
    v1 = np.asarray(sim.p["v"])[:, 0]
    vr = -w - u
    np.testing.assert_allclose(v1, u - cr * vr, rtol=1e-9)
    gained = 0.5 * m * (v1**2 - w**2)
    work = m * (v1 + w) * u
    loss = 0.5 * (1 - cr**2) * m * vr**2
    np.testing.assert_allclose(gained, work - loss, rtol=1e-9, atol=1e-9)
    assert np.all(v1 > u)


def test_parameters_in_the_simulation_never_recompile():
    # A piston whose speed is a parameter: sim.params changes it between calls.
    speed = sdf.Param("speed", 0.5)
    world = sdf.Halfspace(normal=[1, 0], d=-1.0 + speed * sdf.t) | sdf.Circle(
        center=[sdf.Param("cx", 0.5), 0.0], radius=0.2
    )
    r = 0.05
    x = np.array([[-1.0 + r + 0.01, 0.0], [0.5 + 0.2 + r + 0.3, 0.0]])
    sim = _sim(world, x, np.array([[0.0, 0.0], [-1.0, 0.0]]), r, 0.0, dt=1 / 60)
    assert sim.params == {"speed": 0.5, "cx": 0.5}
    sim.run(30)
    mod = sim.engine.kernel()[0]
    count = sum(len(getattr(mod, k).overloads) for k in ("step_ser", "_block"))
    sim.params["speed"] = 1.5
    sim.params["cx"] = -5.0  # the circle leaves
    sim.run(30)
    np.testing.assert_allclose(sim.p["v"][0, 0], 1.5, rtol=1e-9)
    d, _ = sim.query(sim.p["x"][:, 0], sim.p["x"][:, 1])
    np.testing.assert_allclose(d[0], r, atol=1e-9)  # riding on the piston
    # the circle has gone: only the piston is left
    np.testing.assert_allclose(d[1], sim.p["x"][1, 0] - (-1.0 + 1.5 * sim.t), atol=1e-12)
    assert sum(len(getattr(mod, k).overloads) for k in ("step_ser", "_block")) == count
    with pytest.raises(KeyError, match="unknown parameter 'angle'"):
        sim.params["angle"] = 1.0
    with pytest.raises(ValueError, match="finite"):
        sim.params["speed"] = float("nan")
    with pytest.raises(ValueError, match="wall_speed"):
        phys.ParticleSimulation(world, n=4, wall_speed=-1.0)


@pytest.mark.parametrize("calls", [20, 1])
def test_fast_wall_never_tunnels_through_particles(calls):
    # A thin bar (2 radii thick) rising at 10 radii per step through a box of particles at
    # rest: most start nearer a static wall than the bar (their region's wall speed is 0 until
    # the bar comes near), yet every one ends above the bar. calls = 20: one step per call (a
    # new wall-speed table each step); 1: all 20 steps in one call (the table covers them).
    u, r, dt = 6.0, 0.01, 1 / 60
    box = (
        sdf.Halfspace(normal=[0, 1], d=-1.2)
        | sdf.Halfspace(normal=[0, -1], d=-1.2)
        | sdf.Halfspace(normal=[1, 0], d=-1.2)
        | sdf.Halfspace(normal=[-1, 0], d=-1.2)
    )
    lift = sdf.Param("y0", -1.1) + sdf.Param("u", 1.0) * sdf.t
    with sdf.transform(offset=[0.0, lift]):
        bar = sdf.Box(minc=[-1.15, -r], maxc=[1.15, r])
    gx, gy = np.meshgrid(np.linspace(-1.1, 1.1, 45), np.linspace(-0.9, 0.8, 24))
    x = np.stack([gx.ravel(), gy.ravel()], axis=1)
    n = len(x)
    sim = _sim(
        box | bar,
        x,
        np.zeros((n, 2)),
        r,
        cr=np.linspace(0, 1, n) ** 2,
        dt=dt,
        params={"u": u, "y0": -1.1},
    )
    for _ in range(calls):
        sim.run(20 // calls)
    top = -1.1 + u * sim.t + r  # the bar's upper face, now at y = 0.91
    y = np.asarray(sim.p["x"])[:, 1]
    assert np.all(y - r >= top - 0.01 * r), np.min(y - r - top)
    d, _ = sim.query(sim.p["x"][:, 0], sim.p["x"][:, 1])
    assert np.all(d - r >= -0.01 * r)
