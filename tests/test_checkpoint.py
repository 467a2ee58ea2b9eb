"""Save and resume: a loaded simulation continues bit for bit; loading runs no code from the
file (pickled parts only with allow_pickle=True on both sides); pickling continues too."""

import copy
import json
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
from numba import njit

import fastsdf as fs
from fastsdf.expr.graph import Symbol
from fastsdf.fields.band import NarrowBandGridSDF
from fastsdf.fields.grid import GridSDF
from fastsdf.io import load_simulation, save_simulation
from fastsdf.particles import ContactLaw, Drag, FieldForce, Gravity, ParticleSimulation
from fastsdf.particles.checkpoint import FORMAT
from fastsdf.shapes import SDF, Circle, Halfspace

WORLD = Halfspace([0.0, 1.0], -1.0) | Circle([0.3, 0.0], 0.4)
X, Y = Symbol("x"), Symbol("y")


@njit
def swirl(x, y, vx, vy, m, t):
    return -0.5 * y * m, 0.5 * x * m


def wind(p, t):
    """A Python force generator (the slow path), defined at module level so it pickles."""
    f = np.zeros((len(p), 2))
    f[:, 0] = 0.2 * np.sin(3.0 * t)
    return f


def make(world, user=False, python_force=False):
    """Particles in ``world`` under gravity and drag; on an exact world also a swirl: a
    FieldForce (data), or with ``user`` the same swirl as a numba force of this module (only
    pickled); ``python_force``: a Python generator too (only pickled)."""
    sim = ParticleSimulation(world, n=300, timestep=1 / 30, seed=np.random.default_rng(7), cr=0.7)
    sim.force_generators += [Gravity((0.1, -1.0)), Drag(0.05)]
    if world is WORLD:  # (a grid world's kernel without it is shared, cached)
        sim.force_generators.append(swirl if user else FieldForce(-0.5 * Y, 0.5 * X, per_mass=True))
    if python_force:
        sim.force_generators.append(wind)
    return sim


def assert_same(a, b):
    for name in ("x", "v", "m", "r", "cr", "cf"):
        np.testing.assert_array_equal(a.p[name], b.p[name], err_msg=name)
    assert a.t == b.t


# (the band is narrower than the particles' radii: see test_restart_bits)
@pytest.mark.filterwarnings("ignore:particles of radius up to")
@pytest.mark.parametrize("kind", ["grid", "band", "exact", "exact+user"])
def test_resume_is_bit_exact(tmp_path, kind):
    world = {
        "grid": lambda: GridSDF(WORLD, bounds=[(-2, 2), (-2, 2)], samples=[64j, 64j]),
        "band": lambda: NarrowBandGridSDF(WORLD, bounds=[(-2, 2), (-2, 2)], samples=[65j, 65j]),
    }.get(kind, lambda: WORLD)()
    user = kind.endswith("user")  # a numba force and a Python generator: pickled, opted in
    straight = make(world, user, user)  # the same calls, without saving between them
    straight.run(15)
    straight.run(25)
    first = make(world, user, user)
    first.run(15)
    path = tmp_path / "sim.npz"
    if user:
        with pytest.raises(ValueError, match=r"force_generators\[2\] \(swirl\) cannot be saved"):
            save_simulation(first, path)
        assert not path.exists()
    save_simulation(first, path, allow_pickle=user)
    meta = json.loads(bytes(np.load(path)["meta"]))
    assert meta["pickled"] == (
        ["sim.force_generators[2] (swirl)", "sim.force_generators[3] (wind)"] if user else []
    )
    if user:
        with pytest.raises(ValueError, match="holds pickled objects.*allow_pickle=True"):
            load_simulation(path)
    resumed = load_simulation(path, allow_pickle=user)
    assert type(resumed.sdf) is type(world) and resumed.dt == first.dt
    assert [type(g) for g in resumed.force_generators] == [type(g) for g in first.force_generators]
    resumed.run(25)
    assert_same(resumed, straight)
    # one call of 40 steps gives the same state (the clock differs by the rounding of its sum)
    once = make(world, user, user)
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
    sim = make(WORLD, user=True, python_force=True)
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
    # not data, and not even picklable: refused either way
    with pytest.raises(
        ValueError,
        match=r"force_generators\[3\] \(.*<lambda>\) cannot be saved as data.*FieldForce"
        r".*allow_pickle=True",
    ):
        save_simulation(sim, path)
    with pytest.raises(
        ValueError, match=r"force_generators\[3\] \(.*<lambda>\) cannot be saved, even pickled"
    ):
        save_simulation(sim, path, allow_pickle=True)
    assert path.read_bytes() == b"previous" and os.listdir(tmp_path) == ["sim.npz"]


def test_world_of_a_user_class_is_refused_at_save(tmp_path):
    class MyWorld(SDF):
        """A world class of the user's own (its methods are code a file cannot carry)."""

    sim = ParticleSimulation(MyWorld(WORLD.f), n=4, seed=1, lipschitz=1.0)
    with pytest.raises(ValueError, match=r"sim\.sdf \(.*\) cannot be saved as data.*MyWorld"):
        save_simulation(sim, tmp_path / "sim.npz")
    assert os.listdir(tmp_path) == []


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


# ---------------------------------------------------------------------------------------------
# Loading runs no code from the file.


class Marker:
    """Unpickling this creates the file ``path`` (a stand-in for any code a pickle can run)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def entries(path):
    with np.load(path) as data:
        return {name: data[name] for name in data.files}


def text(obj):
    return np.frombuffer(json.dumps(obj).encode(), dtype=np.uint8)


def test_crafted_files_run_no_code(tmp_path):
    # the payload is live: unpickled, it creates its file
    probe = tmp_path / "probe"
    pickle.loads(pickle.dumps(Marker(probe)))
    assert probe.exists()
    marker = tmp_path / "marker"
    payload = np.frombuffer(pickle.dumps(Marker(marker)), dtype=np.uint8)
    sim = make(WORLD)
    sim.run(2)
    good = entries(save_simulation(sim, tmp_path / "good.npz"))
    meta = json.loads(bytes(good["meta"]))
    state = json.loads(bytes(good["state"]))

    crafted = {}
    # 1. the first format: a pickle as a whole (the file claims to be a plain old checkpoint)
    old_meta = dict(meta, version=1)
    crafted["old"] = dict(good, meta=text(old_meta), simulation=payload)
    # 2. this format, the world replaced by a pickled part, the meta not saying so
    world = state["objects"][0]["state"]["dict"]["_sdf"]
    assert world == {"object": 3} and state["objects"][3]["class"].endswith("Union")
    lying = copy.deepcopy(state)
    lying["objects"][3] = {"class": "builtins.open", "state": {"dict": {}}}
    crafted["class"] = dict(good, state=text(lying))
    lying = copy.deepcopy(state)
    lying["objects"][0]["state"]["dict"]["_sdf"] = {"pickled": 0}
    crafted["pickled"] = dict(good, state=text(lying), pickled_0=payload)
    # 3. the state's array of positions holding a Python object (np.save pickles it)
    obj = np.empty(1, dtype=object)
    obj[0] = Marker(marker)
    crafted["object array"] = dict(good, x=obj)
    # 4. an expression graph whose symbol name would be code in the generated kernel
    lying = copy.deepcopy(state)
    sym = next(i for i, n in enumerate(lying["graph"]) if n[0] == "sym")
    lying["graph"][sym][2] = f"x + __import__('builtins').open({str(marker)!r}, 'w')"
    crafted["graph"] = dict(good, state=text(lying))
    expected = {
        "old": "first checkpoint format, a pickle.*allow_pickle=True",
        "class": "'builtins.open' is not a class a checkpoint holds",
        "pickled": "holds pickled objects.*allow_pickle=True",
        "object array": "array 'x' cannot be read as data",
        "graph": "Symbol name must be a Python identifier",
    }
    for kind, contents in crafted.items():
        path = tmp_path / f"{kind}.npz"
        np.savez(path, **contents)
        with pytest.raises(ValueError, match=expected[kind]):
            load_simulation(path)
        assert not marker.exists(), kind


def old_format(sim, path):
    """``sim`` written as the first format did (the state's arrays, the rest one pickle)."""
    state = sim.__getstate__()
    p = state.pop("p")
    state["_saved_params"] = dict(state.pop("params"))
    fields = list(p.keys())
    meta = {"format": FORMAT, "version": 1, "fields": fields}
    blob = pickle.dumps((type(sim), state))
    arrays = {name: p[name] for name in fields}
    np.savez(path, **arrays, meta=text(meta), simulation=np.frombuffer(blob, dtype=np.uint8))


def test_old_pickled_files_load_only_with_the_opt_in(tmp_path):
    sim, straight = make(WORLD), make(WORLD)
    sim.run(5)
    straight.run(5)
    straight.run(5)
    old_format(sim, tmp_path / "old.npz")
    with pytest.raises(ValueError, match="first checkpoint format"):
        ParticleSimulation.load(tmp_path / "old.npz")
    resumed = ParticleSimulation.load(tmp_path / "old.npz", allow_pickle=True)
    resumed.run(5)
    assert_same(resumed, straight)


def test_graph_data_rebuilds_the_same_nodes_and_checks_them():
    from fastsdf.expr.serial import GraphWriter, graph_from_data, graph_to_data

    shapes = [
        WORLD,
        fs.Polygon([[0, 0], [1, 0], [0.2, 1]]).round(0.1),
        fs.Ellipse((0.1, 0.2), (1.0, 0.5)),
        fs.Circle([fs.Param("cx", 0.25), 0.0], 0.5) | fs.Box().union(fs.Circle(), k=8.0),
    ]
    writer = GraphWriter()
    roots = [writer.add(s.f) for s in shapes]
    nodes = json.loads(json.dumps(writer.nodes))  # plain data, through JSON
    rebuilt = graph_from_data(nodes)
    # hash-consing: the same node objects; shared subexpressions written once
    assert [rebuilt[k] for k in roots] == [s.f for s in shapes]
    assert all(rebuilt[k] is s.f for k, s in zip(roots, shapes))
    assert len(nodes) == len({id(n) for n in rebuilt})
    assert graph_from_data(graph_to_data(WORLD.f))[-1] is WORLD.f
    # a constant that is not finite keeps its bits
    inf = fs.Halfspace([1.0, 0.0], 0.0).f * float("inf")
    assert graph_from_data(json.loads(json.dumps(graph_to_data(inf))))[-1] is inf
    bad = [
        ([["sym", [], "import os", None]], "Symbol name"),
        ([["exec", [], None, None]], "unknown operation 'exec'"),
        ([["sym", [], "x", None], ["prim", [0, 0], ["os.system", None], None]], "primitive kind"),
        ([["sym", [], "x", None], ["neg", [1], None, None]], "not an earlier node"),
        ([["sym", [], "x", None], ["smin", [0, 0], "1.0; import os", None]], "not a number"),
        ([["sym", [], "x", None], ["add", [0], None, None]], "takes 2 argument"),
    ]
    for nodes, message in bad:
        with pytest.raises(ValueError, match=message):
            graph_from_data(nodes)


def test_grains_with_contact_springs_resume_bit_for_bit(tmp_path):
    walls = Halfspace((0.0, 1.0), -0.3) | Halfspace((1.0, 0.0), -0.2) | Halfspace((-1.0, 0.0), -0.2)
    world = GridSDF(walls, bounds=[(-0.3, 0.3), (-0.4, 0.3)], samples=[41j, 41j])
    r = 0.02
    i, j = np.meshgrid(np.arange(4), np.arange(3))
    pos = np.stack([-0.2 + (2 * i.ravel() + 1) * r * 1.1, -0.3 + (2 * j.ravel() + 1) * r * 1.1], 1)
    pos += np.random.default_rng(0).uniform(-0.1 * r, 0.1 * r, pos.shape)
    law = ContactLaw(history=True, rolling_friction=0.2)

    def grains():
        sim = ParticleSimulation(world, positions=pos, radius=r, contacts=law)
        sim.force_generators.append(Gravity((0.0, -9.81)))
        return sim

    straight, first = grains(), grains()
    straight.run(6)
    first.run(3)
    pairs, springs, wall = first.engine.tangential_springs()
    assert np.count_nonzero(springs) and np.count_nonzero(wall)  # springs to carry
    path = first.save(tmp_path / "grains.npz")
    assert json.loads(bytes(np.load(path)["meta"]))["pickled"] == []
    resumed = ParticleSimulation.load(path)
    for a, b in zip(resumed.engine.tangential_springs(), (pairs, springs, wall)):
        np.testing.assert_array_equal(a, b)
    resumed.run(3)
    for name in ("x", "v", "omega"):
        np.testing.assert_array_equal(resumed.p[name], straight.p[name])
    assert resumed.t == straight.t
    assert np.abs(straight.p["x"] - pos).max() > 1e-3  # they moved


def test_a_fresh_process_resumes_bit_for_bit(tmp_path):
    """Another process (no node or kernel shared in memory) continues the same way."""
    sim, straight = make(WORLD), make(WORLD)
    sim.run(10)
    straight.run(10)
    straight.run(10)
    path = save_simulation(sim, tmp_path / "sim.npz")
    out = tmp_path / "x.npy"
    code = (
        "import sys, numpy as np; from fastsdf.io import load_simulation; "
        "s = load_simulation(sys.argv[1]); s.run(10); np.save(sys.argv[2], s.p['x'])"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    subprocess.run([sys.executable, "-c", code, str(path), str(out)], check=True, env=env)
    np.testing.assert_array_equal(np.load(out), straight.p["x"])


@pytest.mark.parametrize("name", ["particles", "grid", "grains"])
def test_files_of_an_earlier_fastsdf_continue_bit_for_bit(name):
    """Checkpoints written by fastsdf at revision 9af86bd (``tests/data/<name>_9af86bd.npz``:
    particles in a parametric exact world with resting contact, float32 particles in a grid,
    grains with contact history and rolling friction) load and continue as that version did:
    ``<name>_9af86bd_after.npz`` holds its state after ``steps`` more steps."""
    data = os.path.join(os.path.dirname(__file__), "data")
    sim = ParticleSimulation.load(os.path.join(data, f"{name}_9af86bd.npz"))
    after = np.load(os.path.join(data, f"{name}_9af86bd_after.npz"))
    sim.run(int(after["steps"]))
    assert sim.t == float(after["t"])
    for field in sim.p.FIELDS:
        got = np.asarray(sim.p[field])
        assert got.dtype == after[field].dtype
        np.testing.assert_array_equal(got, after[field], err_msg=field)
