"""Direct tests of the step kernels ``fastsdf.particles.kernels`` (their own test world:
half-planes and discs), of the kernels generated from them, of fused user forces and of the
clock/state rules.

Every test checks a property against an independent computation (analytic geometry, a NumPy
step, the slow Python-force path).
"""

import math

import numba
import numpy as np
import pytest
from numba import njit

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf import GridSDF
from fastsdf.particles import kernels as _step
from fastsdf.particles.forces import fuse
from fastsdf.particles.kernels import constants as C
from fastsdf.shapes.scenes import seed_world

#: The kernel variants by their switches (simd, plain): see fastsdf.particles.kernels.step.
VARIANTS = {(None, None): "general", (None, True): "plain", (True, None): "simd"}
VARIANTS[True, True] = "simd_plain"


def compiled_variants(module, entry="step_ser"):
    """The variants of ``module``'s entry point compiled (or loaded) in this process."""
    done = set()
    for sig in getattr(module, entry).signatures:
        simd, plain = (None if isinstance(t, numba.types.NoneType) else True for t in sig[-2:])
        done.add(VARIANTS[simd, plain])
    return done


def world(planes=(), discs=()):
    """Query data of _step's test world."""
    return (
        np.array(planes, dtype=np.float64).reshape(-1, 3),
        np.array(discs, dtype=np.float64).reshape(-1, 3),
    )


FLOOR = world(planes=[(0.0, 1.0, 0.0)])  # solid where y <= 0


# ---------------------------------------------------------------------------------------------
# The parts, called directly.


def test_query_of_the_test_world_is_the_analytic_distance():
    data = world(planes=[(0.0, 1.0, -1.0)], discs=[(0.0, 0.0, 0.5)])
    rng = np.random.default_rng(0)
    xs, ys = rng.uniform(-2, 2, (2, 500))
    out = np.empty((500, 3))
    _step.query_many(data, xs, ys, out)
    r = np.hypot(xs, ys)
    expect = np.minimum(ys + 1.0, r - 0.5)
    np.testing.assert_allclose(out[:, 0], expect, atol=1e-14)
    disc = r - 0.5 < ys + 1.0
    np.testing.assert_allclose(out[disc, 1], (xs / r)[disc], atol=1e-14)
    np.testing.assert_allclose(out[~disc, 2], 1.0)


@pytest.mark.parametrize("always", [False, True])
def test_respond_matches_house_keyser(always):
    rng = np.random.default_rng(1)
    for _ in range(200):
        x, y, vx, vy = rng.normal(size=4)
        s = -abs(rng.normal()) * 0.1
        gx, gy = rng.normal(size=2) * rng.uniform(0.2, 3.0)
        cr, cf = rng.uniform(0, 1, 2)
        # a moving wall (dd/dt = gt) half of the time
        gt = rng.normal() if rng.uniform() < 0.5 else 0.0
        got = _step._respond(x, y, vx, vy, s, (gx, gy, gt), cr, cf, always)
        n = np.array([gx, gy]) / math.hypot(gx, gy)
        w = -gt / math.hypot(gx, gy)  # the wall's normal speed
        v = np.array([vx, vy])
        vn = v @ n
        xe = np.array([x, y]) - (1 + cr) * s * n
        # the velocity relative to the wall reflects
        ve = (w - cr * (vn - w)) * n + (1 - cf) * (v - vn * n) if (vn < w or always) else v
        np.testing.assert_allclose(got[:2], xe, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(got[2:], ve, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("g", [(0.0, 0.0), (math.nan, 1.0), (math.inf, 0.0)])
def test_respond_without_a_direction_leaves_the_state(g):
    assert _step._respond(0.1, 0.2, -0.3, 0.4, -0.05, (g[0], g[1], 0.0), 0.5, 0.5, True) == (
        0.1,
        0.2,
        -0.3,
        0.4,
    )


def test_march_stops_at_the_first_contact_along_the_segment():
    # A disc of radius 0.1 moving right towards a wall at x = 1 (solid x >= 1).
    data = world(planes=[(-1.0, 0.0, -1.0)])
    t, hit, s, nx, ny = _step._march(data, 0.0, 0.0, 2.0, 0.0, 0.1, 1.0, 0.0, 1.0)
    assert hit == 1
    contact = 0.9 / 2.0  # x + r = 1
    assert contact - 1e-3 <= t <= contact + 1e-9
    assert abs(s) <= C.CONTACT_TOL * 2.0
    assert (nx, ny) == (-1.0, 0.0)


def test_march_free_path_and_known_free_part():
    data = world(planes=[(-1.0, 0.0, -5.0)])
    assert _step._march(data, 0.0, 0.0, 2.0, 0.0, 0.1, 1.0, 0.0, 1.0)[:2] == (1.0, 0)
    # Everything from t_free on is known free: nothing is queried beyond it.
    data = world(planes=[(-1.0, 0.0, -1.0)])
    assert _step._march(data, 0.0, 0.0, 2.0, 0.0, 0.1, 1.0, 0.0, 0.2)[:2] == (1.0, 0)


def test_sweep_reflects_off_a_thin_disc():
    # A point-sized particle flying through a small disc would cross it in one step.
    data = world(discs=[(1.0, 0.0, 0.05)])
    x, y, dx, dy, vx, vy, bounced = _step._sweep(
        data,
        _step.Motion(x=0.0, y=0.0, dx=2.0, dy=0.0, vx=60.0, vy=0.0),
        _step.Disc(r=0.01, cr=1.0, cf=0.0),
        1.0,
        False,
        0.0,
        1.0,
    )
    assert bounced
    assert vx < 0.0  # reflected (cr = 1: elastic)
    assert x + dx < 1.0 - 0.05  # the end point is back in front of the disc


def test_borrow_all_keeps_values():
    @njit
    def total(data):
        b = _step.borrow_all(data)
        return b[0].sum() + b[1] + b[2][1]

    a = np.arange(5.0)
    assert total((a, 2.0, (np.ones(3), 7))) == 10.0 + 2.0 + 7


# ---------------------------------------------------------------------------------------------
# The whole kernel on the test world.


def kernel_args(n, x, v, r=0.05, m=1.0, cr=0.5, cf=0.2):
    X = np.array(x, dtype=np.float64).reshape(n, 2).copy()
    V = np.array(v, dtype=np.float64).reshape(n, 2).copy()
    full = lambda val: np.full(n, val, dtype=np.float64)
    return X, V, full(m), full(r), full(cr), full(cf)


def run_kernel(
    data,
    steps,
    X,
    V,
    M,
    R,
    CR,
    CF,
    dt=0.01,
    g=(0.0, -1.0),
    trace=True,
    skip=True,
    block=7,
    explicit=False,
    always=False,
):
    flags = np.zeros(X.shape[0], np.uint8)
    state = _step.State(X, V, M, R, CR, CF, np.zeros((0, 2)), flags, True)
    physics = _step.Physics(
        dt=dt,
        t0=0.0,
        ax=g[0],
        ay=g[1],
        drag=0.0,
        use_m=False,
        use_ext=False,
        explicit=explicit,
        always=always,
        rest=0.0,
    )
    budget = _step.Budget(trace=trace, lip=1.0, margin=0.0, eps=2.2e-16, skip=skip)
    bad = _step.step_ser(data, state, physics, budget, steps, block, None, None)
    return bad, flags


def test_free_fall_is_semi_implicit_euler():
    n = 5
    X, V, M, R, CR, CF = kernel_args(n, np.c_[np.arange(n), np.full(n, 10.0)], np.ones((n, 2)))
    x0, v0 = X.copy(), V.copy()
    steps, dt = 50, 0.01
    bad, _ = run_kernel(FLOOR, steps, X, V, M, R, CR, CF, dt=dt)
    assert bad == 0
    k = np.arange(1, steps + 1)
    np.testing.assert_allclose(V[:, 1], v0[:, 1] - steps * dt)
    np.testing.assert_allclose(X[:, 1], x0[:, 1] + dt * np.sum(v0[0, 1] - k * dt), rtol=1e-12)
    np.testing.assert_allclose(X[:, 0], x0[:, 0] + steps * dt * v0[:, 0], rtol=1e-12)


def test_particles_come_to_rest_on_the_floor_of_the_test_world():
    n = 40
    rng = np.random.default_rng(3)
    X, V, M, R, CR, CF = kernel_args(
        n,
        np.c_[rng.uniform(-1, 1, n), rng.uniform(0.2, 1, n)],
        rng.normal(size=(n, 2)),
        cr=0.3,
        cf=0.5,
    )
    run_kernel(FLOOR, 3000, X, V, M, R, CR, CF)
    assert np.all(X[:, 1] - R >= -1e-4)  # out of the floor
    assert np.all(X[:, 1] - R <= 2e-3)  # and resting on it
    assert np.all(np.abs(V[:, 1]) < 0.02)


def test_grouping_of_steps_and_blocks_does_not_change_results():
    n = 30
    rng = np.random.default_rng(4)
    data = world(
        planes=[(0.0, 1.0, 0.0), (0.7071067811865476, 0.7071067811865476, -0.5)],
        discs=[(0.3, 0.4, 0.2)],
    )
    args = kernel_args(
        n, np.c_[rng.uniform(-1, 1, n), rng.uniform(0.5, 1.5, n)], rng.normal(size=(n, 2))
    )
    a = [arr.copy() for arr in args]
    b = [arr.copy() for arr in args]
    run_kernel(data, 60, *a, block=3)
    for _ in range(6):
        run_kernel(data, 10, *b, block=64)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_kernel_flags_invalid_particles_and_non_finite_steps():
    n = 4
    X, V, M, R, CR, CF = kernel_args(n, [[0, 1]] * n, [[0, 0]] * n)
    X[1, 0] = math.nan
    CR[2] = 2.0
    bad, flags = run_kernel(FLOOR, 3, X, V, M, R, CR, CF)
    assert bad == 2 and flags.tolist() == [0, C.FLAG_INPUT, C.FLAG_INPUT, 0]
    # A step that overflows is not stored: the particle keeps its last finite state.
    X, V, M, R, CR, CF = kernel_args(1, [[0, 1]], [[1e300, 0]])
    bad, flags = run_kernel(FLOOR, 2, X, V, M, R, CR, CF, dt=1e10, g=(0.0, 0.0))
    assert bad == 1 and flags[0] == C.FLAG_NONFINITE
    assert X.tolist() == [[0.0, 1.0]] and V.tolist() == [[1e300, 0.0]]


def _mixed_state(seed, n=96):
    """Particles resting on the floor (the first third), falling from high up (the second)
    and bouncing among the test world's walls (the rest), with some invalid ones."""
    rng = np.random.default_rng(seed)
    k = n // 3
    x = np.c_[
        rng.uniform(-1, 1, n),
        np.r_[rng.uniform(0.049, 0.051, k), rng.uniform(5, 6, k), rng.uniform(0.1, 1.5, n - 2 * k)],
    ]
    v = np.r_[rng.normal(scale=0.01, size=(k, 2)), rng.normal(size=(n - k, 2))]
    X, V, M, R, CR, CF = kernel_args(n, x, v)
    M[:] = rng.uniform(0.5, 2.0, n)
    R[:] = rng.uniform(0.02, 0.08, n)
    CR[:] = rng.uniform(0.0, 1.0, n)
    CF[:] = rng.uniform(0.0, 1.0, n)
    X[5, 1] = math.nan  # invalid input
    CR[7] = 1.5  # invalid cr, found at its first contact
    CF[n - 3] = -0.1
    return X, V, M, R, CR, CF


@pytest.mark.parametrize(
    "explicit, always, drag, ext",
    [(False, False, 0.0, False), (True, True, 0.3, False), (False, False, 0.0, True)],
)
@pytest.mark.parametrize("block", [5, 64])
def test_plain_kernel_gives_the_general_kernels_results(explicit, always, drag, ext, block):
    # Without skipping and the tunnelling check, calls take the plain variant (a straight
    # and a batched step chosen by the contact count): bit-identical states, flags and counts.
    data = world(
        planes=[(0.0, 1.0, 0.0), (0.7071067811865476, 0.7071067811865476, -0.5)],
        discs=[(0.3, 0.4, 0.2)],
    )
    base = _mixed_state(11)
    n = base[0].shape[0]
    E = np.random.default_rng(2).normal(size=(n, 2)) if ext else np.zeros((0, 2))
    out = []
    for plain in (None, True):
        X, V, M, R, CR, CF = [a.copy() for a in base]
        flags = np.zeros(n, np.int32)
        # check_all off: cr, cf are checked at contacts
        state = _step.State(X, V, M, R, CR, CF, E, flags, False)
        physics = _step.Physics(
            dt=0.01,
            t0=0.0,
            ax=0.0,
            ay=-1.0,
            drag=drag,
            use_m=drag != 0.0 or ext,
            use_ext=ext,
            explicit=explicit,
            always=always,
            rest=0.0,
        )
        budget = _step.Budget(trace=False, lip=1.0, margin=0.0, eps=2.2e-16, skip=False)
        bad = _step.step_ser(data, state, physics, budget, 40, block, None, plain)
        out.append((X, V, flags, bad))
    ref = out[0]
    assert ref[2][5] == C.FLAG_INPUT and ref[2][7] == C.FLAG_COEFF
    assert ref[3] == np.count_nonzero(ref[2])
    assert np.all(ref[1][: n // 3 - 1, 1] ** 2 < 1.0)  # the resting third stays in contact
    for X, V, flags, bad in out[1:]:
        np.testing.assert_array_equal(X, ref[0])
        np.testing.assert_array_equal(V, ref[1])
        np.testing.assert_array_equal(flags, ref[2])
        assert bad == ref[3]


def test_plain_kernel_is_used_without_skipping_and_tunnelling_check():
    g = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[60j, 60j])
    sims = []
    for tunnelling in (False, True):
        sim = phys.ParticleSimulation(g, n=300, seed=1, prevent_tunnelling=tunnelling)
        sim.force_generators.append(phys.Gravity())
        sim.engine.skip = False
        sim.engine.simd = False  # (a grid world would take the block kernel, tested below)
        sims.append(sim)
    sims[0].run(60)
    module = sims[0].engine.kernel()[0]
    assert "plain" in compiled_variants(module)  # compiled and called
    assert "plain" not in compiled_variants(sims[1].engine.kernel()[0]) or (
        sims[1].engine.kernel()[0] is module
    )
    # the general kernel with the same switches gives the same state
    ref = phys.ParticleSimulation(g, n=300, seed=1, prevent_tunnelling=False)
    ref.force_generators.append(phys.Gravity())
    a = ref.p._arrays
    flags = np.zeros(300, np.int32)
    ax, ay, drag, _, _ = fuse(ref.force_generators)
    ref.engine.bind_fallback()  # no particle stops to bind it
    state = _step.State(*[a[k] for k in phys.Particles.FIELDS], np.zeros((0, 2)), flags, True)
    physics = _step.Physics(
        dt=ref.dt,
        t0=0.0,
        ax=ax,
        ay=ay,
        drag=drag,
        use_m=False,
        use_ext=False,
        explicit=ref.integrator == "euler",
        always=ref.collision == "notebook",
        rest=0.0,
    )
    budget = _step.Budget(
        trace=False, lip=ref.lipschitz, margin=ref.engine.margin, eps=2.2e-16, skip=False
    )
    ref.engine.kernel()[0].step_ser(ref.engine.data, state, physics, budget, 60, 512, None, None)
    assert not flags.any()
    np.testing.assert_array_equal(sims[0].p["x"], ref.p["x"])
    np.testing.assert_array_equal(sims[0].p["v"], ref.p["v"])


# ---------------------------------------------------------------------------------------------
# Generated kernels.


def test_generated_kernel_is_the_step_module_with_one_scene_block():
    head, tail = phys._step_source()
    sim = phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=3, seed=0)
    with open(sim.engine.kernel()[0].__file__) as fh:
        src = fh.read()
    assert src.startswith(head) and src.endswith(tail)
    assert "# >>> SCENE BLOCK" not in src and "_CACHE = True" in src


def test_grid_kernel_does_not_depend_on_the_scene():
    a = GridSDF(sdf.Circle([0, 0], 1.0), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    b = GridSDF(sdf.Box([-1, -1], [1, 0.5]), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    sa = phys.ParticleSimulation(a, n=3, seed=0)
    sb = phys.ParticleSimulation(b, n=3, seed=0)
    assert sa.engine.kernel()[0] is sb.engine.kernel()[0]
    # ...and each still answers with its own scene, inside and outside the grid.
    pts = np.array([[0.0, 0.0], [1.5, 0.3], [3.0, -4.0], [-7.0, 0.2]])
    for sim, grid in ((sa, a), (sb, b)):
        d, g = sim.query(pts[:, 0], pts[:, 1])
        de, ge = grid.exact(pts[2:, 0], pts[2:, 1], compute_gradient=True)
        np.testing.assert_allclose(d[2:], de, rtol=1e-14)  # outside: the exact SDF
        np.testing.assert_allclose(g[2:], ge, rtol=1e-14)
        dg, gg = grid(pts[:, 0], pts[:, 1], compute_gradient=True)  # the grid's own query
        np.testing.assert_allclose(d, dg, rtol=1e-14)
        np.testing.assert_allclose(g, gg, rtol=1e-14)


# ---------------------------------------------------------------------------------------------
# Fused user forces.


@njit
def _wind(x, y, vx, vy, m, t):
    return 0.3 * m + 0.1 * t, -0.2 * vy * m


@njit
def _spring(x, y, vx, vy, m, t):
    return -2.0 * x, -2.0 * (y - 0.5)


@pytest.mark.parametrize("n", [50, 5000])
def test_fused_njit_forces_equal_the_python_path(n):
    w = seed_world()
    fused = phys.ParticleSimulation(w, n=n, seed=5)
    slow = phys.ParticleSimulation(w, n=n, seed=5)
    fused.force_generators += [phys.Gravity(), _wind, _spring]

    def wind_py(p, t):
        return np.c_[0.3 * p["m"] + 0.1 * t, -0.2 * p["v"][:, 1] * p["m"]]

    def spring_py(p, t):
        return np.c_[-2.0 * p["x"][:, 0], -2.0 * (p["x"][:, 1] - 0.5)]

    slow.force_generators += [phys.Gravity(), wind_py, spring_py]
    for _ in range(3):
        fused.run(7)
        slow.run(7)
    np.testing.assert_allclose(fused.p["x"], slow.p["x"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fused.p["v"], slow.p["v"], rtol=1e-12, atol=1e-12)
    assert fused.t == slow.t


def test_force_many_sums_the_fused_forces():
    sim = phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=3, seed=0)
    sim.force_generators += [_wind, _spring]
    module, _ = sim.engine.kernel(tuple(sim.force_generators))
    xs, ys, vx, vy, m = np.random.default_rng(6).normal(size=(5, 10))
    out = np.empty((10, 2))
    module.force_many(xs, ys, vx, vy, m, 0.7, out)
    np.testing.assert_allclose(out[:, 0], 0.3 * m + 0.07 - 2.0 * xs, rtol=1e-14)
    np.testing.assert_allclose(out[:, 1], -0.2 * vy * m - 2.0 * (ys - 0.5), rtol=1e-14)


# ---------------------------------------------------------------------------------------------
# Clock and state.


def test_clock_and_state_agree_after_an_invalid_particle():
    w = seed_world()
    good = phys.ParticleSimulation(w, n=20, seed=7)
    bad = phys.ParticleSimulation(w, n=20, seed=7)
    for s in (good, bad):
        s.force_generators.append(phys.Gravity())
    bad.p["x"][3] = [math.nan, 0.0]
    with pytest.raises(ValueError, match=r"p\['x'\]\[3\].*sim.t = 0.1666"):
        bad.run(5)
    good.run(5)
    assert bad.t == good.t == 5 * good.dt
    keep = np.arange(20) != 3
    np.testing.assert_array_equal(bad.p["x"][keep], good.p["x"][keep])


def test_a_step_that_overflows_is_reported_and_not_carried():
    sim = phys.ParticleSimulation(
        sdf.Halfspace([0, 1], -1.0), n=10, seed=0, prevent_tunnelling=False
    )
    sim.force_generators.append(phys.Gravity())
    x0 = sim.p["x"].copy()
    sim.dt = 1e300
    with pytest.raises(ValueError, match="non-finite state"):
        sim.run(1)
    assert np.all(np.isfinite(sim.p["x"])) and np.all(np.isfinite(sim.p["v"]))
    assert sim.t == 1e300
    np.testing.assert_array_equal(sim.p["x"], x0)


@pytest.mark.parametrize("dt", [0.0, -1.0, math.inf, math.nan])
def test_timestep_is_validated_on_assignment(dt):
    sim = phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=2, seed=0)
    with pytest.raises(ValueError, match="timestep must be finite and > 0"):
        sim.dt = dt
    with pytest.raises(ValueError, match="timestep"):
        phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=2, timestep=dt)


def test_field_forces_from_expressions_equal_their_numpy_forms():
    from fastsdf.expr.graph import Symbol, sym_sqrt

    x, y = Symbol("x"), Symbol("y")
    rr = sym_sqrt(x * x + y * y + 0.01)
    attractor = phys.FieldForce(potential=-0.5 / rr, per_mass=True)  # -grad U = -0.5 p / rr^3
    swirl = phys.FieldForce(-y * 0.3, x * 0.3)
    w = sdf.Halfspace([0, 1], -1.8)
    fused = phys.ParticleSimulation(w, n=300, seed=8)
    slow = phys.ParticleSimulation(w, n=300, seed=8)
    fused.force_generators += [attractor, swirl]

    def attractor_py(p, t):
        q = p["x"]
        r3 = (q[:, 0] ** 2 + q[:, 1] ** 2 + 0.01) ** 1.5
        return -0.5 * p["m"][:, None] * q / r3[:, None]

    def swirl_py(p, t):
        return np.c_[-0.3 * p["x"][:, 1], 0.3 * p["x"][:, 0]]

    slow.force_generators += [attractor_py, swirl_py]
    np.testing.assert_allclose(attractor(fused.p, 0.0), attractor_py(fused.p, 0.0), rtol=1e-12)
    for _ in range(4):
        fused.run(5)
        slow.run(5)
    np.testing.assert_allclose(fused.p["x"], slow.p["x"], rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(fused.p["v"], slow.p["v"], rtol=1e-9, atol=1e-11)


def test_field_force_arguments_are_checked():
    with pytest.raises(TypeError, match="fx and fy, or potential"):
        phys.FieldForce(1.0)
    with pytest.raises(TypeError, match="not both"):
        phys.FieldForce(1.0, 2.0, potential=3.0)
    with pytest.raises(TypeError, match="fx must be"):
        phys.FieldForce("wind", 2.0)


@pytest.mark.parametrize("n", [300, 5000])
def test_lazy_exact_fallback_gives_the_same_trajectories(n):
    # Particles start near and beyond the edge of a small grid: the exact fallback is compiled
    # only when the first one gets near the edge, and those particles resume from there.
    w = sdf.Halfspace([0, 1], -0.5) | sdf.Circle([0.4, 0.0], 0.3)
    grid = GridSDF(w, bounds=[(-1, 1), (-1, 1)], samples=[60j, 60j])
    lazy = phys.ParticleSimulation(grid, n=n, seed=9)
    eager = phys.ParticleSimulation(grid, n=n, seed=9)
    eager.engine.bind_fallback()
    assert not lazy.engine.fallback_bound and eager.engine.fallback_bound
    x = np.c_[np.random.default_rng(9).uniform(-0.5, 0.5, n), np.linspace(0.4, 0.9, n)]
    for s in (lazy, eager):
        s.force_generators.append(phys.Gravity())
        s.p["x"] = x
        s.p["v"] = 0.0
    lazy.run(3)  # nobody comes near the edge yet: nothing compiled
    eager.run(3)
    assert not lazy.engine.fallback_bound
    for s in (lazy, eager):
        s.p["v"] = np.c_[np.linspace(-3, 3, n), np.zeros(n)]
    lazy.run(40)
    eager.run(40)
    assert lazy.engine.fallback_bound
    assert np.any(np.abs(eager.p["x"]) > 1.0)  # some did leave the grid
    np.testing.assert_array_equal(lazy.p["x"], eager.p["x"])
    np.testing.assert_array_equal(lazy.p["v"], eager.p["v"])
    assert lazy.t == eager.t


def test_fields_evaluated_ahead_give_the_results_of_inline_forces():
    # A compiled field is evaluated for a batch of particles ahead of their steps; the same
    # force wrapped in a plain @njit function is evaluated inline, one particle at a time.
    # The two orders of work must give bit-identical trajectories (with contacts, a particle
    # count that is not a multiple of the batch, and the parallel kernel).
    from fastsdf.expr.graph import Symbol, sym_sqrt

    x, y = Symbol("x"), Symbol("y")
    field = phys.FieldForce(
        potential=-0.02 / sym_sqrt(x * x + (y + 1.0) * (y + 1.0) + 0.1), per_mass=True
    )
    dispatch = field.dispatcher

    @njit
    def inline(x, y, vx, vy, m, t):
        return dispatch(x, y, vx, vy, m, t)

    n = 2 * phys.PARALLEL_MIN_PARTICLES + 37
    w = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j])
    ahead = phys.ParticleSimulation(w, n=n, seed=11)
    plain = phys.ParticleSimulation(w, n=n, seed=11)
    ahead.force_generators += [phys.Gravity(), field]
    plain.force_generators += [phys.Gravity(), inline]
    for sim in (ahead, plain):
        sim.run(100)
    assert ahead.engine.kernel((field.dispatcher,))[0].FORCE_AHEAD
    assert not plain.engine.kernel((inline,))[0].FORCE_AHEAD
    # free fall for 100 steps would reach a speed of about 3.3: slower particles have hit walls
    assert (np.hypot(*ahead.p["v"].T) < 1.0).sum() > n // 4
    np.testing.assert_array_equal(ahead.p["x"], plain.p["x"])
    np.testing.assert_array_equal(ahead.p["v"], plain.p["v"])


def test_a_users_force_keeps_numbas_own_cache_format(tmp_path, monkeypatch):
    # Generated kernel modules seal the cache files of fastsdf's dispatchers; a user's cached
    # @njit force imported into a kernel must keep numba's format, or running it outside
    # fastsdf (or before a kernel imports it) would fail to read its own cache.
    import sys
    import types

    from fastsdf.backends.kernel import cache as _cache

    (tmp_path / "user_force_mod.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\n"
        "def push(x, y, vx, vy, m, t):\n    return 0.1 * m, 0.0\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    import user_force_mod

    own = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[10j, 10j]).sampler
    fake = types.ModuleType("fastsdf_particles_fake")
    fake._uf0 = user_force_mod.push
    fake._sampler = own
    _cache.guard_module(fake)
    assert not getattr(user_force_mod.push._cache, "_fastsdf_guarded", False)
    assert getattr(own._cache, "_fastsdf_guarded", False)
    sys.modules.pop("user_force_mod", None)


# ---------------------------------------------------------------------------------------------
# Resting contact and sleeping.


def _tilted_floor(angle):
    """Solid below a plane through the origin tilted by ``angle`` (radians)."""
    return sdf.Halfspace([-math.sin(angle), math.cos(angle)], 0.0)


@pytest.mark.parametrize("angle, rests", [(0.0, True), (0.2, True), (0.4, False)])
def test_resting_contact_holds_below_the_friction_angle(angle, rests):
    # cf = 0.3: static friction holds on a plane tilted less than atan(0.3) = 0.29 rad.
    sim = phys.ParticleSimulation(_tilted_floor(angle), n=200, seed=1, rest_speed=0.1, cf=0.3)
    sim.force_generators.append(phys.Gravity())
    rng = np.random.default_rng(2)
    sim.p["x"][:] = np.c_[rng.uniform(-1, 1, 200), rng.uniform(0.3, 0.6, 200)]
    sim.p["v"][:] = 0.0
    sim.run(240)
    before = sim.p.copy()
    sim.run(1)
    speed = np.hypot(*sim.p["v"].T)
    if rests:
        assert np.all(speed == 0.0)
        np.testing.assert_array_equal(sim.p["x"], before["x"])  # an exact fixed point
        # resting on the plane, within rest_speed dt + g dt**2 of touching it
        n = np.array([-math.sin(angle), math.cos(angle)])
        gap = sim.p["x"] @ n - sim.p["r"]
        assert np.all(gap > -1e-9) and np.all(gap <= 0.1 * sim.dt + sim.dt**2 + 1e-9)
    else:
        # sliding down at the contact model's terminal speed ((1 - cf) g_t dt / cf, 0.03)
        assert np.all(speed > 0.02)
        assert np.all(sim.p["x"][:, 0] < before["x"][:, 0])  # down the slope, towards -x


def test_sleeping_particles_give_the_results_of_single_steps():
    # Within one run(k) call a particle whose step repeats its state is skipped for the rest
    # of the call; one advance() per step never skips. Both must give the same bits.
    w = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j])
    sim = phys.ParticleSimulation(w, n=phys.PARALLEL_MIN_PARTICLES + 55, seed=6, rest_speed=0.1)
    sim.force_generators.append(phys.Gravity())
    sim.run(300)
    other = phys.ParticleSimulation(w, n=sim.n, seed=0, rest_speed=0.1)
    other.force_generators.append(phys.Gravity())
    other.p = sim.p.copy()
    other.t = sim.t
    sim.run(20)
    for _ in range(20):
        other.advance()
    np.testing.assert_array_equal(sim.p["x"], other.p["x"])
    np.testing.assert_array_equal(sim.p["v"], other.p["v"])
    assert np.mean(np.all(sim.p["v"] == 0.0, axis=1)) > 0.3  # many did sleep


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf])
def test_rest_speed_is_validated(bad):
    with pytest.raises(ValueError, match="rest_speed must be finite and >= 0"):
        phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=2, rest_speed=bad)


# ---------------------------------------------------------------------------------------------
# The block kernel of grid worlds (the simd variant) against the particle-by-particle kernels.


@njit(cache=True)
def _gust(x, y, vx, vy, m, t):
    """A fused user force for the block kernel's tests (depends on position, velocity,
    mass and time)."""
    return 0.2 * (0.5 + 0.3 * y - vx) * m, -0.1 * vy + 0.05 * math.sin(3.0 * t)


def _block_pair(grid, n, seed, block, forces=(), **kw):
    """Two simulations in the same state: the block kernel and the particle-by-particle one."""
    rng = np.random.default_rng(seed)
    sims = []
    for simd in (True, False):
        sim = phys.ParticleSimulation(grid, n=n, seed=seed, block=block, **kw)
        sim.force_generators += [phys.Gravity()] + list(forces)
        sim.engine.simd = simd
        sims.append(sim)
    k = n // 4
    # resting on the floor of the seed world's funnel, falling, fast across the scene, and
    # beyond the grid's bounds (the exact fallback, or the clamped answer for 'nearest')
    x = np.r_[
        np.c_[rng.uniform(-0.3, 0.3, k), rng.uniform(-1.0, -0.5, k)],
        np.c_[rng.normal(0, 0.3, k), rng.uniform(0.5, 1.8, k)],
        np.c_[rng.uniform(-1.8, 1.8, k), rng.uniform(-1.8, 1.8, k)],
        np.c_[rng.uniform(1.9, 2.6, n - 3 * k), rng.uniform(-2.5, 2.5, n - 3 * k)],
    ]
    v = np.r_[rng.normal(scale=0.05, size=(2 * k, 2)), rng.normal(scale=4.0, size=(n - 2 * k, 2))]
    for sim in sims:
        sim.p["x"] = x
        sim.p["v"] = v
        sim.p["r"] = rng.uniform(0.0, 0.05, n) if sim is sims[0] else sims[0].p["r"]
        sim.p["m"] = rng.uniform(0.5, 2.0, n) if sim is sims[0] else sims[0].p["m"]
        sim.p["cr"] = rng.uniform(0.0, 1.0, n) if sim is sims[0] else sims[0].p["cr"]
        sim.p["cf"] = rng.uniform(0.0, 1.0, n) if sim is sims[0] else sims[0].p["cf"]
    return sims


def _run_pair(sims, calls, steps):
    """Run both; the states, clocks and any errors must agree bit for bit after each call."""
    for _ in range(calls):
        errors = []
        for sim in sims:
            try:
                sim.run(steps)
                errors.append(None)
            except ValueError as e:
                errors.append(str(e))
        assert errors[0] == errors[1]
        for f in ("x", "v"):
            np.testing.assert_array_equal(sims[0].p[f], sims[1].p[f])
        assert sims[0].t == sims[1].t


@pytest.mark.parametrize(
    "tunnelling, skip, extra",
    [
        (False, False, {}),  # the peers' work
        (True, True, {}),  # the defaults
        (True, False, {"integrator": "euler", "collision": "notebook"}),
        (False, True, {}),
    ],
)
@pytest.mark.parametrize("block", [100, 300])
def test_block_kernel_gives_the_particle_kernels_results(tunnelling, skip, extra, block):
    g = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j])
    sims = _block_pair(g, 1000, 3, block, prevent_tunnelling=tunnelling, **extra)
    for sim in sims:
        sim.engine.skip = skip
        sim.p["x"][7] = math.nan  # invalid input: frozen, flagged, left as it is
        sim.p["v"][8] = math.inf
        sim.p["cr"][:40] = 1.5  # invalid cr, found at a contact
    sims[0].force_generators.append(phys.Drag(0.2))
    sims[1].force_generators.append(phys.Drag(0.2))
    _run_pair(sims, 3, 30)
    # the block kernel ran: the entry point compiled for calls with or without skipping
    module = sims[0].engine.kernel()[0]
    assert ("simd" if skip else "simd_plain") in compiled_variants(module)
    # some particles touched surfaces, some left the grid, some were frozen
    assert np.any(np.abs(sims[0].p["x"]) > 2.0)
    assert np.isnan(sims[0].p["x"][7, 0]) and np.isinf(sims[0].p["v"][8, 0])


@pytest.mark.parametrize("mode", ["exact", "nearest"])
def test_block_kernel_with_a_fused_force_and_in_parallel(mode):
    # A fused user force, blocks over threads, blocks not a multiple of the lanes, and a grid
    # whose exact fallback is bound when the first particle comes near its edge ('exact').
    g = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j], mode=mode)
    n = phys.PARALLEL_MIN_PARTICLES + 77
    sims = _block_pair(g, n, 5, 700, forces=[_gust])
    _run_pair(sims, 2, 25)
    sims[0].engine.skip = sims[1].engine.skip = False
    _run_pair(sims, 1, 25)
    module = sims[0].engine.kernel((_gust,))[0]
    assert {"simd", "simd_plain"} <= compiled_variants(module)
    assert sims[0].engine.fallback_bound or mode == "nearest"


def test_block_kernel_is_used_only_where_it_applies(monkeypatch):
    g = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    picked = []
    pick = phys.engine.ParticleEngine._variant

    def spy(self, *args):
        variant = pick(self, *args)
        picked.append(VARIANTS[variant])
        return variant

    monkeypatch.setattr(phys.engine.ParticleEngine, "_variant", spy)
    cases = [
        ({}, "simd"),
        ({"prevent_tunnelling": False}, "simd"),
        ({"rest_speed": 0.1}, "general"),
        ({"dtype": np.float32}, "general"),
    ]
    for kw, name in cases:
        picked.clear()
        sim = phys.ParticleSimulation(g, n=200, seed=2, **kw)
        sim.force_generators.append(phys.Gravity())
        sim.run(2)
        assert set(picked) == {name}  # (twice where particles resume at the edge)
    picked.clear()
    plain = phys.ParticleSimulation(g, n=200, seed=2)
    plain.engine.skip = False  # (as for a world without a known Lipschitz bound)
    plain.run(2)
    assert set(picked) == {"simd_plain"}
    picked.clear()
    sim.force_generators.append(lambda p, t: np.zeros((len(p), 2)))  # a Python force
    sim.run(1)
    assert set(picked) == {"general"}
    # an exact-SDF world has no block kernel
    circle = phys.ParticleSimulation(sdf.Circle([0, 0], 1.0), n=5, seed=2)
    assert not circle.engine.kernel()[0].GRID_SIMD


@pytest.mark.parametrize("grid", [True, False])
def test_switching_skip_trace_and_rest_per_call_compiles_each_variant_once(grid):
    """The tunnelling check, query skipping and resting contact are chosen per call: each
    choice takes one of the kernel family's variants, compiled the first time it is needed;
    switching back and forth compiles nothing more (the variants' specializations, and the
    functions they call, keep their counts)."""
    world = seed_world()
    if grid:
        world = GridSDF(world, bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    sim = phys.ParticleSimulation(world, n=300, seed=2)
    sim.force_generators.append(phys.Gravity())
    module = sim.engine.kernel()[0]
    settings = [(True, True, 0.0), (False, True, 0.0), (True, False, 0.0), (False, False, 0.0)]
    settings.append((True, True, 0.1))

    def cycle():
        for trace, skip, rest in settings:
            sim.prevent_tunnelling, sim.engine.skip, sim.rest_speed = trace, skip, rest
            sim.run(3)

    def counts():
        names = ("step_ser", "_block_of", "_block", "_block_plain", "_block_simd")
        return [len(getattr(module, k).overloads) for k in names]

    def by_arguments():
        """The entry point's variants compiled, by the types of the call's other arguments
        (other tests of this process may have compiled the shared grid kernel for others)."""
        found: dict = {}
        for sig in module.step_ser.signatures:
            kinds = tuple(None if isinstance(t, numba.types.NoneType) else True for t in sig[-2:])
            found.setdefault(sig[:-2], []).append(VARIANTS[kinds])
        return found

    before = by_arguments()
    cycle()
    first = counts()
    used = compiled_variants(module)
    # the grid world's calls without resting contact take the block step, with or without
    # skipping; the exact world's take the plain step without skipping and tunnelling check
    assert used >= ({"simd", "simd_plain", "general"} if grid else {"general", "plain"})
    after = by_arguments()
    # the switches are values, not types: the call adds at most one set of argument types,
    # and each variant is compiled once for it
    assert len(after) - len(before) <= 1
    assert all(len(variants) == len(set(variants)) for variants in after.values())
    cycle()
    cycle()
    assert counts() == first


def test_block_kernel_on_a_float32_grid():
    # The cells' values are widened to float64 as the scalar sampler does.
    g = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j], dtype=np.float32)
    sims = _block_pair(g, 600, 8, 256)
    _run_pair(sims, 2, 30)
    assert "simd" in compiled_variants(sims[0].engine.kernel()[0])


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs two threads")
@pytest.mark.parametrize("grid", [True, False])
@pytest.mark.parametrize("long", [False, True])
def test_threads_give_the_results_of_one_thread(grid, long, monkeypatch):
    # A short call: the particles cut into slices of whole blocks, one per thread; a long one:
    # numba's parallel entry point. The same bits as one call over all of them on one thread
    # (the block kernel of a grid world, the general kernel of an exact SDF with its
    # tunnelling sweep), frozen particles and error included.
    if long:
        monkeypatch.setattr(phys.engine, "LONG_CALL", 1000)
    world = seed_world()
    if grid:
        world = GridSDF(world, bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j])
    n = phys.PARALLEL_MIN_PARTICLES + 77
    out = []
    for threads in (1, 2):
        sim = phys.ParticleSimulation(world, n=n, seed=4, block=300)
        sim.force_generators.append(phys.Gravity())
        rng = np.random.default_rng(4)
        sim.p["x"] = rng.uniform(-1.9, 1.9, (n, 2))
        sim.p["v"] = rng.normal(scale=3.0, size=(n, 2))
        sim.p["cr"][n - 5] = 1.5  # invalid: frozen at its first contact
        previous = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            errors = []
            for _ in range(3):
                try:
                    sim.run(10)
                except ValueError as e:
                    errors.append(str(e))
        finally:
            numba.set_num_threads(previous)
        out.append((sim.p["x"].copy(), sim.p["v"].copy(), errors))
    for a, b in zip(out[0][:2], out[1][:2], strict=True):
        np.testing.assert_array_equal(a, b)
    assert out[0][2] == out[1][2] and out[0][2]


def test_python_forces_near_the_grids_edge():
    # One step per Python-force evaluation: the first step binds the grid's exact fallback
    # for the particles near its edge, and every later step uses it (no particle is left
    # stopped there). A Python drag force gives the fused Drag's results, bit for bit.
    g = GridSDF(seed_world(), bounds=[(-1.5, 1.5), (-1.5, 1.5)], samples=[64j, 64j])
    sims = []
    for force in (lambda p, t: -0.1 * p["v"], phys.Drag(0.1)):
        sim = phys.ParticleSimulation(g, n=200, seed=3)
        sim.force_generators += [phys.Gravity(), force]
        sim.p["x"][:50, 1] = np.linspace(1.3, 1.6, 50)  # near and beyond the top edge
        sim.run(3)
        sims.append(sim)
    assert sims[0].engine.fallback_bound
    np.testing.assert_array_equal(sims[0].p["x"], sims[1].p["x"])
    np.testing.assert_array_equal(sims[0].p["v"], sims[1].p["v"])
