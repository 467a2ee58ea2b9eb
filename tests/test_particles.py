"""Physics and interface tests of fastsdf.particles (the notebook's ``phys`` module).

Every test checks a physical property or the notebook's interface; none asserts timing.
"""

import math

import numpy as np
import pytest

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf import GridSDF
from fastsdf.expr.graph import Symbol, sym_abs
from fastsdf.function import Function
from fastsdf.shapes.scenes import seed_world

G = 1.0  # |acceleration| of phys.Gravity() (the notebook's gravity)


def make_sim(f, n, **kw):
    sim = phys.ParticleSimulation(f, n=n, **kw)
    sim.force_generators += [phys.Gravity()]
    return sim


@pytest.fixture(scope="module")
def floor():
    """The half-plane y <= 0 (solid below)."""
    return sdf.Halfspace(normal=[0, 1], d=0.0)


@pytest.fixture(scope="module")
def world():
    return seed_world()


@pytest.fixture(scope="module")
def world_grid(world):
    return GridSDF(world, bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j], mode="exact")


def apexes(ys, floor_gap=1e-3):
    """Heights of the local maxima of a bouncing trajectory."""
    return np.array(
        [
            ys[i]
            for i in range(1, len(ys) - 1)
            if ys[i] >= ys[i - 1] and ys[i] > ys[i + 1] and ys[i] > floor_gap
        ]
    )


def drop(f, dt, cr, integrator="symplectic", h=1.0, r=0.05, seconds=8.0, **kw):
    sim = make_sim(f, 1, timestep=dt, seed=0, integrator=integrator, **kw)
    p = sim.p
    p["x"] = [[0.3, h + r]]
    p["v"] = 0.0
    p["r"] = r
    p["m"] = 2.0
    p["cr"] = cr
    p["cf"] = 0.0
    ys = []
    for _ in range(int(seconds / dt)):
        sim.advance()
        ys.append(p["x"][0, 1] - r)
    return np.array(ys)


# ---------------------------------------------------------------------------------------------
# Bounces, friction, resting contact, energy.


@pytest.mark.parametrize("integrator", ["symplectic", "euler"])
def test_bounce_apex_falls_by_cr_squared(floor, integrator):
    cr = 0.8
    a = apexes(drop(floor, 1e-3, cr, integrator))[:4]
    assert len(a) == 4
    # The rebound speed is cr times the impact speed, so each apex is cr**2 of the previous one.
    np.testing.assert_allclose(a[1:] / a[:-1], cr**2, rtol=0.02)
    np.testing.assert_allclose(a[0], cr**2 * 1.0, rtol=0.02)


def test_bounce_apex_at_notebook_timestep_with_sweep(floor):
    """dt = 1/30: the ball moves farther than half its radius per step near the floor, so the
    bounces go through the sweep; the apex ratio is still about cr**2."""
    cr = 0.8
    a = apexes(drop(floor, 1 / 30, cr))[:4]
    assert len(a) == 4
    np.testing.assert_allclose(a[1:] / a[:-1], cr**2, rtol=0.1)


@pytest.mark.parametrize("sweep", [False, True])
def test_friction_and_restitution_follow_the_formula(sweep):
    """One collision with a 30-degree slope: v' = -cr v_n + (1 - cf) v_t exactly."""
    angle = math.radians(30)
    nrm = np.array([-math.sin(angle), math.cos(angle)])
    slope = sdf.Halfspace(normal=nrm, d=0.0)
    cr, cf, r = 0.7, 0.25, 0.05
    dt = 0.02 if not sweep else 0.2  # step 0.036 < r/2, or 0.36 > r/2 (swept)
    tangent = np.array([nrm[1], -nrm[0]])
    v0 = 1.5 * tangent - 1.0 * nrm  # approaching the slope
    sim = phys.ParticleSimulation(slope, n=1, timestep=dt, seed=0)  # no gravity
    p = sim.p
    p["x"] = [(r + 0.01) * nrm]
    p["v"] = [v0]
    p["r"] = r
    p["cr"] = cr
    p["cf"] = cf
    sim.advance()
    v1 = p["v"][0]
    np.testing.assert_allclose(v1 @ nrm, cr * 1.0, rtol=1e-12)
    np.testing.assert_allclose(v1 @ tangent, (1 - cf) * 1.5, rtol=1e-12)
    # Position: pushed out to cr times the penetration on the free side (no sinking).
    assert p["x"][0] @ nrm >= r - 1e-12


def test_friction_slows_a_sliding_particle_geometrically(floor):
    """A particle sliding on a floor with restitution 0 under gravity: every contact step
    multiplies its tangential speed by (1 - cf)."""
    cf = 0.1
    sim = make_sim(floor, 1, timestep=1 / 100, seed=0)
    p = sim.p
    p["x"] = [[0.0, 0.05]]
    p["r"] = 0.05
    p["v"] = [[2.0, 0.0]]
    p["cr"] = 0.0
    p["cf"] = cf
    speeds = []
    for _ in range(20):
        sim.advance()
        speeds.append(p["v"][0, 0])
    np.testing.assert_allclose(speeds, 2.0 * (1 - cf) ** np.arange(1, 21), rtol=1e-12)


@pytest.mark.parametrize("integrator", ["symplectic", "euler"])
def test_resting_particles_neither_sink_nor_climb(floor, integrator):
    n, steps = 200, 10_000
    rng = np.random.default_rng(1)
    sim = make_sim(floor, n, seed=0, integrator=integrator)
    p = sim.p
    p["r"] = rng.uniform(0.005, 0.1, n)
    p["x"][:, 0] = rng.uniform(-1, 1, n)
    p["x"][:, 1] = p["r"]
    p["v"] = 0.0
    # Explicit Euler pumps energy into a bouncing particle with cr near 1 (why it is not the
    # default); resting contact with it is tested for cr <= 0.5.
    p["cr"] = rng.uniform(0, 1 if integrator == "symplectic" else 0.5, n)
    p["cf"] = rng.uniform(0, 1, n)
    r = p["r"].copy()
    dt = sim.dt
    lowest, highest = np.inf, []
    for _ in range(steps):
        sim.advance()
        gap = p["x"][:, 1] - r
        lowest = min(lowest, float(np.min(gap / r)))
        highest.append(float(gap.max()))
    highest = np.array(highest)
    assert lowest > -0.01  # penetration < 1% of the radius
    # Micro-bounces: at most cr g dt^2 with semi-implicit Euler; explicit Euler's are larger
    # (up to about 5 g dt^2 for cr <= 0.5; for cr near 1 they grow without bound).
    bound = 1.0 if integrator == "symplectic" else 5.0
    assert highest.max() <= bound * G * dt * dt
    assert highest[-1000:].max() <= highest[:1000].max() + 1e-12  # and do not grow
    np.testing.assert_array_equal(p["v"][:, 0], 0.0)  # nothing drifts sideways


@pytest.mark.parametrize("use_grid", [False, True])
def test_energy_never_grows_beyond_one_step_of_gravity_work(world, world_grid, use_grid):
    """Bouncing in the seed world for 3000 steps with cr, cf uniform in [0, 1].

    Bound: a first-order integrator's energy error is of the order of the work gravity does in
    one step, m g |v| dt. Each particle's energy (kinetic + m g y) must never exceed its start
    value by more than m g v_max dt, where v_max is the speed it would have at the bottom of
    the funnel (y = -1.8); the total likewise.
    """
    n = 300
    sim = make_sim(world_grid if use_grid else world, n, seed=4)
    rng = np.random.default_rng(4)
    p = sim.p
    p["cr"] = rng.uniform(0, 1, n)
    p["cf"] = rng.uniform(0, 1, n)
    m = p["m"].copy()

    def energies():
        return 0.5 * m * (p["v"] ** 2).sum(axis=1) + m * G * p["x"][:, 1]

    e0 = energies()
    assert math.isclose(e0.sum(), sim.energy()["total"], rel_tol=1e-12)
    v_max = np.sqrt(2 * (e0 / m + G * 1.8))
    bound = m * G * v_max * sim.dt
    worst = np.full(n, -np.inf)
    total_worst = -np.inf
    for _ in range(3000):
        sim.advance()
        e = energies()
        worst = np.maximum(worst, e - e0)
        total_worst = max(total_worst, e.sum() - e0.sum())
    assert np.all(worst <= bound), float(np.max(worst / bound))
    assert total_worst <= bound.sum()
    assert energies().sum() < e0.sum()  # and it did dissipate


# ---------------------------------------------------------------------------------------------
# Tunnelling.


def thin_wall():
    """A vertical wall 0.02 thick, from y = -1 to 1, at x = 0 (exact box SDF)."""
    return sdf.Box(minc=[-0.01, -1.0], maxc=[0.01, 1.0])


def shoot(f, n=400, seed=0, steps=12, **kw):
    rng = np.random.default_rng(seed)
    sim = phys.ParticleSimulation(f, n=n, timestep=1 / 30, seed=seed, **kw)
    p = sim.p
    r = rng.uniform(0.005, 0.05, n)
    p["r"] = r
    p["x"][:, 0] = rng.uniform(-0.8, -0.1, n)
    p["x"][:, 1] = rng.uniform(-0.5, 0.5, n)
    speed = rng.uniform(1.0, 60.0, n)  # up to 2 length units per step
    ang = rng.uniform(-0.5, 0.5, n)
    p["v"][:, 0] = speed * np.cos(ang)
    p["v"][:, 1] = speed * np.sin(ang)
    p["cr"] = rng.uniform(0, 1, n)
    p["cf"] = rng.uniform(0, 1, n)
    # particles whose straight path would cross the wall by more than 0.1 within the run
    sim.would_cross = p["x"][:, 0] + p["v"][:, 0] * steps * sim.dt > 0.1
    max_x = np.full(n, -np.inf)
    for _ in range(steps):
        sim.advance()
        max_x = np.maximum(max_x, p["x"][:, 0])
    return sim, max_x, r


def test_thin_wall_stops_fast_particles(world):
    wall = thin_wall()
    sim, max_x, r = shoot(wall)
    assert np.all(max_x <= -0.01 - r + 1e-9)  # never touched the far side
    assert np.all(sim.p["v"][sim.would_cross, 0] <= 0)  # all bounced back


def test_thin_wall_without_the_check_is_crossed():
    sim, max_x, _ = shoot(thin_wall(), prevent_tunnelling=False)
    assert np.mean(max_x[sim.would_cross] > 0.01) > 0.5  # the notebook's step tunnels


def test_thin_wall_grid():
    wall = GridSDF(thin_wall(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j], mode="exact")
    sim, max_x, r = shoot(wall, seed=1)
    h = 4 / 399
    assert np.all(max_x <= -0.01 - r + h)  # within the grid's resolution
    assert np.all(sim.p["v"][sim.would_cross, 0] <= 0)


def test_zero_thickness_wall():
    """d = |x|: a wall of no thickness at x = 0."""
    x, y = Symbol("x"), Symbol("y")
    wall = Function(sym_abs(x), [x, y])
    sim, max_x, r = shoot(wall, seed=2, n=300, lipschitz=1.0)
    assert np.all(max_x <= -0.99 * r)
    assert np.all(sim.p["v"][sim.would_cross, 0] <= 0)


def test_point_particles_do_not_cross_a_zero_thickness_wall():
    x, y = Symbol("x"), Symbol("y")
    wall = Function(sym_abs(x), [x, y])
    sim = phys.ParticleSimulation(wall, n=200, timestep=1 / 30, seed=5, lipschitz=1.0)
    p = sim.p
    rng = np.random.default_rng(5)
    p["r"] = 0.0
    p["x"][:, 0] = rng.uniform(-0.8, -0.1, 200)
    p["v"][:, 0] = rng.uniform(1, 60, 200)
    p["v"][:, 1] = rng.uniform(-5, 5, 200)
    for _ in range(10):
        sim.advance()
        assert np.all(p["x"][:, 0] <= 1e-12)


# ---------------------------------------------------------------------------------------------
# Reproducibility, paths that must agree.


def test_same_seed_same_trajectory(world_grid):
    runs = []
    for _ in range(2):
        sim = make_sim(world_grid, 20_000, seed=7)
        sim.run(60)
        runs.append(sim.p.copy())
    for name in ("x", "v"):
        np.testing.assert_array_equal(runs[0][name], runs[1][name])
    other = make_sim(world_grid, 20_000, seed=8)
    assert not np.array_equal(other.p["x"], runs[0]["x"])


@pytest.mark.parametrize(
    "use_grid, dtype", [(False, np.float64), (True, np.float64), (True, np.float32)]
)
def test_blocking_and_skipping_do_not_change_results(world, world_grid, use_grid, dtype):
    """run(steps) processes blocks of particles for all steps at once, and skips the SDF
    query of a particle while its distance budget proves it cannot touch anything; particles
    do not interact and a skipped query would have found no contact, so any block size and
    step-by-step advancing (which never skips) give identical bits."""
    f = world_grid if use_grid else world
    a = make_sim(f, 5000, seed=9, dtype=dtype)
    b = make_sim(f, 5000, seed=9, dtype=dtype, block=10**9)
    c = make_sim(f, 5000, seed=9, dtype=dtype, block=7)
    a.run(150)
    for _ in range(150):
        b.advance()
    c.run(150)
    for name in ("x", "v"):
        np.testing.assert_array_equal(a.p[name], b.p[name])
        np.testing.assert_array_equal(a.p[name], c.p[name])


def test_notebook_parity(world, world_grid):
    """integrator='euler', collision='notebook', no sweep: the notebook's advance() to rounding."""
    for f in (world, world_grid):
        sim = make_sim(
            f, 500, seed=2, integrator="euler", collision="notebook", prevent_tunnelling=False
        )
        ref = sim.p.copy()
        for _ in range(100):
            sim.advance()
            phys.reference_step(ref, f, sim.dt, [phys.Gravity()])
        np.testing.assert_allclose(sim.p["x"], ref["x"], atol=1e-9)
        np.testing.assert_allclose(sim.p["v"], ref["v"], atol=1e-9)


def test_exact_and_grid_paths_agree(world, world_grid):
    a = make_sim(world, 2000, seed=3)
    b = make_sim(world_grid, 2000, seed=3)
    h = 4 / 399
    a.run(60)
    b.run(60)
    dist = np.linalg.norm(a.p["x"] - b.p["x"], axis=1)
    # Most particles have bounced once by now; collisions amplify the grid's small error, so
    # the tail is looser than the median.
    assert np.median(dist) < 0.1 * h
    assert np.percentile(dist, 90) < h
    # One bounce on the floor: apexes agree to the grid's accuracy.
    ya = apexes(drop(world, 1 / 240, 0.7, h=1.0, seconds=3))
    yb = apexes(drop(world_grid, 1 / 240, 0.7, h=1.0, seconds=3))
    np.testing.assert_allclose(ya[:2], yb[:2], atol=0.1 * h)


def test_kernel_query_matches_the_sdf(world, world_grid):
    rng = np.random.default_rng(0)
    xs, ys = rng.uniform(-2.5, 2.5, (2, 500))  # some outside the grid's bounds
    sim = phys.ParticleSimulation(world, n=1)
    d, g = sim.query(xs, ys)
    d0, g0 = world(xs, ys, compute_gradient=True)
    np.testing.assert_array_equal(d, d0)
    np.testing.assert_array_equal(g, g0)
    simg = phys.ParticleSimulation(world_grid, n=1)
    d, g = simg.query(xs, ys)
    d1, g1 = world_grid(xs, ys, compute_gradient=True)
    np.testing.assert_allclose(d, d1, atol=1e-12)
    outside = (np.abs(xs) > 2) | (np.abs(ys) > 2)
    np.testing.assert_array_equal(d[outside], d0[outside])  # mode 'exact': the exact SDF
    nearest = GridSDF(world, bounds=[(-2, 2), (-2, 2)], samples=[100j, 100j], mode="nearest")
    simn = make_sim(nearest, 300, seed=0)
    d, g = simn.query(xs, ys)
    d2, g2 = nearest(xs, ys, compute_gradient=True)
    np.testing.assert_allclose(d, d2, atol=1e-12)
    simn.p["v"] *= 30  # many leave the grid's bounds
    simn.run(100)
    assert np.all(np.isfinite(simn.p["x"]))


def test_grid_with_a_sampler_that_cannot_be_imported(world, world_grid):
    """A GridSDF-like object whose sampler is made at run time (not importable by name): the
    kernel binds it without the disk cache and agrees with the real grid."""
    from numba import njit

    real = world_grid.sampler

    def make():
        @njit
        def sampler(data, x, y):
            return real(data, x, y)

        return sampler

    class Wrapped:
        exact, mode, spacing = world_grid.exact, world_grid.mode, world_grid.spacing
        sampler_data = world_grid.sampler_data
        sampler = make()

        def __call__(self, x, y, compute_gradient=False):
            return world_grid(x, y, compute_gradient)

    a = make_sim(Wrapped(), 300, seed=1)
    b = make_sim(world_grid, 300, seed=1)
    a.run(100)
    b.run(100)
    np.testing.assert_array_equal(a.p["x"], b.p["x"])


def test_python_generator_agrees_with_fused_gravity_and_drag(world):
    def gravity(p, t):
        """The notebook's gravity."""
        return p["m"][:, np.newaxis] * np.array([0, -1])

    def drag(p, t):
        return -0.3 * p["v"]

    fused = phys.ParticleSimulation(world, n=300, seed=6)
    fused.force_generators += [phys.Gravity(), phys.Drag(0.3)]
    slow = phys.ParticleSimulation(world, n=300, seed=6)
    slow.force_generators += [gravity, drag]
    mixed = phys.ParticleSimulation(world, n=300, seed=6)
    mixed.force_generators += [phys.Gravity(), drag]
    for _ in range(40):
        fused.advance()
        slow.advance()
    mixed.run(40)
    for other in (slow, mixed):
        np.testing.assert_allclose(other.p["x"], fused.p["x"], atol=1e-9)
        np.testing.assert_allclose(other.p["v"], fused.p["v"], atol=1e-9)
    assert math.isclose(slow.t, 40 / 30) and math.isclose(fused.t, 40 / 30)


def test_drag_reaches_terminal_velocity():
    free = sdf.Halfspace(normal=[0, 1], d=-1e6)  # nothing to hit
    sim = phys.ParticleSimulation(free, n=50, timestep=1 / 100, seed=0)
    c = 2.0
    sim.force_generators += [phys.Gravity(), phys.Drag(c)]
    sim.run(10_000)  # 20 time constants m / c
    # m dv/dt = -m g - c v  ->  v_terminal = -m g / c
    np.testing.assert_allclose(sim.p["v"][:, 1], -sim.p["m"] * G / c, rtol=1e-6)


def test_float32_state_tracks_float64(world):
    a = make_sim(world, 1000, seed=11)
    b = make_sim(world, 1000, seed=11, dtype=np.float32)
    assert b.p["x"].dtype == np.float32 and b.p.nbytes == 32 * 1000
    assert a.p.nbytes == 64 * 1000
    a.run(30)  # free fall: no collisions yet
    b.run(30)
    np.testing.assert_allclose(b.p["x"], a.p["x"], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# The notebook's interface.


def test_notebook_interface(world):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def gravity(p, t):
        return p["m"][:, np.newaxis] * np.array([0, -1])

    ps = phys.ParticleSimulation(world, n=100, timestep=1 / 30, seed=0)
    ps.force_generators += [gravity]
    p = ps.p
    for name, shape in (
        ("x", (100, 2)),
        ("v", (100, 2)),
        ("m", (100,)),
        ("r", (100,)),
        ("cr", (100,)),
        ("cf", (100,)),
    ):
        assert p[name].shape == shape
    np.testing.assert_allclose(p["r"], 0.01 * p["m"])
    assert np.all((p["m"] >= 1) & (p["m"] <= 10))
    assert abs(p["x"][:, 1].mean() - 1.5) < 0.1
    rec = p.as_structured()
    np.testing.assert_array_equal(rec["x"], p["x"])
    fig, ax = plt.subplots()
    anim = phys.create_animation(fig, ax, ps, frames=3, repeat=True, use_wall_time=False)
    html = anim.to_jshtml()
    assert "<img" in html or "frames" in html
    assert ps.t > 0
    ps.reset(ax)
    assert ps.t == 0
    np.testing.assert_array_equal(ps.p["x"], phys.ParticleSimulation(world, n=100, seed=0).p["x"])
    (drawable,) = ps.update(ax, use_wall_time=True)
    np.testing.assert_allclose(drawable.get_offsets(), ps.p["x"])
    plt.close(fig)

    # the notebook's own SimpleParticleSimulation: reset returns nothing, update its drawable
    class Simple:
        def __init__(self):
            self.drawable, self.dt, self.frames = None, 1 / 30, 0

        def reset(self, ax):
            self.drawable = ax.scatter([0.0], [0.0])

        def update(self, ax, use_wall_time):
            self.frames += 1
            self.drawable.set_offsets([[0.0, -0.1 * self.frames]])
            return (self.drawable,)

    fig, ax = plt.subplots()
    simple = Simple()
    phys.create_animation(fig, ax, simple, frames=3, repeat=False).to_jshtml()
    assert simple.frames >= 3
    plt.close(fig)
    # many particles: a density image instead of circles
    fig, ax = plt.subplots()
    ax.set_xlim(-2, 2)
    ax.set_ylim(-2, 2)
    big = phys.ParticleSimulation(world, n=20_000, seed=0)
    (image,) = big.reset(ax)
    (image,) = big.update(ax)
    assert image.get_array().sum() > 0.9 * 20_000
    plt.close(fig)


def test_assigning_another_world_rebinds_the_step(floor):
    sim = phys.ParticleSimulation(floor, n=1, timestep=0.01, seed=0)
    sim.p["x"] = [[0.0, 0.5]]
    sim.p["v"] = 0.0
    sim.p["r"] = 0.05
    sim.advance()
    assert sim.p["x"][0, 1] == 0.5
    sim.sdf = sdf.Halfspace(normal=[0, 1], d=1.0)  # the floor rises to y = 1
    sim.advance()
    assert sim.p["x"][0, 1] >= 1.05 - 1e-12  # pushed out of the new floor
    with pytest.raises(TypeError, match="f must be a fastsdf SDF"):
        sim.sdf = "floor"


def test_user_writes_state_before_stepping(floor):
    sim = phys.ParticleSimulation(floor, n=3, timestep=0.1, seed=0)
    sim.p["x"] = [[0, 1], [1, 1], [2, 1]]
    sim.p["v"] = [1.0, 0.0]  # broadcast
    sim.p.m[:] = 2.0  # in place, attribute access
    sim.advance()
    np.testing.assert_allclose(sim.p["x"], [[0.1, 1], [1.1, 1], [2.1, 1]])


# ---------------------------------------------------------------------------------------------
# Bad input: clear errors naming the parameter, no corruption of valid particles.


@pytest.mark.parametrize(
    "kw, exc, words",
    [
        ({"n": 0}, ValueError, "n must be > 0"),
        ({"n": -5}, ValueError, "n=-5"),
        ({"n": 2.5}, TypeError, "n must be an integer"),
        ({"n": True}, TypeError, "n must be an integer"),
        ({"timestep": 0}, ValueError, "timestep"),
        ({"timestep": -0.1}, ValueError, "timestep=-0.1"),
        ({"timestep": float("nan")}, ValueError, "timestep=nan"),
        ({"timestep": float("inf")}, ValueError, "timestep=inf"),
        ({"timestep": "fast"}, TypeError, "timestep"),
        ({"cr": 1.5}, ValueError, "cr=1.5"),
        ({"cf": -0.1}, ValueError, "cf=-0.1"),
        ({"integrator": "rk4"}, ValueError, "integrator='rk4'"),
        ({"collision": "elastic"}, ValueError, "collision='elastic'"),
        ({"dtype": np.int32}, ValueError, "dtype"),
        ({"lipschitz": 0}, ValueError, "lipschitz=0"),
        ({"block": 0}, ValueError, "block=0"),
    ],
)
def test_bad_parameters(floor, kw, exc, words):
    args = {"n": 10, **kw}
    with pytest.raises(exc, match=words.replace("(", r"\(").replace(")", r"\)")):
        phys.ParticleSimulation(floor, **args)


def test_world_without_a_known_lipschitz_bound_warns():
    x, y = Symbol("x"), Symbol("y")
    bare = Function(sym_abs(x) - 0.1, [x, y])
    with pytest.warns(RuntimeWarning, match="not known to be a distance bound"):
        sim = phys.ParticleSimulation(bare, n=10)
    assert not sim.engine.skip
    rough = sdf.SDF(sym_abs(x) * 3.0 - 0.1)  # steeper than a distance
    assert rough.exactness == "none"
    with pytest.warns(RuntimeWarning, match="exactness 'none'"):
        phys.ParticleSimulation(rough, n=10)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim = phys.ParticleSimulation(rough, n=10, lipschitz=3.0)
        phys.ParticleSimulation(rough, n=10, prevent_tunnelling=False)
    assert sim.engine.skip and sim.lipschitz == 3.0


def test_bad_world():
    with pytest.raises(TypeError, match="f must be a fastsdf SDF"):
        phys.ParticleSimulation(lambda x, y: x, n=3)


def test_bad_force_generator_names_the_generator(floor):
    def wrong_shape(p, t):
        return np.zeros((len(p), 3))

    def not_finite(p, t):
        f = np.zeros((len(p), 2))
        f[2, 1] = np.nan
        return f

    sim = phys.ParticleSimulation(floor, n=5, seed=0)
    before = sim.p.copy()
    sim.force_generators = [wrong_shape]
    with pytest.raises(ValueError, match=r"wrong_shape.*\(5, 2\).*\(5, 3\)"):
        sim.advance()
    sim.force_generators = [not_finite]
    with pytest.raises(ValueError, match=r"not_finite.*particle 2"):
        sim.advance()
    sim.force_generators = [lambda p, t: "up"]
    with pytest.raises(TypeError, match="lambda"):
        sim.advance()
    sim.force_generators = [42]
    with pytest.raises(TypeError, match="force_generators"):
        sim.advance()
    np.testing.assert_array_equal(sim.p["x"], before["x"])  # nothing moved
    assert sim.t == 0
    with pytest.raises(ValueError, match="coefficient"):
        phys.Drag(-1)
    with pytest.raises(ValueError, match="acceleration"):
        phys.Gravity([0, np.inf])


@pytest.mark.parametrize(
    "field, index, value, words",
    [
        ("x", 3, [np.nan, 0.0], r"p\['x'\]\[3\] = \[nan, 0.0\] must be finite"),
        ("v", 1, [0.0, np.inf], r"p\['v'\]\[1\].*must be finite"),
        ("m", 4, -2.0, r"p\['m'\]\[4\] = -2.0 must be finite and > 0"),
        ("m", 0, 0.0, r"p\['m'\]\[0\] = 0.0"),
        ("r", 2, -0.1, r"p\['r'\]\[2\] = -0.1 must be finite and >= 0"),
        ("cr", 5, 1.2, r"p\['cr'\]\[5\] = 1.2 must be in \[0, 1\]"),
        ("cf", 6, -0.5, r"p\['cf'\]\[6\] = -0.5 must be in \[0, 1\]"),
    ],
)
@pytest.mark.parametrize("n", [10, 5000])  # serial and parallel kernels
def test_invalid_state_is_reported_and_isolated(world, field, index, value, words, n):
    good = make_sim(world, n, seed=12)
    bad = make_sim(world, n, seed=12)
    bad.p[field][index] = value
    with pytest.raises(ValueError, match=words):
        bad.run(5)
    good.run(5)
    keep = np.ones(n, bool)
    keep[index] = False
    for name in ("x", "v"):  # the other particles advanced exactly as without the bad one
        np.testing.assert_array_equal(bad.p[name][keep], good.p[name][keep])
    assert (
        np.array_equal(bad.p["x"][index], make_sim(world, n, seed=12).p["x"][index]) or field == "x"
    )  # the bad one was left unchanged


def test_state_assignment_errors(floor):
    sim = phys.ParticleSimulation(floor, n=4)
    with pytest.raises(ValueError, match=r"p\['x'\] has shape \(4, 2\)"):
        sim.p["x"] = np.zeros((3, 2))
    with pytest.raises(TypeError, match="real numbers"):
        sim.p["m"] = "heavy"
    with pytest.raises(KeyError, match="no particle field 'q'"):
        sim.p["q"]
    with pytest.raises(ValueError, match="steps must be >= 0"):
        sim.run(-1)
    with pytest.raises(TypeError, match="steps must be an integer"):
        sim.run(1.5)
