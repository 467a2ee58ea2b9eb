"""The granular engine's CUDA target (``GranularSimulation(..., device='cuda')``), under
numba-cuda's simulator (tests/conftest.py sets ``NUMBA_ENABLE_CUDASIM=1``; the same tests run on
a GPU with ``NUMBA_ENABLE_CUDASIM=0``): the same physics as the CPU engine, step for step, with
and without contact history, across neighbour-list rebuilds and the reorder of grains; a
head-on impact's restitution; static friction on an incline; the list's overflow reported.
"""

import math
import pickle
import warnings

import numpy as np
import pytest

import fastsdf as fs
from fastsdf.device import available
from fastsdf.granular import ContactLaw, GranularSimulation, StartingStateWarning
from fastsdf.particles import Gravity, ParticleSimulation

pytestmark = pytest.mark.skipif(not available(), reason="numba-cuda is not installed")


@pytest.fixture(autouse=True)
def _one_thread():
    """A few dozen grains: one thread for the CPU engine."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(threads)


def bed(device, law, world, seed=1):
    """32 discs of radii 0.5-0.525 on a jittered hexagonal lattice (spacing 0.99: pressed),
    thrown at random velocities above ``world``, x periodic, gravity tilted: every contact
    kind, sliding and sticking, and list rebuilds within tens of substeps."""
    rng = np.random.default_rng(seed)
    j, i = np.divmod(np.arange(32), 8)
    pos = np.stack([(i + 0.5 * (j % 2)) * 0.99, 0.5 + j * 0.99 * math.sqrt(3) / 2], 1)
    pos[:, 0] += 0.01 * rng.standard_normal(32)
    with warnings.catch_warnings():  # (pressed on purpose)
        warnings.simplefilter("ignore", StartingStateWarning)
        return GranularSimulation(
            world,
            positions=pos,
            radius=0.5 * (1 + 0.05 * rng.random(32)),
            velocities=4.0 * rng.standard_normal((32, 2)),
            contacts=law,
            gravity=(0.3, -1.0),
            substep=3e-4,
            timestep=3e-4,
            skin=0.1,
            periodic_x=(0.0, 7.92),
            device=device,
        )


@pytest.mark.parametrize(
    "history, rolling", [(False, 0.0), (True, 0.0), (True, 0.1)], ids=["hooke", "history", "roll"]
)
def test_bed_steps_as_on_the_cpu(history, rolling):
    """The same bed on both targets agrees to rounding (the force sums run in another order)
    after each of three runs that rebuild the list (and reorder the grains) between them:
    state, the force on the floor, energies, the list's pairs and, with history, every
    contact's spring (carried across the rebuilds by matching neighbour ids)."""
    law = ContactLaw(2e4, 0.5, 0.5, 0.5, history=history, rolling_friction=rolling)
    floor = fs.Halfspace((0.0, 1.0), 0.0)
    cpu = bed("cpu", law, floor)
    gpu = bed("cuda", law, floor)
    assert type(gpu).__name__ == "CudaGranularSimulation"
    for _ in range(3):
        cpu.advance(20)
        gpu.advance(20)
        assert (gpu.rebuilds, gpu.time) == (cpu.rebuilds, cpu.time)
        np.testing.assert_array_equal(gpu.ids, cpu.ids)  # the device sort: the CPU's order
        np.testing.assert_allclose(gpu.positions, cpu.positions, rtol=0, atol=1e-12)
        np.testing.assert_allclose(gpu.velocities, cpu.velocities, rtol=0, atol=1e-9)
        np.testing.assert_allclose(gpu.angular_velocities, cpu.angular_velocities, atol=1e-9)
        np.testing.assert_allclose(gpu.wall_force, cpu.wall_force, rtol=1e-12, atol=1e-9)
    assert cpu.rebuilds >= 3  # the runs crossed rebuilds
    ec, eg = cpu.energy(), gpu.energy()
    for key in ec:
        assert eg[key] == pytest.approx(ec[key], rel=1e-12, abs=1e-9)
    assert gpu.contact_counts() == cpu.contact_counts()
    pairs, walls = cpu.contact_counts()
    assert pairs > 30 and walls > 0
    np.testing.assert_array_equal(gpu.neighbour_pairs(), cpu.neighbour_pairs())
    if history:
        pc, sc, wc = cpu.tangential_springs()
        pg, sg, wg = gpu.tangential_springs()
        np.testing.assert_array_equal(pg, pc)
        np.testing.assert_allclose(sg, sc, rtol=0, atol=1e-12)
        np.testing.assert_allclose(wg, wc, rtol=0, atol=1e-12)
        assert np.count_nonzero(sc) > 20  # springs in use, carried across the rebuilds


def test_grid_world_and_state_changes_as_on_the_cpu():
    """A GridSDF world (its sampler on the device) and ``set_state`` (a restart from new
    velocities) give the CPU's trajectory too; a pickled copy (device state through the host)
    continues bit for bit as the original."""
    floor = fs.shapes.union([fs.Halfspace((0.0, 1.0), 0.0), fs.Circle((4.0, 0.0), 0.8)])
    world = fs.GridSDF(floor, bounds=[(-1.0, 9.0), (-1.0, 5.0)], samples=[101, 61])
    law = ContactLaw(2e4, 0.5, 0.5, 0.5, history=True)
    cpu = bed("cpu", law, world, seed=2)
    gpu = bed("cuda", law, world, seed=2)
    cpu.advance(20)
    gpu.advance(20)
    v = np.random.default_rng(5).standard_normal((32, 2))
    cpu.set_state(velocities=v)
    gpu.set_state(velocities=v)
    copy = pickle.loads(pickle.dumps(gpu))
    cpu.advance(20)
    gpu.advance(20)
    np.testing.assert_allclose(gpu.positions, cpu.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gpu.velocities, cpu.velocities, rtol=0, atol=1e-9)
    assert cpu.contact_counts()[1] > 0
    copy.advance(20)
    np.testing.assert_array_equal(copy.positions, gpu.positions)
    np.testing.assert_array_equal(copy.tangential_springs()[1], gpu.tangential_springs()[1])


def test_head_on_restitution():
    """Two discs meeting head on rebound with the law's restitution (0.9: within 0.3% at 40
    substeps per contact) and keep their momentum, on the GPU alone."""
    e = 0.9
    sim = GranularSimulation(
        None,
        positions=[[-0.502, 0.0], [0.502, 0.0]],
        radius=0.5,
        velocities=[[1.0, 0.0], [-1.0, 0.0]],
        contacts=ContactLaw(1e4, e, 0.0, 0.0),
        gravity=(0.0, 0.0),
        timestep=1e-3,
        device="cuda",
    )
    contact = math.pi * math.sqrt(math.pi / 8 / 1e4)
    sim.advance(int(1.5 * contact / sim.substep) + 8)
    v = sim.velocities
    assert sim.contact_counts()[0] == 0  # apart again
    assert (v[1, 0] - v[0, 0]) / 2.0 == pytest.approx(e, rel=3e-3)
    assert v[:, 0].sum() == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("degrees, rests", [(12.0, True), (25.0, False)])
def test_disc_rests_below_atan_mu_and_slides_above(degrees, rests):
    """A disc that cannot roll (rolling resistance ``mu_r = 1 > tan theta``) on an incline
    with ``mu = 0.3`` (``atan mu = 16.7`` degrees), its contact with a spring (history): at 12
    degrees it comes to rest; at 25 it slides at ``g (sin - mu cos)``."""
    th = math.radians(degrees)
    t = np.array([math.cos(th), math.sin(th)])  # up the slope
    n = np.array([-math.sin(th), math.cos(th)])
    law = ContactLaw(200.0, 0.5, 0.3, history=True, rolling_friction=1.0)
    sim = GranularSimulation(
        fs.Halfspace((float(n[0]), float(n[1])), 0.0),
        positions=[0.5 * n],
        radius=0.5,
        contacts=law,
        gravity=(0.0, -1.0),
        timestep=0.5,
        substeps_per_contact=20,
        device="cuda",
    )
    sim.run(3)
    s0, v0 = float(sim.positions[0] @ t), float(sim.velocities[0] @ t)
    sim.run(2)
    s1, v1 = float(sim.positions[0] @ t), float(sim.velocities[0] @ t)
    if rests:  # (the spring's oscillation about the rest decays slowly: 3e-4 here)
        assert abs(s1 - s0) < 1e-3  # sliding covers 0.2 in that second
        assert abs(v1) < 2e-3
    else:
        assert (v1 - v0) / 1.0 == pytest.approx(-(math.sin(th) - 0.3 * math.cos(th)), rel=0.05)


def test_device_prefix_sum():
    """The rebuild's exclusive prefix sum on the device (runs per thread, their totals summed
    recursively) against NumPy's, at sizes of one, two and three levels."""
    from fastsdf.granular.cuda import cu

    sim = GranularSimulation(
        None, positions=[[0.0, 0.0]], radius=0.5, gravity=(0.0, 0.0), device="cuda"
    )
    rng = np.random.default_rng(0)
    for m in (1, 64, 65, 4097 + 64):
        counts = rng.integers(0, 5, m).astype(np.int32)
        a = cu.to_device(counts)
        sim._scan(a, m)
        np.testing.assert_array_equal(a.copy_to_host(), np.cumsum(counts) - counts)


def test_too_many_neighbours_is_reported():
    """A list with fewer slots than a grain's neighbours is a RuntimeError naming the count
    found and the parameter to raise."""
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    with pytest.raises(RuntimeError, match=r"4 neighbours.*max_neighbours=3.*max_neighbours=5"):
        GranularSimulation(
            None, positions=pos, radius=0.5, gravity=(0.0, 0.0), device="cuda", max_neighbours=3
        )


def test_device_and_world_are_checked():
    with pytest.raises(ValueError, match="device must be 'cpu' or 'cuda', got device='gpu'"):
        GranularSimulation(None, positions=[[0.0, 0.0]], radius=0.5, device="gpu")
    moving = fs.Halfspace((0.0, 1.0), fs.t)
    with pytest.raises(ValueError, match="static world"):
        GranularSimulation(moving, positions=[[0.0, 1.0]], radius=0.5, device="cuda")


def test_particle_family_reaches_the_cuda_engine():
    """``ParticleSimulation(..., contacts=ContactLaw(...), device='cuda')``: grains whose engine
    runs on the device, with the family's state window."""
    sim = ParticleSimulation(
        fs.Halfspace((0.0, 1.0), 0.0),
        positions=[[0.0, 0.6], [1.2, 0.6]],
        radius=0.5,
        contacts=ContactLaw(1e3, 0.5, 0.5),
        timestep=0.01,
        device="cuda",
    )
    sim.force_generators.append(Gravity((0.0, -1.0)))
    sim.run(3)
    assert type(sim.engine).__name__ == "CudaGranularSimulation"
    assert sim.p["x"].shape == (2, 2) and np.all(sim.p["v"][:, 1] < 0)
