"""Pruning per tile: pruned evaluation equals the unpruned kernel bit for bit for hard chains
(random scenes, hypothesis), stays within ``tol`` for exponential chains, and is used by
``f(x, y)`` and GridSDF construction."""

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

import fastsdf as sdf
from fastsdf.expr.graph import evaluate_numpy

finite = dict(allow_nan=False, allow_infinity=False)
_NO_SHRINK = (Phase.explicit, Phase.reuse, Phase.generate)


def _bits(a, b):
    return np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


def _scene(seed, n, k=0.0, kinds=("box", "circle"), op="|", extra=True):
    """A chain of small same-shape primitives (folded into loops over tables) at random places,
    optionally with a few unfolded operands and a nested chain."""
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace([0.2, 1], -1.7) if extra else None
    for i in range(n):
        kind = kinds[i % len(kinds)]
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)):
            s = (
                sdf.Box([-0.05, -0.03], [0.04, 0.06])
                if kind == "box"
                else sdf.Circle([0.01, 0.0], 0.04)
            )
        if f is None:
            f = s
        elif op == "|":
            f = f.union(s, k=k)
        else:
            f = f.intersection(s, k=k)
    if extra:
        f = f | sdf.Circle([0.5, -0.5], 0.2)
    return f


@pytest.mark.slow
@settings(
    max_examples=3,
    deadline=None,
    derandomize=True,
    phases=_NO_SHRINK,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    seed=st.integers(0, 10**6),
    n=st.integers(8, 40),
    op=st.sampled_from(["|", "&"]),
    extra=st.booleans(),
    tiles=st.integers(1, 12),
)
def test_pruned_hard_chains_are_bit_identical(seed, n, op, extra, tiles):
    f = _scene(seed, n, op=op, extra=extra)
    rng = np.random.default_rng(seed)
    p = rng.uniform(-2.3, 2.3, (2, 3000))
    p[:, :7] = [[-2.3, 2.3, -2.3, 2.3, 0.0, np.nan, 1.0], [-2.3, -2.3, 2.3, 2.3, 0.0, 1.0, np.inf]]
    d0, g0 = f(*p, compute_gradient=True, prune=False)
    comp = f.compiled
    plan = comp.plan(((-2.3, 2.3), (-2.3, 2.3)), tiles=(tiles, tiles + 1))
    out, grad = comp.run(p[0].copy(), p[1].copy(), "vg", plan)
    assert _bits(out, d0) and _bits(grad, g0)
    assert np.isnan(out[5]) and np.isnan(out[6]) and np.all(np.isnan(grad[5:7]))
    if tiles >= 8 and op == "|":
        assert plan.fraction < 0.6  # a union of small shapes: most operands drop out


def test_pruned_call_is_automatic_for_large_inputs_and_matches():
    f = _scene(7, 60, kinds=("box",), extra=True)
    p = np.random.default_rng(0).uniform(-2, 2, (2, 100_000))
    d_auto, g_auto = f(*p, compute_gradient=True, backend="kernel")  # the kernel decides
    assert f.compiled._plans, "the automatic path built a plan"
    d0, g0 = f(*p, compute_gradient=True, prune=False)
    assert _bits(d_auto, d0) and _bits(g_auto, g0)
    assert _bits(f(*p), f(*p, prune=False))  # value only
    rep = f.pruning_report([(-2, 2), (-2, 2)], tiles=(16, 16))
    assert rep["operands"] == 60 and rep["survivors_max"] <= 60
    assert 0 < rep["survivors_mean"] < 30 and rep["build_s"] >= 0
    # The reference for the same points (independent implementation).
    np.testing.assert_allclose(
        d_auto[:500],
        evaluate_numpy(f.f, {"x": p[0, :500], "y": p[1, :500]}),
        rtol=1e-12,
        atol=1e-12,
    )


@pytest.mark.parametrize("k", [40.0])
def test_pruned_exponential_chains_stay_within_tol(k):
    f = _scene(3, 40, k=k, kinds=("box",), extra=False)
    p = np.random.default_rng(1).uniform(-2, 2, (2, 5000))
    d0, g0 = f(*p, compute_gradient=True, prune=False)
    comp = f.compiled
    for tol in (None, 1e-9, 1e-4, 1e-2):
        plan = comp.plan(((-2.0, 2.0), (-2.0, 2.0)), tiles=(16, 16), tol=tol)
        out, grad = comp.run(p[0].copy(), p[1].copy(), "vg", plan)
        bound = (1e-15 if tol is None else tol) + 1e-14 * (1 + np.abs(d0))
        assert np.all(np.abs(out - d0) <= bound)
        if tol == 1e-2 and k == 40.0:
            assert plan.fraction < 0.5


def test_grid_construction_uses_pruning_and_matches():
    import fastsdf.function as F

    f = _scene(11, 80, kinds=("box",), extra=True)
    g = sdf.GridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[300j, 300j])
    assert f.compiled._plans
    old = F.PRUNE_MIN_POINTS
    try:
        F.PRUNE_MIN_POINTS = 10**15
        g2 = sdf.GridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[300j, 300j])
    finally:
        F.PRUNE_MIN_POINTS = old
    assert _bits(g.data, g2.data)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(counts=st.lists(st.integers(0, 1300), min_size=1, max_size=12), seed=st.integers(0, 99))
def test_tile_blocks_cover_every_point_once_with_the_union_of_their_tiles_rows(counts, seed):
    from fastsdf.backends.kernel.drive import _merge_rows, _tile_work
    from fastsdf.backends.kernel.simd import BLOCK

    rng = np.random.default_rng(seed)
    T, sizes = len(counts), [7, 3]
    starts = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    order = rng.permutation(int(starts[-1])).astype(np.int64)
    tile_of = np.repeat(np.arange(T), counts)[np.argsort(order)]  # tile of each point
    lists = [[np.flatnonzero(rng.random(n) < 0.4) for n in sizes] for _ in range(T)]
    act = np.concatenate([r for tl in lists for r in tl] + [np.zeros(0)]).astype(np.int64)
    offs = np.zeros((T, len(sizes) + 1), dtype=np.int64)
    at = 0
    for t in range(T):
        for g, r in enumerate(lists[t]):
            offs[t, g] = at
            at += len(r)
        offs[t, -1] = at
    seq, work = _tile_work(order, starts)
    assert np.array_equal(np.sort(seq), np.arange(starts[-1]))
    assert work[:, 1].sum() == starts[-1] and np.all((work[:, 1] > 0) & (work[:, 1] <= BLOCK))
    padded = sum(1 for w in work if w[1] < BLOCK)
    assert padded <= 1  # only the last shared block is partly empty
    actb, offb = np.empty(sum(sizes), np.int64), np.empty(len(sizes) + 1, np.int64)
    cur = np.empty(T, np.int64)
    for s, m, t0, t1 in work:
        tiles = tile_of[seq[s : s + m]]
        assert t0 <= tiles.min() and tiles.max() <= t1
        if t0 == t1:
            continue
        _merge_rows(act, offs, t0, t1, starts, actb, offb, cur)
        for g in range(len(sizes)):
            want = sorted(
                set().union(*[set(lists[t][g].tolist()) for t in range(t0, t1 + 1) if counts[t]])
            )
            assert actb[offb[g] : offb[g + 1]].tolist() == want


def _initial_velocities(n):
    return np.random.default_rng(5).normal(0, 1, (n, 2))


def _particle_run(world, prune, n=3000, steps=30):
    """Positions and velocities after ``steps`` steps of ``n`` falling particles; ``prune=False``
    builds the simulation as for a small scene (the scene's own per-point function, every
    row) and never builds a plan."""
    import fastsdf.function as F
    import fastsdf.particles as phys

    old = F.PRUNE_MIN_OPERANDS, F.PRUNE_MIN_POINTS
    if not prune:
        F.PRUNE_MIN_OPERANDS = F.PRUNE_MIN_POINTS = 10**15
    try:
        sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=3)
        sim.force_generators += [phys.Gravity()]
        sim.p.x[:] = np.random.default_rng(4).uniform(-2.4, 2.4, (n, 2))
        sim.p.v[:] = _initial_velocities(n)
        sim.run(steps)
    finally:
        F.PRUNE_MIN_OPERANDS, F.PRUNE_MIN_POINTS = old
    return sim


@pytest.mark.slow
def test_particle_step_on_an_exact_sdf_pruned_gives_identical_trajectories():
    f = _scene(5, 60, kinds=("box",), extra=True)
    on, off = _particle_run(f, True), _particle_run(f, False)
    assert on.engine.plan is not None and on.engine.plan.fraction < 0.5  # the plan was used
    assert off.engine.plan is None and len(off.engine.data) == 1  # the scene's inline function
    assert _bits(on.p.x, off.p.x) and _bits(on.p.v, off.p.v)
    assert np.abs(on.p.x - off.p.x).max() == 0 and on.t == off.t
    # some particles hit boxes: their velocity is not that of free fall (gravity 1 for 1 s)
    free = _initial_velocities(3000) + [0.0, -1.0]
    assert np.sum(np.abs(on.p.v - free).max(axis=1) > 1e-6) > 30


@pytest.mark.slow
def test_grid_exact_fallback_pruned_gives_identical_trajectories():
    f = _scene(6, 60, kinds=("box",), extra=True)
    g = sdf.GridSDF(f, bounds=[(-1, 1), (-1, 1)], samples=[81j, 81j], mode="exact")
    on, off = _particle_run(g, True, steps=40), _particle_run(g, False, steps=40)
    assert on.engine.plan is not None  # particles outside the grid used a plan
    assert off.engine.plan is None
    assert _bits(on.p.x, off.p.x) and _bits(on.p.v, off.p.v)
    # the pruned C function equals the scene's kernel at points outside the grid
    p = np.random.default_rng(2).uniform(-2.4, 2.4, (2, 2000))
    d, grad = on.query(*p)
    d0, g0 = f(*p, compute_gradient=True, prune=False)
    out = (np.abs(p[0]) > 1) | (np.abs(p[1]) > 1)
    assert _bits(d[out], d0[out]) and _bits(grad[out], g0[out])


@pytest.mark.slow
@settings(
    max_examples=3,
    deadline=None,
    derandomize=True,
    phases=_NO_SHRINK,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    seed=st.integers(0, 10**6),
    n=st.integers(10, 40),
    kind=st.sampled_from(["quadratic", "cubic"]),
    k=st.sampled_from([0.02, 0.1, 0.4]),
    tiles=st.integers(1, 12),
)
def test_pruned_polynomial_chains_are_bit_identical(seed, n, kind, k, tiles):
    # runs of boxes (folded into loops) between circles, blended left to right with one k
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace([0.2, 1], -1.7)
    for i in range(n):
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)):
            s = (
                sdf.Circle([0.01, 0.0], 0.04)
                if i % 9 == 4
                else sdf.Box([-0.05, -0.03], [0.04, 0.06])
            )
        f = f.union(s, k=k, kind=kind)
    comp = f.compiled
    assert comp.groups and all(g.op in ("qmin", "cmin") for g in comp.groups)
    p = rng.uniform(-2.3, 2.3, (2, 3000))
    p[:, :3] = [[0.0, np.nan, 1.0], [0.0, 1.0, np.inf]]
    d0, g0 = f(*p, compute_gradient=True, prune=False)
    # the folded chain is the nested binary blends, in the written order
    ref = evaluate_numpy(f.f, {"x": p[0, 3:], "y": p[1, 3:]})
    np.testing.assert_allclose(d0[3:], ref, rtol=1e-12, atol=1e-12)
    plan = comp.plan(((-2.3, 2.3), (-2.3, 2.3)), tiles=(tiles, tiles + 1))
    out, grad = comp.run(p[0].copy(), p[1].copy(), "vg", plan)
    assert _bits(out, d0) and _bits(grad, g0)
    if tiles >= 8 and k < 0.4:
        assert plan.fraction < 0.6


def _mixed_chain(seed, n, k, op):
    """Boxes, ellipses and polygons (compiled primitives) at random places in one chain."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)):
            shapes.append(
                [
                    sdf.Box([-0.05, -0.03], [0.04, 0.06]),
                    sdf.Ellipse([0, 0], [0.06, 0.03]),
                    sdf.Star([0, 0], 0.07, 5),
                ][i % 3]
            )
    shapes.append(sdf.Halfspace([0.2, 1], -1.7))
    return sdf.union(shapes, k=k) if op == "|" else sdf.intersection(shapes, k=k)


@settings(max_examples=8, deadline=None, derandomize=True, phases=_NO_SHRINK)
@given(
    seed=st.integers(0, 10**6),
    n=st.integers(12, 45),
    op=st.sampled_from(["|", "&"]),
    k=st.sampled_from([0.0, 5.0, 40.0]),
    tol=st.sampled_from([None, 1e-6]),
    tiles=st.sampled_from([(8, 8), (32, 32), (20, 7), (3, 40)]),
)
def test_coarse_to_fine_plans_are_sound_and_no_looser_than_the_dense_rule(
    seed, n, op, k, tol, tiles
):
    # Plans over many tiles bound each chain's members coarse to fine: a member that cannot
    # matter anywhere in a coarse tile is dropped in all its tiles. Checked against the values
    # of every operand (NumPy reference) at random points: each tile keeps the operands that
    # reach the chain's minimum (maximum) there, and for the exponential blends the dropped
    # operands change the value by less than the tolerance; the plan keeps at most the rows of
    # the dense rule (every member bounded over every tile: its Lipschitz bounds around a small
    # tile's centre can be looser than the coarse tile's).
    from fastsdf.backends import prune

    f = _mixed_chain(seed, n, k, op)
    groups = f.compiled.groups
    assert len(groups) == 3 and any(g.steps[-1][0].op == "prim" for g in groups)
    bounds = ((-2.5, 2.5), (-2.4, 2.6))
    plan = prune.make_plan(groups, bounds, *tiles, tol)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(prune, "_COARSE_TOP_TILES", 10**9)  # the fine tiles alone
        dense = prune.make_plan(groups, bounds, *tiles, tol)
    assert plan.act.size <= dense.act.size
    rng = np.random.default_rng(seed)
    p = np.stack([rng.uniform(*bounds[0], 2000), rng.uniform(*bounds[1], 2000)])
    order, starts = prune.bin_points(p[0], p[1], plan)
    tile = np.empty(p.shape[1], dtype=np.int64)
    for t in range(len(starts) - 1):
        tile[order[starts[t] : starts[t + 1]]] = t
    pts = {"x": p[0], "y": p[1]}
    sign = 1.0 if op == "|" else -1.0  # a max is the min of the negated operands
    vals, kept = [], []
    for gi, g in enumerate(groups):
        for j, m in enumerate(g.members):
            vals.append(sign * evaluate_numpy(m, pts))
            rows = [
                set(plan.act[plan.offs[t, gi] : plan.offs[t, gi + 1]].tolist())
                for t in range(plan.nx * plan.ny)
            ]
            kept.append(np.array([j in rows[t] for t in tile]))
    vals += [sign * evaluate_numpy(o, pts) for o in groups[0].others]
    kept += [np.ones(p.shape[1], dtype=bool)] * len(groups[0].others)
    vals, kept = np.array(vals), np.array(kept)
    low = vals.min(axis=0)
    if k == 0.0:
        assert np.all(kept[vals == low[None, :]])
    else:
        lost = np.log1p(np.sum(np.where(kept, 0.0, np.exp(-k * (vals - low))), axis=0)) / k
        assert np.all(lost <= (tol if tol is not None else np.spacing(np.abs(low))))
    if op == "|" and k == 0.0 and tiles[0] * tiles[1] >= 256:
        assert plan.fraction < 0.5
