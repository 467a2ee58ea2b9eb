"""Pickling of scenes and simulations; fastsdf.apps.distributed on a real 2-process LocalCluster.

The cluster tests start one LocalCluster (2 worker processes, 1 thread each, loopback only) for
the whole module and compare every distributed result with the single-process computation.
"""

import os
import pickle
import signal

import numpy as np
import pytest

import fastsdf as sdf
from fastsdf.particles import Drag, Gravity, ParticleSimulation
from fastsdf.shapes.scenes import seed_world
from fastsdf.viz.render import density_image


def _same(a, b):
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


# ---------------------------------------------------------------------------------------------
# Pickling (no cluster).


def test_sdf_pickle_is_the_graph_and_gives_the_same_bits(rng):
    f = seed_world()
    before = pickle.dumps(f)
    x, y = rng.uniform(-2.5, 2.5, (2, 5000))
    x[7] = np.nan
    d, g = f(x, y, compute_gradient=True)  # compiles: the pickle must not grow
    after = pickle.dumps(f)
    assert len(after) == len(before) < 20_000
    assert b"numba" not in after and b"fastsdf_scene" not in after
    f2 = pickle.loads(after)
    assert type(f2) is type(f) and f2.f is f.f and f2.exactness == f.exactness
    d2, g2 = f2(x, y, compute_gradient=True)
    assert _same(d, d2) and _same(g, g2) and _same(f(x, y), f2(x, y))


def test_deep_graph_pickles_without_recursion():
    g = sdf.Circle(center=[0, 0], radius=0.1)
    for i in range(3000):  # deeper than Python's recursion limit
        g = g | sdf.Circle(center=[0.01 * i, 0.0], radius=0.1)
    data = pickle.dumps(g)
    h = pickle.loads(data)
    assert h.f is g.f
    # In a process that never saw the graph the nodes are rebuilt: same text, same structure.
    from fastsdf.expr.graph import _from_flat, _to_flat

    flat = _to_flat(g.f)
    assert len(flat) > 3000 and _from_flat(flat) is g.f


def test_grid_pickle_holds_its_nodes_once_and_queries_the_same_bits(rng):
    world = seed_world()
    grid = sdf.GridSDF(world, samples=[120j, 90j])
    data = pickle.dumps(grid)
    assert grid.nbytes < len(data) < grid.nbytes + 20_000  # the node array once, no code
    g2 = pickle.loads(data)
    assert _same(g2.data, grid.data) and g2.exact.f is world.f
    x, y = rng.uniform(-3, 3, (2, 4000))  # inside and outside the bounds (mode 'exact')
    for cg in (False, True):
        a, b = grid(x, y, compute_gradient=cg), g2(x, y, compute_gradient=cg)
        assert all(_same(u, v) for u, v in zip(a, b)) if cg else _same(a, b)


def test_simulation_pickle_continues_with_the_same_bits():
    grid = sdf.GridSDF(seed_world(), samples=[100j, 100j])
    sim = ParticleSimulation(grid, 2000, seed=4)
    sim.force_generators = [Gravity(), Drag(0.2)]
    sim.run(5)
    clone = pickle.loads(pickle.dumps(sim))
    sim.run(30)
    clone.run(30)
    assert clone.t == sim.t
    for k in sim.p.keys():  # noqa: SIM118 - Particles has keys() but is not iterable
        assert _same(sim.p[k], clone.p[k])


# ---------------------------------------------------------------------------------------------
# A real cluster: 2 worker processes on the loopback interface.

distributed = pytest.importorskip("distributed")
from fastsdf.apps.distributed import (  # noqa: E402 - after the skip
    DistributedSimulation,
    ShardLostError,
    evaluate,
    local_cluster,
    shard_seed,
    shard_sizes,
)


@pytest.fixture(scope="module")
def client():
    with local_cluster(2, threads_per_worker=1) as cluster, distributed.Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def grid():
    return sdf.GridSDF(seed_world(), samples=[100j, 100j])


@pytest.mark.slow
def test_evaluate_dask_arrays_equal_the_single_process_call(client, rng):
    da = pytest.importorskip("dask.array")
    f = seed_world()
    x, y = rng.uniform(-2.5, 2.5, (2, 60, 50))
    x[3, 4] = np.inf
    ev, eg = f(x, y, compute_gradient=True)  # first here: the workers load these kernels
    dx, dy = da.from_array(x, chunks=(25, 20)), da.from_array(y, chunks=(30, 50))
    d = evaluate(f, dx, dy)
    dv, grad = evaluate(f, dx, dy, compute_gradient=True)
    assert d.shape == (60, 50) and grad.shape == (60, 50, 2) and d.chunks == dx.chunks
    rd, (rv, rg) = client.compute([d, (dv, grad)], sync=True)
    assert _same(rd, f(x, y))
    assert _same(rv, ev) and _same(rg, eg)
    assert np.isnan(rd[3, 4]) and np.isfinite(np.delete(rd.ravel(), 3 * 50 + 4)).all()
    # A grid travels too (its nodes are data; outside its bounds it answers exactly).
    g = sdf.GridSDF(f, samples=[64j, 64j])
    gv = g(x, y)
    assert _same(evaluate(g, dx, dy).compute(scheduler=client.get), gv)
    with pytest.raises(ValueError, match="same shape"):
        evaluate(f, dx, dy[:10])
    with pytest.raises(TypeError, match="f must be"):
        evaluate(lambda a, b: a, dx, dy)


def _wind(p, t):
    """A Python force generator (the slow path): a position-dependent push."""
    push = np.column_stack([0.3 * np.sin(3 * p["x"][:, 1]), np.zeros(len(p["x"]))])
    return push * p["m"][:, None]


def _lift(sim, i):
    """An ``init`` hook: move shard i's particles up by 0.1 i; returns 10 i."""
    sim.p["x"][:, 1] += 0.1 * i
    return 10 * i


def _reference(world, n, shards, seed, gens, runs, init=None, **kw):
    """The shards run one after another in this process (the documented construction)."""
    sims = []
    for i, size in enumerate(shard_sizes(n, shards)):
        s = ParticleSimulation(world, size, seed=shard_seed(seed, shards, i), **kw)
        if init is not None:
            init(s, i)
        s.force_generators = list(gens)
        for k in runs:
            s.run(k)
        sims.append(s)
    return sims


@pytest.mark.slow
def test_sharded_simulation_equals_shards_run_in_one_process(client, grid):
    n, shards, seed = 7001, 3, 11
    gens = [Gravity(), Drag(0.05)]
    runs = (1, 7, 12)
    ref = _reference(grid, n, shards, seed, gens, runs, cr=0.7)
    with DistributedSimulation(
        grid, n, client=client, shards=shards, seed=seed, force_generators=gens, cr=0.7
    ) as sim:
        assert len(set(sim.workers)) == 2  # both workers hold shards
        for k in runs:
            sim.run(k)
        assert sim.t == ref[0].t and sim.steps == sum(runs)
        p = sim.gather()
        for k in p.keys():  # noqa: SIM118 - Particles has keys() but is not iterable
            assert _same(p[k], np.concatenate([s.p[k] for s in ref])), k
        st = sim.stats()
        assert st.counts == tuple(shard_sizes(n, shards)) and st.n == n
        assert st.kinetic == sum(s.kinetic_energy() for s in ref)
        assert st.potential == sum(s.potential_energy() for s in ref)
        x = p["x"]
        assert st.bbox == (x[:, 0].min(), x[:, 1].min(), x[:, 0].max(), x[:, 1].max())
        bounds, shape = ((-2.0, 2.0), (-1.0, 2.5)), (70, 90)
        img = sim.density(bounds, shape)
        assert _same(img, density_image(x[:, 0], x[:, 1], bounds, shape))
        assert _same(img, np.histogram2d(x[:, 0], x[:, 1], bins=(90, 70), range=bounds)[0].T)
        smp = sim.sample(50, seed=2)
        assert len(np.unique(smp["index"])) == 50
        for k in p.keys():  # noqa: SIM118 - Particles has keys() but is not iterable
            assert _same(smp[k], p[k][smp["index"]])


@pytest.mark.slow
def test_python_force_generators_init_hook_and_changes_between_runs(client):
    world = seed_world()
    n, shards, seed = 3000, 2, 5
    ref = _reference(world, n, shards, seed, [Gravity(), _wind], (4,), init=_lift)
    with DistributedSimulation(
        world,
        n,
        client=client,
        shards=shards,
        seed=seed,
        force_generators=[Gravity(), _wind],
        init=_lift,
    ) as sim:
        assert sim.init_results == [0, 10]
        sim.run(4)
        sim.force_generators[:] = [Gravity(acceleration=(0.5, -2.0))]
        sim.run(3)
        for s in ref:
            s.force_generators = [Gravity(acceleration=(0.5, -2.0))]
            s.run(3)
        assert _same(sim.gather()["x"], np.concatenate([s.p["x"] for s in ref]))
        assert sim.energy()["total"] == pytest.approx(
            sum(s.energy()["total"] for s in ref), rel=1e-14
        )
        assert set(sim.energy()) == set(ref[0].energy())


@pytest.mark.slow
def test_bad_parameters_are_named_at_construction(client, grid):
    with pytest.raises(TypeError, match="client"):
        DistributedSimulation(grid, 10, client=None)
    with pytest.raises(ValueError, match="n must be >= shards"):
        DistributedSimulation(grid, 2, client=client, shards=3)
    with pytest.raises(ValueError, match="shards"):
        DistributedSimulation(grid, 10, client=client, shards=0)
    with pytest.raises(ValueError, match="timestep"):
        DistributedSimulation(grid, 10, client=client, timestep=-1)
    with pytest.raises(TypeError, match="force_generators"):
        DistributedSimulation(grid, 10, client=client, force_generators=[3])
    with pytest.raises(TypeError, match="world"):
        DistributedSimulation("circle", 10, client=client)


@pytest.mark.slow
def test_demo_on_the_cluster(client, tmp_path):
    from fastsdf.apps.cli import build_parser
    from fastsdf.apps.distributed import run_demo

    assert build_parser().parse_args(["demo", "--workers", "2"]).workers == 2
    # The single-process demo test's scenario and bound (particles spawned inside boxes
    # have been pushed out by step 45).
    res = run_demo(
        particles=3000,
        steps=45,
        grid=120,
        seed=3,
        frames=3,
        animate=False,
        out=str(tmp_path),
        client=client,
    )
    assert res.steps == 45 and res.particles == 3000 and "2 Dask worker" in res.sdf
    assert os.path.getsize(res.last_frame) > 10_000
    assert res.inside_fraction < 0.01


@pytest.mark.slow
def test_a_dead_worker_raises_naming_its_shards(client, grid):
    # Last in the module: it kills a worker (the nanny starts a fresh one).
    sim = DistributedSimulation(
        grid, 4000, client=client, shards=4, seed=1, force_generators=[Gravity()]
    )
    try:
        sim.run(2)
        victim = sim.workers[1]
        pid = client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(ShardLostError) as info:
            sim.run(3)
        lost = [i for i, w in enumerate(sim.workers) if w == victim]
        assert info.value.shards == tuple(lost) and victim in str(info.value)
        assert all(f"shard {i} on {victim}" in str(info.value) for i in lost)
        with pytest.raises(ShardLostError):  # and it stays an error: nothing resumes silently
            sim.density()
    finally:
        sim.close()
