"""NarrowBandGridSDF: equality with a dense grid of the same spacing in the band, sound far
answers (lower bounds with the right sign, against brute force), continuity across tile edges,
tolerance builds that meet their tolerance on random scenes, the numba sampler contract, and
particles that neither tunnel nor rest differently from the dense grid."""

import math

import numpy as np
import pytest
from conftest import brute_distance
from numba import njit

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.fields.band import NarrowBandGridSDF, band_points, measure_band_error, sample_band
from fastsdf.fields.grid import GridSDF
from fastsdf.shapes.scenes import seed_world

BOUNDS = [(-2, 2), (-2, 2)]


def _two_circles():
    """Two overlapping circles: the exact SDF of the union is known by brute force (the
    distance to the boundary arcs outside the other circle)."""
    return sdf.Circle(center=[-0.4, 0.1], radius=0.7) | sdf.Circle(center=[0.5, -0.2], radius=0.6)


def _two_circles_boundary(n=20_000):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    a = np.stack([-0.4 + 0.7 * np.cos(t), 0.1 + 0.7 * np.sin(t)], axis=1)
    b = np.stack([0.5 + 0.6 * np.cos(t), -0.2 + 0.6 * np.sin(t)], axis=1)
    a = a[np.hypot(a[:, 0] - 0.5, a[:, 1] + 0.2) >= 0.6]
    b = b[np.hypot(b[:, 0] + 0.4, b[:, 1] - 0.1) >= 0.7]
    return np.concatenate([a, b])


def _random_scene(seed):
    """A union of random circles and rotated boxes, some smoothly blended."""
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace(normal=[0, 1], d=-1.7)
    for k in range(4):
        c = rng.uniform(-1.2, 1.2, 2)
        with sdf.smoothness(float(rng.choice([0, 8]))):
            if k % 2:
                f |= sdf.Circle(center=c, radius=float(rng.uniform(0.15, 0.4)))
            else:
                with sdf.transform(angle=float(rng.uniform(-1, 1)), offset=c):
                    f |= sdf.Box(minc=[-0.3, -0.2], maxc=[0.3, 0.2])
    return f


@pytest.fixture(scope="module")
def world():
    return seed_world()


def test_exported_from_package():
    assert sdf.NarrowBandGridSDF is NarrowBandGridSDF
    assert "NarrowBandGridSDF" in sdf.__all__


@pytest.mark.parametrize("samples", [[129j, 129j], [130, 97]])
def test_band_values_equal_a_dense_grid_of_the_same_spacing(world, samples):
    band = 0.06
    g = NarrowBandGridSDF(world, bounds=BOUNDS, band=band, samples=samples)
    dense = GridSDF(world, bounds=BOUNDS, samples=samples)
    assert g.spacing == dense.spacing
    # Every stored node is the dense grid's node, bitwise.
    nf = g.n_fine
    assert 0 < nf < g.tiles[0] * g.tiles[1]
    fine = np.flatnonzero(g._table >= 0)
    ti, tj = fine // g.tiles[1], fine % g.tiles[1]
    nx, ny = dense.shape
    for k in range(0, nf, max(1, nf // 40)):
        i0, j0 = ti[k] * 8, tj[k] * 8
        i1, j1 = min(i0 + 9, nx), min(j0 + 9, ny)
        np.testing.assert_array_equal(g._q[k, : i1 - i0, : j1 - j0], dense.data[i0:i1, j0:j1])
    # Queries in the band agree to rounding.
    xs, ys = band_points(g, 50_000, seed=1)
    inb = np.abs(world(xs, ys)) <= band
    assert inb.sum() > 10_000
    d, gr = g(xs[inb], ys[inb], compute_gradient=True)
    dd, dg = dense(xs[inb], ys[inb], compute_gradient=True)
    np.testing.assert_allclose(d, dd, rtol=0, atol=1e-13)
    np.testing.assert_allclose(gr, dg, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "band, lo, hi", [(0.03, -0.03, 0.03), ((-0.01, 0.06), -0.01, 0.06), ((0.0, 0.04), 0.0, 0.04)]
)
def test_every_band_point_lies_in_a_fine_tile(world, band, lo, hi):
    g = NarrowBandGridSDF(world, bounds=BOUNDS, band=band, samples=[257j, 257j])
    assert g.band_range == (lo, hi)
    rng = np.random.default_rng(2)
    xs, ys = rng.uniform(-2, 2, (2, 400_000))
    d = world(xs, ys)
    inb = (d >= lo) & (d <= hi)
    assert inb.sum() > 1000
    assert g.is_fine(xs[inb], ys[inb]).all()
    # Far answers keep their guarantee on both sides of an asymmetric band: a lower bound of
    # |d| with d's sign, and never inside the band.
    far = ~g.is_fine(xs, ys)
    gf = g(xs[far], ys[far])
    assert np.all(np.abs(gf) <= np.abs(d[far])) and np.all(np.sign(gf) * np.sign(d[far]) >= 0)
    assert not np.any((d[far] >= lo) & (d[far] <= hi))


def test_an_asymmetric_band_stores_less_and_agrees_with_the_symmetric_one_inside_it(world):
    """A band reaching 0.12 outside and 0.01 inside (for particles of radius up to 0.1) stores
    fewer fine tiles than the symmetric band of 0.12 and answers the same values in its range."""
    sym = NarrowBandGridSDF(world, bounds=BOUNDS, band=0.12, samples=[257j, 257j])
    asym = NarrowBandGridSDF(world, bounds=BOUNDS, band=(-0.01, 0.12), samples=[257j, 257j])
    assert asym.n_fine < 0.8 * sym.n_fine and asym.nbytes < sym.nbytes
    xs, ys = band_points(asym, 50_000, seed=5)
    d = world(xs, ys)
    inb = (d > -0.01) & (d < 0.12)
    assert inb.sum() > 10_000
    va, ga = asym(xs[inb], ys[inb], compute_gradient=True)
    vs, gs = sym(xs[inb], ys[inb], compute_gradient=True)
    np.testing.assert_array_equal(va, vs)
    np.testing.assert_array_equal(ga, gs)
    err = measure_band_error(asym, n=50_000)
    assert err.band_n > 10_000 and err.band_value_max < 0.01


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_far_answers_are_lower_bounds_with_the_right_sign(dtype):
    f = _two_circles()
    boundary = _two_circles_boundary()
    g = NarrowBandGridSDF(f, bounds=BOUNDS, band=0.05, samples=[161j, 161j], dtype=dtype)
    rng = np.random.default_rng(3)
    pts = rng.uniform(-2, 2, (3000, 2))
    far = ~g.is_fine(pts[:, 0], pts[:, 1])
    assert far.sum() > 2000
    pts = pts[far]
    truth = brute_distance(pts, boundary)  # unsigned distance to the union's boundary
    inside = (np.hypot(pts[:, 0] + 0.4, pts[:, 1] - 0.1) < 0.7) | (
        np.hypot(pts[:, 0] - 0.5, pts[:, 1] + 0.2) < 0.6
    )
    d, grad = g(pts[:, 0], pts[:, 1], compute_gradient=True)
    # The boundary is sampled at spacing < 2.2e-4, so the true distance is at least the brute
    # one less 1.1e-4: this checks |d| <= true distance.
    assert np.all(np.abs(d) <= truth - 1.2e-4)
    assert np.all(np.abs(d) > 0.05 - g.spacing[0])  # far tiles lie beyond the band
    assert np.all((d < 0) == inside)
    # Far tiles answer the direction of the exact gradient at their centre (4096 directions).
    hx, hy = g.spacing
    ti, tj = np.floor((pts[:, 0] + 2) / (8 * hx)), np.floor((pts[:, 1] + 2) / (8 * hy))
    _, gc = f((ti * 8 + 4) * hx - 2, (tj * 8 + 4) * hy - 2, compute_gradient=True)
    np.testing.assert_allclose(np.hypot(grad[:, 0], grad[:, 1]), 1.0, rtol=0, atol=1e-12)
    cos = np.sum(grad * gc, axis=1) / np.hypot(gc[:, 0], gc[:, 1])
    assert np.all(cos > math.cos(math.radians(0.05)))


def test_continuous_across_tile_edges(world):
    g = NarrowBandGridSDF(world, bounds=BOUNDS, band=0.1, samples=[257j, 257j])
    hx, hy = g.spacing
    xs, ys = band_points(g, 20_000, seed=4)
    # Snap to the nearest vertical tile edge and step a hair to either side.
    edge = np.round((xs + 2) / (8 * hx)) * 8 * hx - 2
    ok = (edge > -2) & (edge < 2)
    eps = 1e-9
    a = g(edge[ok] - eps, ys[ok])
    b = g(edge[ok] + eps, ys[ok])
    both = g.is_fine(edge[ok] - eps, ys[ok]) & g.is_fine(edge[ok] + eps, ys[ok])
    assert both.sum() > 1000
    assert np.max(np.abs(a - b)[both]) < 10 * eps


@pytest.mark.parametrize("seed", [0, 1])
def test_tolerance_builds_meet_their_tolerance(seed):
    f = _random_scene(seed)
    for tol in (1e-3, 1e-4):
        g = NarrowBandGridSDF(f, bounds=BOUNDS, band=0.05, tolerance=tol)
        err = g.measure_error(n=100_000, seed=seed)
        assert err.band_n > 20_000
        assert err.band_value_max <= tol, (seed, tol, err, g)
    # A tighter tolerance chooses a finer spacing.
    coarse = NarrowBandGridSDF(f, bounds=BOUNDS, band=0.05, tolerance=1e-3)
    assert g.spacing[0] < coarse.spacing[0]


def test_tolerance_build_marks_kinks_exact_and_uses_the_exact_sdf_there():
    f = sdf.Box(minc=[-0.5, -0.5], maxc=[0.5, 0.5])  # kinks on the diagonals inside
    g = NarrowBandGridSDF(f, bounds=BOUNDS, band=0.05, tolerance=1e-5)
    assert g.n_exact_cells > 0
    # Points on the box's inner diagonals, in the band: answered exactly.
    t = np.linspace(0.46, 0.5, 101)
    d, grad = g(t, t, compute_gradient=True)
    de, ge = f(t, t, compute_gradient=True)
    np.testing.assert_allclose(d, de, rtol=0, atol=1e-15)


def test_sampler_contract_from_njit_code(world):
    g = NarrowBandGridSDF(world, bounds=BOUNDS, band=0.05, samples=[129j, 129j], tolerance=1e-4)

    @njit
    def run(data, xs, ys):
        out = np.empty((xs.shape[0], 3))
        ins = np.empty(xs.shape[0], dtype=np.bool_)
        for i in range(xs.shape[0]):
            d, gx, gy, inside = sample_band(data, xs[i], ys[i])
            out[i, 0] = d
            out[i, 1] = gx
            out[i, 2] = gy
            ins[i] = inside
        return out, ins

    rng = np.random.default_rng(5)
    xs, ys = rng.uniform(-2.5, 2.5, (2, 5000))
    xs[:3] = [np.nan, np.inf, 0.0]
    ys[:3] = [0.0, 0.0, -np.inf]
    out, ins = run(g.sampler_data, xs, ys)
    assert g.sampler is sample_band
    d, grad = g(xs, ys, compute_gradient=True)
    inb = (np.abs(xs) <= 2) & (np.abs(ys) <= 2)
    assert not ins[~inb].any()
    assert np.isnan(out[~ins]).all()
    np.testing.assert_array_equal(out[ins, 0], d[ins])
    np.testing.assert_array_equal(out[ins, 1:], grad[ins])
    # Where the sampler says "not inside", the batch call used the exact SDF (NaN for NaN input).
    fin = ~ins & np.isfinite(xs) & np.isfinite(ys)
    np.testing.assert_array_equal(d[fin], world(xs[fin], ys[fin]))
    assert np.isnan(d[:3]).all()


def test_serial_and_parallel_paths_and_value_only_agree(world):
    g = NarrowBandGridSDF(world, bounds=BOUNDS, band=0.05, samples=[200j, 200j])
    rng = np.random.default_rng(6)
    xs, ys = rng.uniform(-2.2, 2.2, (2, 20_000))
    d, grad = g(xs, ys, compute_gradient=True)
    np.testing.assert_array_equal(g(xs, ys), d)
    d2, g2 = g(xs[:1000], ys[:1000], compute_gradient=True)  # serial kernel
    np.testing.assert_array_equal(d2, d[:1000])
    np.testing.assert_array_equal(g2, grad[:1000])
    assert g(xs.reshape(100, 200), ys.reshape(100, 200)).shape == (100, 200)


def test_float32_storage_error_and_memory(world):
    a = NarrowBandGridSDF(world, bounds=BOUNDS, band=0.05, samples=[129j, 129j])
    b = NarrowBandGridSDF(world, bounds=BOUNDS, band=0.05, samples=[129j, 129j], dtype=np.float32)
    assert b.n_fine == a.n_fine
    assert a.memory["nodes"] == a.n_fine * 81 * 3 * 8 == 2 * b.memory["nodes"]
    assert a.nbytes == sum(a.memory.values())
    assert a.memory["table"] == 4 * a.tiles[0] * a.tiles[1]
    xs, ys = band_points(a, 20_000, seed=7)
    fine = a.is_fine(xs, ys)
    da, db = a(xs[fine], ys[fine]), b(xs[fine], ys[fine])
    assert np.max(np.abs(da - db)) <= 2.0**-24 * np.max(np.abs(a._q[..., 0])) * 1.01


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(band=0), ValueError, "band"),
        (dict(band=-1), ValueError, "band"),
        (dict(band="x"), TypeError, "band"),
        (dict(band=(0.01, 0.2)), ValueError, "band=.*lo <= 0 <= hi"),
        (dict(band=(-0.1, -0.01)), ValueError, "band=.*lo <= 0 <= hi"),
        (dict(band=(0.0, 0.0)), ValueError, "band=.*lo < hi"),
        (dict(band=(-0.1, math.inf)), ValueError, "band"),
        (dict(band=(0.1,)), TypeError, "band must be"),
        (dict(band=(-0.1, "a")), TypeError, "band=.*two real numbers"),
        (dict(samples=None), ValueError, "samples= .* or tolerance="),
        (dict(tolerance=0), ValueError, "tolerance"),
        (dict(samples=[1, 5]), ValueError, "samples"),
        (dict(bounds=[(1, 0), (0, 1)]), ValueError, "bounds"),
        (dict(dtype=np.int32), ValueError, "dtype"),
        (dict(lipschitz=0), ValueError, "lipschitz"),
        (dict(lipschitz=math.inf), ValueError, "lipschitz"),
    ],
)
def test_bad_parameters_are_rejected(world, kwargs, exc, match):
    args = dict(bounds=BOUNDS, band=0.05, samples=[65j, 65j])
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        NarrowBandGridSDF(world, **args)


def test_f_must_be_an_sdf_and_unknown_lipschitz_uses_interval_bounds():
    with pytest.raises(TypeError, match="f must be"):
        NarrowBandGridSDF(lambda x, y: x, band=0.1, samples=[10, 10])
    import fastsdf.graph as cg

    x, y = cg.Symbol("x"), cg.Symbol("y")
    bare = cg.Function(x * x + y - 1.0, [x, y])
    # Without a known Lipschitz bound, tiles are classified by interval bounds.
    for lip in (3.0, None):
        g = NarrowBandGridSDF(
            bare, bounds=[(-1, 1), (-1, 1)], band=0.1, samples=[33, 33], lipschitz=lip
        )
        assert g.lipschitz == lip
        xs, ys = np.random.default_rng(8).uniform(-1, 1, (2, 5000))
        d = g(xs, ys)
        exact = bare(xs, ys)
        assert g.is_fine(xs[np.abs(exact) <= 0.1], ys[np.abs(exact) <= 0.1]).all()
        far = ~g.is_fine(xs, ys)
        assert far.any()
        assert np.all(np.abs(d[far]) <= np.abs(exact[far])) and np.all(d[far] * exact[far] > 0)


@pytest.mark.slow
@pytest.mark.parametrize("width", [0.15, (-0.05, 0.15)])
def test_particles_on_a_band_grid_do_not_tunnel_and_rest_as_on_the_dense_grid(world, width):
    # The band covers the largest radius (0.1) with room on the outside: every contact is in a
    # fine tile.
    band = NarrowBandGridSDF(world, bounds=BOUNDS, band=width, samples=[200j, 200j])
    dense = GridSDF(world, bounds=BOUNDS, samples=[200j, 200j])
    finals = []
    for g in (band, dense):
        sim = phys.ParticleSimulation(g, n=3000, seed=11)
        sim.force_generators += [phys.Gravity()]
        sim.run(240)
        finals.append((sim.p["x"].copy(), sim.p["v"].copy(), sim.p["r"].copy()))
    (xb, vb, r), (xd, vd, _) = finals
    # Never tunnels: every particle is above the funnel's floor and not inside matter by more
    # than the grid's interpolation error.
    assert np.all(np.isfinite(xb))
    pen = r - world(xb[:, 0], xb[:, 1])
    assert pen.max() < 0.01
    assert np.all(xb[:, 1] > -1.8)
    # Rests as on the dense grid of the same spacing: the band grid answers the same values
    # wherever a particle touches, so resting particles end where they end on the dense grid.
    rest = (np.linalg.norm(vd, axis=1) < 0.05) & (np.linalg.norm(vb, axis=1) < 0.05)
    assert rest.mean() > 0.2
    disp = np.linalg.norm(xb - xd, axis=1)[rest]
    assert np.median(disp) < 1e-6
