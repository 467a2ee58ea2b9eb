"""Contact history (Cundall-Strack tangential springs, LAMMPS ``gran/hooke/history``) and rolling
resistance: static friction on an incline against Coulomb's law and the rolling disc, the
springs carried across list rebuilds and the reorder of grains against a run that never
rebuilds, the Coulomb cap of the kernel, and a heap that keeps its slope.

Heaps of 2D discs: without rolling resistance discs roll, and a poured heap flows away (the
figures against ``mu_r`` are in ``bench/RESULTS.md``); the angle of repose rises with rolling
resistance as in Zhou, Wright, Yang, Xu & Yu (Physica A 269 (1999) 536, "Rolling friction in
the dynamic simulation of sandpile formation") and Itasca's PFC2D rolling-resistance
repose-angle verification; Ai, Chen, Rotter & Ooi (Powder Technology 206 (2011) 269) assess the
rolling models (model C is the rolling spring here). A frictionless heap spreads flat.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fastsdf as fs
from fastsdf.expr.graph import Param
from fastsdf.granular import ContactLaw, GranularSimulation, repose_angle
from fastsdf.granular.kernels import Law, _contact_history


@pytest.fixture(autouse=True)
def _one_thread():
    """Scenes of a few to a few hundred grains: one thread (waking workers three times a
    substep costs more than it saves, most of all on a loaded machine)."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(threads)


def incline(theta_deg, law, offsets):
    """Discs of radius 0.5 resting (just touching) on a floor tilted by ``theta``, at
    ``offsets`` = (along the slope, above it); gravity 1 straight down."""
    th = math.radians(theta_deg)
    t = np.array([math.cos(th), math.sin(th)])  # up the slope
    n = np.array([-math.sin(th), math.cos(th)])
    pos = np.array([a * t + b * n for a, b in offsets])
    sim = GranularSimulation(
        fs.Halfspace((Param("nx", float(n[0])), Param("ny", float(n[1]))), 0.0),
        positions=pos,
        radius=0.5,
        contacts=law,
        gravity=(0.0, -1.0),
        timestep=1.0,
    )
    return sim, t, n


BLOCK = [(-1, 0.5), (0, 0.5), (1, 0.5), (-0.5, 0.5 + 0.75**0.5), (0.5, 0.5 + 0.75**0.5)]


def test_block_rests_below_atan_mu_and_slides_above():
    """Five discs stacked as a block (3 + 2), with rolling resistance so that the block cannot
    roll: at 12 degrees (below atan 0.3 = 16.7) it comes to rest and stays there; at 20 it
    slides, accelerating at no more than a rigid block's ``g (sin - mu cos)``."""
    law = ContactLaw(
        stiffness=1e4, restitution=0.5, friction=0.3, history=True, rolling_friction=0.5
    )
    sim, t, _ = incline(12.0, law, BLOCK)
    sim.run(5)
    p0 = sim.positions
    sim.run(10)
    assert np.abs(sim.velocities).max() < 1e-9
    assert np.abs(sim.positions - p0).max() < 1e-8
    sim, t, _ = incline(20.0, law, BLOCK)
    sim.run(4)
    v0 = sim.velocities @ t
    sim.run(6)
    accel = (sim.velocities @ t - v0) / 6.0
    th = math.radians(20.0)
    coulomb = -(math.sin(th) - 0.3 * math.cos(th))  # down the slope
    assert np.all(accel < 0.5 * coulomb)  # slides (moving down: negative)
    assert np.all(accel > 1.02 * coulomb)  # never faster than a frictionless-limit block


@pytest.mark.parametrize("history", [True, False])
def test_disc_rolls_without_slipping_below_atan_3mu(history):
    """A disc on an incline rolls without slipping while ``tan theta <= 3 mu`` (the friction a
    rolling disc needs is a third of ``m g sin``), at ``a = (2/3) g sin theta``, and slips
    above. With the spring the contact point is at rest (static friction); without it the
    contact creeps: it slips at the speed where the viscous force carries the load."""
    law = ContactLaw(stiffness=1e4, restitution=0.5, friction=0.3, history=history)
    sim, t, _ = incline(25.0, law, [(0.0, 0.5)])  # tan 25 = 0.47 < 0.9
    sim.run(2)
    v0 = float((sim.velocities @ t)[0])
    sim.run(4)
    v = float((sim.velocities @ t)[0])
    slip = v + 0.5 * sim.angular_velocities[0]  # contact point's speed along the slope
    if history:
        assert abs(slip) < 1e-9
        assert (v - v0) / 4.0 == pytest.approx(-(2 / 3) * math.sin(math.radians(25.0)), rel=1e-6)
    else:
        assert abs(slip) > 1e-4  # creeps
    if history:
        sim, t, n = incline(50.0, law, [(0.0, 0.5)])  # tan 50 = 1.19 > 0.9: slips
        sim.run(3)
        slip = float((sim.velocities @ t)[0]) + 0.5 * sim.angular_velocities[0]
        assert slip < -0.1
        v0 = float((sim.velocities @ t)[0])
        sim.run(2)
        th = math.radians(50.0)
        assert (float((sim.velocities @ t)[0]) - v0) / 2 == pytest.approx(
            -(math.sin(th) - 0.3 * math.cos(th)), rel=1e-6
        )


def settling_pile(skin, seed=3):
    """36 discs of radii 0.4-0.6 dropped into a V-shaped trough: many sliding, sticking and
    breaking contacts."""
    rng = np.random.default_rng(seed)
    i = np.arange(36)
    pos = np.stack([(i % 6 - 2.5) * 1.3, 2.4 + (i // 6) * 1.25], 1) + rng.uniform(
        -0.1, 0.1, (36, 2)
    )
    world = fs.shapes.union([fs.Halfspace((-0.5, 1.0), 0.0), fs.Halfspace((0.5, 1.0), 0.0)])
    return GranularSimulation(
        world,
        positions=pos,
        radius=rng.uniform(0.4, 0.6, 36),
        contacts=ContactLaw(
            stiffness=1e4, restitution=0.5, friction=0.5, history=True, rolling_friction=0.2
        ),
        gravity=(0.0, -1.0),
        timestep=0.25,
        skin=skin,
        chunks=3,
    )


def test_springs_survive_rebuilds_and_reorders():
    """The same pile run twice: once with a skin so wide the list is never rebuilt (each
    contact keeps its list entry, nothing to carry), once rebuilt (grains reordered by cell,
    the list remade, the springs carried by pair) every 5 substeps. Every contact's spring
    agrees (to rounding: the reordered run adds forces in another order) after many springs
    have stretched and slipped."""
    ref = settling_pile(skin=12.0)
    run = settling_pile(skin=0.2)
    steps = 10 * ref.substeps_per_frame  # 2.5 time units: the grains land and settle
    for _ in range(steps // 5):
        ref.advance(5)
        run.advance(5)
        run._rebuild()
    assert ref.rebuilds == 1 and run.rebuilds > steps // 5
    assert not np.array_equal(run.ids, np.arange(36))  # reordered
    pa, sa, wa = ref.tangential_springs()
    pb, sb, wb = run.tangential_springs()
    touching = {tuple(p): s for p, s in zip(pa, sa) if s != 0.0}
    other = {tuple(p): s for p, s in zip(pb, sb) if s != 0.0}
    assert len(touching) >= 8 and touching.keys() == other.keys()
    a = np.array([touching[k] for k in touching])
    b = np.array([other[k] for k in touching])
    scale = np.abs(a).max()
    assert scale > 1e-4  # stretched springs, not zeros
    assert np.abs(a - b).max() < 1e-6 * scale
    assert np.abs(wa - wb).max() < 1e-6 * max(np.abs(wa).max(), 1e-12)
    assert np.abs(wa).max() > 1e-5
    np.testing.assert_allclose(ref.positions, run.positions, atol=1e-9)


@settings(max_examples=300, deadline=None)
@given(
    delta=st.floats(1e-6, 0.1),
    vn=st.floats(-5, 5),
    vt=st.floats(-5, 5),
    wr=st.floats(-5, 5),
    s=st.floats(-0.05, 0.05),
    mu=st.floats(0.0, 1.0),
    angle=st.floats(0, 2 * math.pi),
)
def test_tangential_force_never_exceeds_coulomb(delta, vn, vt, wr, s, mu, angle):
    """``|f_t| <= mu |F_n|`` always; below the cap the force is the spring and dashpot,
    ``-(k_t s' + gamma_t v_t)`` with ``s' = s + v_t dt``; at the cap the spring is truncated so
    that the same formula gives the capped force (the spring stores exactly the force)."""
    nx, ny = math.cos(angle), math.sin(angle)
    tx, ty = -ny, nx
    vrx = vn * nx + vt * tx
    vry = vn * ny + vt * ty
    kn, kt, gamma_n, tdamp, dt = 1e4, 1e4 * 2 / 7, 30.0, 0.5, 1e-3
    law = Law(kn=kn, kt=kt, zeta=0.0, damp=0.0, mu=mu, mu_r=0.0, tdamp=tdamp, density=1.0, dt=dt)
    fx, fy, ftx, fty, s_new, fn = _contact_history(delta, nx, ny, vrx, vry, wr, gamma_n, law, s)
    ft = math.hypot(ftx, fty)
    assert ft <= abs(mu * fn) * (1 + 1e-12) + 1e-300
    vts = vt - wr
    reach = abs(vn) * dt
    g_eff = gamma_n * (0.5 + delta / reach) if reach > 2 * delta else gamma_n  # ramped dashpot
    assert fn == pytest.approx(kn * delta - g_eff * vn, rel=1e-9, abs=1e-9)
    gamma_t = tdamp * g_eff
    spring_force = -(kt * s_new + gamma_t * vts)
    assert ftx * tx + fty * ty == pytest.approx(spring_force, rel=1e-9, abs=1e-9)
    free = -(kt * (s + vts * dt) + gamma_t * vts)  # the force were the contact to stick
    if abs(free) <= abs(mu * fn) * (1 - 1e-9):  # sticks: the spring took the whole sliding
        assert s_new == pytest.approx(s + vts * dt, rel=1e-12, abs=1e-15)
    elif abs(free) > abs(mu * fn) * (1 + 1e-9):  # slides: at the cap
        assert ft == pytest.approx(abs(mu * fn), rel=1e-9, abs=1e-12)


def _example(name):
    import importlib.util
    import os

    path = os.path.join(os.path.dirname(__file__), "..", "examples", f"{name}.py")
    spec = importlib.util.spec_from_file_location(f"_example_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_poured_heap_keeps_a_slope_that_a_frictionless_heap_cannot():
    """250 discs poured through a hopper (``examples/heap.py``) onto a floor. With sliding
    friction 0.5 and rolling resistance 0.3 the heap's flanks stand at 12-30 degrees on average
    (a loose bracket around the 20-30 degrees of sand, which a frictionless heap fails) and
    keep their slope over a further 20 time units; frictionless discs spread flat (below 3
    degrees)."""
    import numba

    heap = _example("heap")
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # a small scene: one thread is fastest
    try:
        law = ContactLaw(
            stiffness=2e3, restitution=0.3, friction=0.5, history=True, rolling_friction=0.3
        )
        sim = heap.pour(250, law)
        left, right, _ = repose_angle(sim.p["x"], sim.p["r"], floor=0.0, bin_width=1.0)
        assert 12.0 < (left + right) / 2 < 30.0 and min(left, right) > 8.0
        sim.run(20)
        left2, right2, _ = repose_angle(sim.p["x"], sim.p["r"], floor=0.0, bin_width=1.0)
        assert abs(left2 - left) < 0.5 and abs(right2 - right) < 0.5
        flat = heap.pour(250, law._replace(friction=0.0, rolling_friction=0.0), time_limit=40)
        angles = repose_angle(flat.p["x"], flat.p["r"], floor=0.0, bin_width=1.0)[:2]
        assert all(not (a >= 3.0) for a in angles)  # NaN: no flank at all
    finally:
        numba.set_num_threads(threads)


# Springs store energy: without dashpots, and while no spring slips, the kinetic, rotational
# and spring energies sum to a constant (the tangential force does work -k_t s v_t on the
# grains, the spring's k_t s**2 / 2 grows by k_t s v_t; likewise the rolling torque). A spring
# cut down to Coulomb's cap dissipates, so the check stops where a spring comes near its cap
# (which every spring does as the contact ends: the cap goes to 0 with the overlap). The
# stretch grows with the velocity the force pass sees, a step's end, not its middle: the
# energy drifts at first order in the substep, hence the fine substep here.
ELASTIC_SUBSTEPS_PER_CONTACT = 2560


def elastic_contact_energies(sim, spring_ratio):
    """Step ``sim`` one substep at a time through its first contact; each substep's energy
    parts (the dict of ``energy()``) and whether every spring is below 0.9 of its cap
    (``spring_ratio(sim, energy)``: the largest spring over its cap)."""
    rows = []
    for _ in range(100_000):
        sim.advance(1)
        touching = sum(sim.contact_counts()) > 0
        if touching:
            e = sim.energy()
            rows.append((e, spring_ratio(sim, e) < 0.9))
        elif rows:
            return rows
    raise AssertionError("the contact did not end")


def check_conserved_with_springs(rows, e0, springs):
    sticking = [e for e, ok in rows if ok]
    assert len(sticking) >= 0.75 * len(rows)  # most of the contact is checked
    for e in sticking:
        assert abs(e["total"] - e0) < 1e-3 * e0
        assert e["total"] == pytest.approx(sum(v for k, v in e.items() if k != "total"), rel=1e-12)
    # the springs hold enough that the sum without them is not conserved
    for name in springs:
        assert max(e[name] for e in sticking) > 5e-3 * e0, name
    assert max(abs(e["total"] - sum(e[k] for k in springs) - e0) for e in sticking) > 2e-2 * e0


def test_oblique_elastic_pair_keeps_energy_in_its_tangential_spring():
    """Two equal discs, one at rest, struck off-centre (restitution 1: no dashpots; friction
    10: the spring holds): the tangential spring takes up to about 6% of the energy."""
    law = ContactLaw(stiffness=1e4, restitution=1.0, friction=10.0, history=True)
    sim = GranularSimulation(
        None,
        positions=[[-1.0, -0.3], [0.2, 0.3]],
        radius=0.5,
        velocities=[[2.0, 0.0], [0.0, 0.0]],
        gravity=(0.0, 0.0),
        contacts=law,
        timestep=1e-3,
        substeps_per_contact=ELASTIC_SUBSTEPS_PER_CONTACT,
    )
    e0 = sim.energy()["total"]
    assert e0 == pytest.approx(0.5 * math.pi * 0.25 * 4.0)  # m v**2 / 2, density 1
    kn, kt = law.stiffness, law.stiffness * law.tangential_stiffness

    def ratio(sim, e):
        _, stretch, _ = sim.tangential_springs()
        x = sim.positions
        overlap = 1.0 - float(np.hypot(*(x[0] - x[1])))
        return kt * float(np.abs(stretch).max()) / (law.friction * kn * overlap)

    rows = elastic_contact_energies(sim, ratio)
    check_conserved_with_springs(rows, e0, ["tangential_springs"])


def test_spinning_disc_on_a_floor_keeps_energy_in_its_tangential_and_rolling_springs():
    """A disc spinning against its motion lands obliquely on a floor (restitution 1, friction
    10, rolling friction 0.2): both springs of the wall contact store energy."""
    law = ContactLaw(
        stiffness=1e4, restitution=1.0, friction=10.0, history=True, rolling_friction=0.2
    )
    sim = GranularSimulation(
        fs.Halfspace((0.0, 1.0), 0.0),
        positions=[[0.0, 0.55]],
        radius=0.5,
        velocities=[[1.0, -1.0]],
        gravity=(0.0, 0.0),
        contacts=law,
        timestep=1e-3,
        substeps_per_contact=ELASTIC_SUBSTEPS_PER_CONTACT,
    )
    sim.set_state(angular_velocities=[2.0])
    e0 = sim.energy()["total"]
    m = math.pi * 0.25
    assert e0 == pytest.approx(0.5 * m * 2.0 + 0.25 * m * 0.25 * 4.0)
    kn, kt = law.stiffness, law.stiffness * law.tangential_stiffness
    kr = 2.25 * kn * law.rolling_friction**2 * 0.25  # R_eff = R against the world

    def ratio(sim, e):
        _, _, wall = sim.tangential_springs()
        overlap = 0.5 - float(sim.positions[0, 1])
        torque = math.sqrt(2.0 * kr * e["rolling_springs"])
        return max(
            kt * abs(float(wall[0])) / (law.friction * kn * overlap),
            torque / (law.rolling_friction * 0.5 * kn * overlap),
        )

    rows = elastic_contact_energies(sim, ratio)
    check_conserved_with_springs(rows, e0, ["tangential_springs", "rolling_springs"])


def test_energy_has_the_same_parts_on_every_route():
    """``energy()`` of grains in the particle family, of their engine and of plain particles:
    one dict of named parts and their total. The grains' parts agree with the family's own
    kinetic and potential energy and with the state (rotational ``m r**2 w**2 / 4``); plain
    particles hold no rotation and no springs."""
    import fastsdf.particles as phys

    floor = fs.Halfspace((0.0, 1.0), 0.0)
    law = ContactLaw(stiffness=2e3, friction=0.5, history=True, rolling_friction=0.2)
    xs = np.arange(6) * 0.05
    pos = np.c_[xs, np.full(6, 0.02 - 6e-6)]  # on the floor, pressed by about their weight
    sim = phys.ParticleSimulation(floor, positions=pos, radius=0.02, contacts=law, timestep=0.01)
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    sim.p["v"] = np.c_[np.full(6, 0.3), np.zeros(6)]  # sliding: the springs stretch
    sim.run(1)
    assert sim.engine.contact_counts() == (0, 6)
    e = sim.energy()
    parts = ("kinetic", "rotational", "potential")
    springs = ("normal_springs", "tangential_springs", "rolling_springs")
    assert list(e) == [*parts, *springs, "total"]
    assert e == sim.engine.energy()
    assert e["kinetic"] == pytest.approx(sim.kinetic_energy(), rel=1e-12)
    assert e["potential"] == pytest.approx(sim.potential_energy(), rel=1e-12)
    m, r, w = sim.p["m"], sim.p["r"], sim.p["omega"]
    assert e["rotational"] == pytest.approx(float(np.sum(m * r * r * w * w / 4)), rel=1e-12)
    assert e["rotational"] > 0 and all(e[k] > 0 for k in springs)
    assert e["total"] == pytest.approx(sum(e[k] for k in (*parts, *springs)), rel=1e-12)

    plain = phys.ParticleSimulation(floor, n=5, seed=0)
    plain.force_generators.append(phys.Gravity())
    plain.run(2)
    p = plain.energy()
    assert list(p) == list(e)
    assert p["rotational"] == 0.0 and all(p[k] == 0.0 for k in springs)
    assert p["kinetic"] == pytest.approx(plain.kinetic_energy(), rel=1e-12)
    assert p["total"] == pytest.approx(plain.kinetic_energy() + plain.potential_energy())
