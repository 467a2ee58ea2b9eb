"""Grains in the particle family: ParticleSimulation(world, positions=..., contacts=ContactLaw())
takes the family's names and tools (trajectories, video, save/load bit for bit, the notebook's
drawing, fused forces); ContactLaw() derives a stiffness at the library's scale; placed start
positions for non-interacting particles; the Dask refusal."""

import math
import pickle

import numpy as np
import pytest
from numba import njit

import fastsdf as fs
import fastsdf.graph as cg
import fastsdf.particles as phys
from fastsdf.granular import GranularSimulation, StartingStateWarning
from fastsdf.granular.params import derived_stiffness


def box_world(half_width, y0, y1, margin=0.1):
    """An open box: floor at y0, walls at +-half_width, sampled on a grid whose bounds span
    ``y0 - margin .. y1`` (the height a derived stiffness sees)."""
    walls = (
        fs.Halfspace((0.0, 1.0), y0)
        | fs.Halfspace((1.0, 0.0), -half_width)
        | fs.Halfspace((-1.0, 0.0), -half_width)
    )
    w = half_width + margin
    return fs.GridSDF(walls, bounds=[(-w, w), (y0 - margin, y1)], samples=[81j, 81j])


def lattice(nx, ny, r, x0, y0, gap=1.1, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    pos = np.stack([x0 + (2 * i.ravel() + 1) * r * gap, y0 + (2 * j.ravel() + 1) * r * gap], 1)
    return pos + rng.uniform(-jitter, jitter, pos.shape)


@pytest.fixture(scope="module")
def small_box():
    return box_world(0.2, -0.3, 0.3)


def grains(world, nx=6, ny=4, r=0.02, law=None, **kw):
    pos = lattice(nx, ny, r, -0.2, -0.3, jitter=0.1 * r)
    law = phys.ContactLaw() if law is None else law
    sim = phys.ParticleSimulation(world, positions=pos, radius=r, contacts=law, **kw)
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    return sim


def test_grains_are_a_member_of_the_family(small_box):
    sim = grains(small_box)
    assert isinstance(sim, phys.ParticleSimulation) and isinstance(sim, phys.GrainSimulation)
    assert sim.world is small_box and sim.sdf is small_box and sim.t == 0.0
    assert sim.p["x"].shape == (24, 2) and sim.p["v"].shape == (24, 2)
    np.testing.assert_array_equal(sim.p["r"], 0.02)
    np.testing.assert_allclose(sim.p["m"], math.pi * 0.02**2)
    x0 = sim.p["x"].copy()
    sim.run(2)
    assert sim.t == pytest.approx(2 / 30)
    # under gravity the grains fall onto the floor and stay out of it
    assert sim.p["x"][:, 1].mean() < x0[:, 1].mean()
    assert sim.p["x"][:, 1].min() > -0.3
    # the engine is the granular one, with the same physics
    assert isinstance(sim.engine, GranularSimulation)
    with pytest.raises(TypeError, match="cr= does not apply to grains"):
        phys.ParticleSimulation(small_box, positions=[[0, 0]], contacts=phys.ContactLaw(), cr=0.5)
    with pytest.raises(ValueError, match="need positions"):
        phys.ParticleSimulation(small_box, n=10, contacts=phys.ContactLaw())
    with pytest.raises(ValueError, match="n=5 does not match positions"):
        phys.ParticleSimulation(
            small_box, 5, positions=np.zeros((3, 2)) + [0, 0.1], contacts=phys.ContactLaw()
        )


#: The particles' fused-step machinery: a grain simulation has none of it.
PARTICLE_STEP_ONLY = {"_kernel", "_launch", "_pick_kernel", "_resume", "_kernels", "_exact_ptr"}


def test_each_member_inherits_only_what_it_uses(small_box):
    """The family shares its tools through one base (fastsdf.particles.family.Simulation);
    grains count as ParticleSimulation without inheriting the particles' step: neither their
    class nor an instance has any of its machinery, and every method of the base that a
    grain simulation inherits runs on one."""
    from fastsdf.particles.family import Simulation

    assert not PARTICLE_STEP_ONLY & set(dir(phys.GrainSimulation))
    sim = grains(small_box, nx=3, ny=2)
    assert not PARTICLE_STEP_ONLY & set(dir(sim))
    assert phys.ParticleSimulation not in type(sim).__mro__
    assert isinstance(sim, phys.ParticleSimulation) and issubclass(
        phys.GrainSimulation, phys.ParticleSimulation
    )
    particles = phys.ParticleSimulation(small_box, n=5, seed=0)
    assert isinstance(particles, Simulation) and isinstance(sim, Simulation)
    assert not isinstance(particles, phys.GrainSimulation)
    # what the members share, each from its own engine
    assert isinstance(sim.engine, GranularSimulation)
    assert isinstance(particles.engine, phys.engine.ParticleEngine)
    inherited = {
        name
        for name in dir(phys.GrainSimulation)
        if not name.startswith("__") and name not in vars(phys.GrainSimulation)
    }
    assert inherited <= set(vars(Simulation)) | {"_abc_impl"}, inherited
    sim.advance()
    sim.update(None)
    sim.check()
    assert sim.t == pytest.approx(2 / 30) and sim.world is small_box
    assert set(sim.host()) == set(sim.p.keys())
    np.testing.assert_array_equal(sim.host("x"), sim.p["x"])
    e = sim.kinetic_energy()
    v = sim.p["v"]
    assert e == pytest.approx(0.5 * float(np.sum(sim.p["m"] * (v * v).sum(1))))


def test_the_family_and_the_engine_take_the_same_arguments_and_gravity(small_box):
    """One way to make grains: the family's constructor and the engine's take the world first
    and the same keywords, and Gravity()'s default is the engine's: the two routes step the
    same grains to the same states (derived stiffness included)."""
    pos = lattice(6, 4, 0.02, -0.2, -0.3, jitter=0.002)
    law = phys.ContactLaw(history=True)
    args = dict(positions=pos, radius=0.02, contacts=law, timestep=1 / 30, skin=0.01)
    family = phys.ParticleSimulation(small_box, **args)
    family.force_generators.append(phys.Gravity())
    engine = GranularSimulation(small_box, **args)
    family.run(5)
    engine.run(5)
    assert family.engine.contact == engine.contact  # the same derived stiffness
    assert family.substeps_per_frame == engine.substeps_per_frame
    np.testing.assert_allclose(family.p["x"], engine.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(family.p["v"], engine.velocities, rtol=0, atol=1e-12)
    assert family.p["x"][:, 1].mean() < pos[:, 1].mean()  # both fell
    # the grains' own keywords on particles, and the particles' on grains, are named
    with pytest.raises(TypeError, match="wall_contacts= applies to grains only"):
        phys.ParticleSimulation(small_box, wall_contacts=law)
    with pytest.raises(TypeError, match="periodic_x= applies to grains only"):
        phys.ParticleSimulation(small_box, periodic_x=(0.0, 1.0))
    with pytest.raises(TypeError, match="rest_speed= does not apply to grains"):
        phys.ParticleSimulation(small_box, positions=pos, contacts=law, rest_speed=0.1)


def test_writes_to_p_reach_the_engine_and_masses_follow_radius(small_box):
    pos = [[-0.1, 0.0], [0.1, 0.0]]
    sim = phys.ParticleSimulation(small_box, positions=pos, contacts=phys.ContactLaw())
    # no gravity: a grain given a velocity moves freely
    sim.p["v"][0] = [1.0, 0.0]
    x = sim.p["x"][0].copy()
    sim.run(1)
    np.testing.assert_allclose(sim.p["x"][0], x + [1 / 30, 0.0], atol=1e-12)
    sim.p["m"][1] = 5.0
    with pytest.raises(ValueError, match="follows from their radius"):
        sim.run(1)


def test_fused_forces_act_on_grains_exactly():
    """A constant @njit force and a FieldForce on a lone grain (no world, no gravity):
    velocity Verlet is exact for a constant force, x = a t**2 / 2."""
    world = box_world(5.0, -5.0, 5.0)

    @njit
    def push(x, y, vx, vy, m, t):
        return 2.0 * m, 0.0

    up = phys.FieldForce(potential=-3.0 * cg.Symbol("y"), per_mass=True)  # (0, 3) per mass
    sim = phys.ParticleSimulation(
        world, positions=[[0.0, 0.0]], radius=0.02, contacts=phys.ContactLaw()
    )
    sim.force_generators += [push, up]
    sim.run(3)
    t = sim.t
    np.testing.assert_allclose(sim.p["x"][0], [0.5 * 2.0 * t * t, 0.5 * 3.0 * t * t], rtol=1e-9)
    # a Python generator would run at every substep: refused with what works
    sim.force_generators.append(lambda p, t: np.zeros((len(p), 2)))
    with pytest.raises(TypeError, match="@njit"):
        sim.run(1)


def test_drag_on_a_grain_decays_exponentially():
    world = box_world(5.0, -5.0, 5.0)
    sim = phys.ParticleSimulation(
        world,
        positions=[[0.0, 0.0]],
        velocities=[[1.0, 0.0]],
        radius=0.1,
        contacts=phys.ContactLaw(),
    )
    m = float(sim.p["m"][0])
    sim.force_generators.append(phys.Drag(0.5 * m))  # rate 0.5 / s
    sim.run(15)
    assert sim.p["v"][0, 0] == pytest.approx(math.exp(-0.5 * sim.t), rel=1e-5)


@pytest.mark.parametrize(
    "law",
    [
        phys.ContactLaw(),
        phys.ContactLaw(history=True, rolling_friction=0.2),  # springs carried in the file
    ],
    ids=["history-free", "history"],
)
def test_save_load_resumes_bit_for_bit(small_box, tmp_path, law):
    a = grains(small_box, nx=5, ny=3, law=law)
    b = grains(small_box, nx=5, ny=3, law=law)
    a.run(4)
    b.run(2)
    path = b.save(tmp_path / "grains.npz")
    c = phys.ParticleSimulation.load(path)
    assert isinstance(c, phys.GrainSimulation)
    np.testing.assert_array_equal(np.load(path)["x"], b.p["x"])  # readable without fastsdf
    c.run(2)
    for name in ("x", "v", "omega"):
        np.testing.assert_array_equal(c.p[name], a.p[name])
    assert c.t == a.t
    d = pickle.loads(pickle.dumps(b))
    d.run(2)
    np.testing.assert_array_equal(d.p["x"], a.p["x"])


def test_trajectory_video_and_notebook_drawing_take_grains(small_box, tmp_path):
    pytest.importorskip("h5py")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fastsdf.io import TrajectoryRecorder, read_trajectory
    from fastsdf.viz import record_video

    sim = grains(small_box, nx=3, ny=2)
    with TrajectoryRecorder(tmp_path / "g.h5", every=1, fields=("position", "radius")) as rec:
        sim.run(2, record=rec)
    traj = read_trajectory(tmp_path / "g.h5")
    assert traj["position"].shape == (3, 6, 2)
    np.testing.assert_array_equal(traj["position"][-1], sim.p["x"])
    np.testing.assert_array_equal(traj["step"], [0, 1, 2])
    video = record_video(
        sim, str(tmp_path / "g.mp4"), frames=2, bounds=small_box.bounds, size=(240, 200)
    )
    assert (tmp_path / "g.mp4").stat().st_size > 500, video
    fig, ax = plt.subplots()
    start = sim.reset(ax)
    assert sim.t == 0.0 and len(start) == 1
    np.testing.assert_array_equal(sim.p["x"], grains(small_box, nx=3, ny=2).p["x"])
    sim.update(ax)
    assert sim.t == pytest.approx(1 / 30)
    anim = phys.create_animation(fig, ax, sim, frames=2)
    anim._init_draw()
    plt.close(fig)


def test_derived_stiffness_holds_a_settled_pile_within_one_percent():
    """A pile half as tall as its world, settled in a box: the derived stiffness keeps its
    largest overlap (grain-grain and grain-floor) within 1% of the diameter, and not far below
    (half the world's column: about 0.5%; a law far stiffer than needed would cost
    substeps)."""
    r, d = 0.02, 0.04
    world = box_world(0.1, -0.15, 0.6, margin=0.05)  # height 0.8; the pile about 0.41
    pos = lattice(5, 10, r, -0.1, -0.15, gap=1.02, jitter=0.01 * r)
    # five gapped columns are wider than the box: the right column starts pressed into its
    # wall, which the starting-state check reports (the springs push it back in a few substeps)
    with pytest.warns(StartingStateWarning, match="^10 grains start inside the world"):
        sim = phys.ParticleSimulation(
            world, positions=pos, radius=r, contacts=phys.ContactLaw(restitution=0.2)
        )
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    assert sim.contacts.stiffness == pytest.approx(derived_stiffness(1.0, 9.81, 0.8))
    sim.run(20)
    assert np.abs(sim.p["v"]).max() < 0.01  # settled (falling a grain's gap: 0.1 m/s)
    x = sim.p["x"]
    gap = np.hypot(*(x[:, None, :] - x[None, :, :]).transpose(2, 0, 1))
    overlap = (d - gap)[np.triu_indices(len(x), 1)]
    floor = (r - (x[:, 1] + 0.15)).max()
    worst = max(overlap.max(), floor) / d
    assert 0.002 <= worst <= 0.01


def test_library_scale_grains_step_at_most_1500_substeps_per_frame():
    """Grains of r = 0.02 under g = 9.81 in the library's [-2, 2]^2 world: the derived law's
    substeps per 1/30 s frame (the simulation's own figure), against 7,573 with the former
    fixed stiffness 2e5."""
    world = fs.GridSDF(
        fs.Halfspace((0.0, 1.0), -1.8), bounds=[(-2, 2), (-2, 2)], samples=[41j, 41j]
    )
    pos = lattice(10, 2, 0.02, -0.5, 0.0)
    sim = phys.ParticleSimulation(world, positions=pos, radius=0.02, contacts=phys.ContactLaw())
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    assert sim.substeps_per_frame <= 1500
    old = phys.ParticleSimulation(
        world, positions=pos, radius=0.02, contacts=phys.ContactLaw(stiffness=2e5)
    )
    old.force_generators.append(phys.Gravity((0.0, -9.81)))
    assert old.substeps_per_frame == 7573
    # the contact time sets it: 40 substeps per contact of two grains
    m = math.pi * 0.02**2
    tc = math.pi * math.sqrt(m / 2 / derived_stiffness(1.0, 9.81, 4.0))
    assert sim.substeps_per_frame == math.ceil((1 / 30) / (tc / 40) - 1e-9)


def test_placed_particles_start_where_given_and_the_blob_is_unchanged():
    world = fs.Halfspace((0.0, 1.0), -1.8)
    blob = phys.ParticleSimulation(world, n=50, seed=3)
    again = phys.ParticleSimulation(world, n=50, seed=3, contacts=None)
    for name in phys.Particles.FIELDS:
        np.testing.assert_array_equal(blob.p[name], again.p[name])
    pos = np.random.default_rng(0).uniform(-1, 1, (7, 2))
    sim = phys.ParticleSimulation(
        world, positions=pos, radius=np.linspace(0.01, 0.07, 7), density=2.0
    )
    assert sim.n == 7
    np.testing.assert_array_equal(sim.p["x"], pos)
    np.testing.assert_array_equal(sim.p["v"], 0.0)
    np.testing.assert_allclose(sim.p["m"], 2.0 * math.pi * np.linspace(0.01, 0.07, 7) ** 2)
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    sim.run(3)
    sim.reset()
    np.testing.assert_array_equal(sim.p["x"], pos)
    moving = phys.ParticleSimulation(world, positions=pos, velocities=np.ones((7, 2)))
    np.testing.assert_array_equal(moving.p["v"], 1.0)
    assert np.all((moving.p["r"] >= 0.01) & (moving.p["r"] <= 0.1))  # the notebook's sizes
    with pytest.raises(ValueError, match="velocities must be finite, of shape"):
        phys.ParticleSimulation(world, positions=pos, velocities=np.ones((3, 2)))
    with pytest.raises(ValueError, match="positions must have shape"):
        phys.ParticleSimulation(world, positions=np.ones(3))


def test_dask_refuses_grains_and_says_what_shards():
    from fastsdf.apps.distributed import DistributedSimulation

    with pytest.raises(
        ValueError, match="non-interacting particles.*halo exchange|halo exchange.*non-interacting"
    ):
        DistributedSimulation(
            fs.Halfspace((0.0, 1.0), -1.8), 100, client=None, contacts=phys.ContactLaw()
        )


def test_a_dense_bed_of_grains_holds_at_most_200_bytes_per_grain():
    """Grains in a hexagonal packing, each touching six neighbours: the engine's arrays, its
    neighbour list and the start kept for reset() (the state window empty while stepping)."""
    r, side = 0.02, 40
    i, j = np.meshgrid(np.arange(side), np.arange(side))
    pos = np.stack([(2 * i + (j % 2)).ravel() * r, (j * math.sqrt(3) * r).ravel()], 1)
    world = fs.GridSDF(
        fs.Halfspace((0.0, 1.0), -r), bounds=[(-0.1, 1.7), (-0.1, 1.5)], samples=[21j, 21j]
    )
    sim = phys.ParticleSimulation(world, positions=pos, radius=r, contacts=phys.ContactLaw())
    sim.run(1)
    assert len(sim.engine.neighbour_pairs()) >= 2.9 * side * side  # about 3 pairs per grain
    assert sim.memory_per_grain() <= 200
    sim.p["x"]  # reading the state fills the window until the next step
    assert sim.memory_per_grain() > 200
    sim.run(1)
    assert sim.memory_per_grain() <= 200
