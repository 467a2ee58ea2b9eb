"""The compiled frame writer: splats against brute force, and the videos it writes."""

import math
import os

import numpy as np
import pytest
from matplotlib.colors import to_rgb

from fastsdf.viz.frames import (
    VideoWriter,
    color_table,
    composite,
    record_video,
    splat_counts,
    splat_discs,
)

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

BOUNDS = ((-2.0, 2.0), (-1.0, 2.0))
SMALL = dict(size=(320, 240), samples=24, fps=10)


def brute_counts(x, y, x0, y1, sx, sy, h, w):
    """Per pixel, the number of points whose scaled coordinates fall in its unit square."""
    fx, fy = (x - x0) * sx, (y1 - y) * sy
    out = np.zeros((h, w), dtype=np.int64)
    for i in range(h):
        for j in range(w):
            out[i, j] = np.count_nonzero((fx >= j) & (fx < j + 1) & (fy >= i) & (fy < i + 1))
    return out


def test_splat_counts_matches_brute_force(rng):
    h, w, x0, y1 = 23, 31, -1.0, 1.5
    sx, sy = w / 2.0, h / 3.0
    x = rng.uniform(-1.3, 1.3, 2000)
    y = rng.uniform(-1.8, 1.8, 2000)
    # points exactly on pixel edges, on the bounds, and non-finite ones
    x[:40] = x0 + rng.integers(0, w + 1, 40) / sx
    y[:40] = y1 - rng.integers(0, h + 1, 40) / sy
    x[40], y[41], x[42] = np.nan, np.inf, -np.inf
    counts = np.zeros((h, w), dtype=np.uint16)
    splat_counts(x, y, x0, y1, sx, sy, counts)
    expect = brute_counts(x, y, x0, y1, sx, sy, h, w)
    np.testing.assert_array_equal(counts, expect)
    assert expect.sum() > 1000  # the comparison is not vacuous


def test_splat_counts_saturates():
    counts = np.zeros((2, 2), dtype=np.uint16)
    x = np.full(70000, 0.25)
    splat_counts(x, x, 0.0, 1.0, 2.0, 2.0, counts)
    assert counts[1, 0] == 65535 and counts.sum() == 65535


def test_splat_discs_matches_brute_force(rng):
    h, w, x0, y1 = 40, 50, 0.0, 4.0
    sx = sy = 10.0  # 5 x 4 data units
    n = 60
    x = rng.uniform(-0.5, 5.5, n)
    y = rng.uniform(-0.5, 4.5, n)
    r = rng.uniform(0.0, 0.6, n)
    r[:5] = 0.01  # smaller than a pixel: the centre pixel only
    r[5] = -1.0  # negative: treated as 0
    x[6] = np.nan
    r[7] = np.inf
    counts = np.zeros((h, w), dtype=np.uint16)
    splat_discs(x, y, r, x0, y1, sx, sy, counts)
    jc, ic = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    expect = np.zeros((h, w), dtype=bool)
    for p in range(n):
        cx, cy, rr = (x[p] - x0) * sx, (y1 - y[p]) * sy, max(r[p], 0.0)
        if not np.isfinite([cx, cy, rr]).all():
            continue
        if rr > 0:
            expect |= ((jc - cx) / (rr * sx)) ** 2 + ((ic - cy) / (rr * sy)) ** 2 <= 1.0
        expect |= (np.floor(jc) == np.floor(cx)) & (np.floor(ic) == np.floor(cy))
    np.testing.assert_array_equal(counts.astype(bool), expect)
    assert 100 < expect.sum() < h * w


def test_composite_matches_blend_formula(rng):
    counts = rng.integers(0, 9, size=(12, 17)).astype(np.uint16)
    colors = rng.uniform(0, 1, size=(6, 3))  # counts >= 5 take the last colour
    table, keep = color_table(colors, 0.8)
    frame = rng.integers(0, 256, size=(20, 30, 3)).astype(np.uint8)
    before = frame.copy()
    composite(counts, table, keep, frame, 3, 5)
    c = np.minimum(counts, 5)
    col = np.rint(colors * 255).astype(np.int64)[c] * 205  # round(0.8 * 256) = 205
    blended = (before[3:15, 5:22].astype(np.int64) * 51 + col) >> 8
    expect = before.copy()
    expect[3:15, 5:22] = np.where(counts[..., None] > 0, blended, before[3:15, 5:22])
    np.testing.assert_array_equal(frame, expect)


def read_video(path):
    reader = imageio_ffmpeg.read_frames(path)
    meta = next(reader)
    w, h = meta["size"]
    return meta, [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]


def cluster(rng, cx, cy, n=3000, sd=0.03):
    return rng.normal(cx, sd, n), rng.normal(cy, sd, n)


def test_video_frames_positions_and_fixed_scale(tmp_path, rng):
    path = str(tmp_path / "clip.mp4")
    centres = [(-1.0, 1.0), (0.0, 0.5), (1.0, 0.0), (1.5, 1.5)]
    with VideoWriter(
        path, None, BOUNDS, mode="density", scale_frames=2, title="test", **SMALL
    ) as writer:
        for k, (cx, cy) in enumerate(centres):
            # frame k: one cluster, of growing size; the scale comes from frames 0 and 1
            x, y = cluster(rng, cx, cy, n=1000 * (k + 1))
            writer.add(x, y, t=0.1 * k, step=k)
        assert not os.path.exists(path)  # nothing at the path before the video is complete
        vmax_seen = writer.vmax
    assert sorted(os.listdir(tmp_path)) == ["clip.mp4"]  # and no temporary file left
    meta, frames = read_video(path)
    assert len(frames) == 4 and meta["size"] == (320, 240)
    for k, (cx, cy) in enumerate(centres):
        row, col = writer.pixel(cx, cy)
        far_row, far_col = writer.pixel(*centres[(k + 2) % 4])  # empty in frame k
        here = frames[k][row - 1 : row + 2, col - 1 : col + 2].astype(float).mean((0, 1))
        there = frames[k][far_row, far_col].astype(float)
        # the particles' dark orange, against the light free-space colour
        assert here[2] < 120 and there.min() > 200, (k, here, there)
    # the colour bar and axes are the same in every frame (static background, fixed scale)
    bar = (slice(None), slice(writer.pixel(2.0, 0.0)[1] + 4, None))
    for f in frames[1:]:
        assert np.abs(f[bar].astype(int) - frames[0][bar].astype(int)).mean() < 1.5
    # the scale came from the first two frames: their largest count
    assert vmax_seen >= 2 and writer.vmax == vmax_seen


def test_colour_of_a_count_does_not_change_between_frames(tmp_path, rng):
    writer = VideoWriter(str(tmp_path / "a.mp4"), None, BOUNDS, mode="density", vmax=100, **SMALL)
    x, y = np.array([-1.0]), np.array([1.0])
    few = writer.render(x, y).copy()
    many_x = np.concatenate([x, np.full(500, 1.0)])
    many_y = np.concatenate([y, np.full(500, 0.0)])
    many = writer.render(many_x, many_y).copy()
    row, col = writer.pixel(-1.0, 1.0)
    np.testing.assert_array_equal(few[row, col], many[row, col])
    # a pixel over the scale's top takes its top colour; one particle a lighter one
    r2, c2 = writer.pixel(1.0, 0.0)
    assert int(many[r2, c2].sum()) < int(many[row, col].sum())


def test_only_the_clock_changes_with_time(tmp_path, rng):
    writer = VideoWriter(str(tmp_path / "a.mp4"), None, BOUNDS, mode="discs", **SMALL)
    x, y = cluster(rng, 0.0, 0.5, n=50)
    a = writer.render(x, y, 0.02, t=1.0, step=30).copy()
    b = writer.render(x, y, 0.02, t=2.5, step=75).copy()
    rows, cols = np.nonzero((a != b).any(axis=2))
    assert rows.size > 10
    top_row, right_col = writer.pixel(-2.0, 2.0)[0], writer.pixel(2.0, 2.0)[1]
    assert rows.max() < top_row and cols.max() <= right_col  # above the axes, at its right
    np.testing.assert_array_equal(a, writer.render(x, y, 0.02, t=1.0, step=30))


def test_discs_video_of_a_simulation(tmp_path):
    from fastsdf.particles import Gravity, ParticleSimulation
    from fastsdf.shapes import Halfspace

    floor = Halfspace([0.0, 1.0], -1.0)  # the world of test_io_trajectory (one kernel)
    sim = ParticleSimulation(floor, n=20, timestep=1 / 30, seed=1)
    sim.force_generators.append(Gravity())
    sim.p["r"] = 0.1
    path = record_video(
        sim,
        str(tmp_path / "sim.mp4"),
        frames=3,
        steps_per_frame=5,
        bounds=BOUNDS,
        title="20 particles",
        **SMALL,
    )
    _, frames = read_video(path)
    assert len(frames) == 3 and abs(sim.t - 10 / 30) < 1e-12
    # the last frame shows a disc at each particle's place
    with VideoWriter(str(tmp_path / "b.mp4"), floor, BOUNDS, **SMALL) as w:
        w.add(sim.p["x"][:, 0], sim.p["x"][:, 1], sim.p["r"])
        assert w.mode == "discs"
    x = sim.p["x"]
    for k in range(0, 20, 4):
        if BOUNDS[0][0] < x[k, 0] < BOUNDS[0][1] and BOUNDS[1][0] < x[k, 1] < BOUNDS[1][1]:
            row, col = w.pixel(x[k, 0], x[k, 1])
            assert frames[-1][row, col, 2] < 110, frames[-1][row, col]


def test_failed_video_leaves_nothing(tmp_path, rng):
    path = tmp_path / "keep.mp4"
    path.write_bytes(b"old")
    with (
        pytest.raises(ZeroDivisionError),
        VideoWriter(str(path), None, BOUNDS, mode="density", vmax=10, **SMALL) as w,
    ):
        w.add(*cluster(rng, 0, 0))
        raise ZeroDivisionError("a failure while frames are written")
    assert path.read_bytes() == b"old" and sorted(os.listdir(tmp_path)) == ["keep.mp4"]


@pytest.mark.parametrize(
    "kw, word",
    [
        ({"mode": "dots"}, "mode"),
        ({"size": (321, 240)}, "size"),
        ({"vmax": 1.0}, "vmax"),
        ({"fps": 0}, "fps"),
        ({"scale_frames": 0}, "scale_frames"),
    ],
)
def test_bad_parameters_are_named(tmp_path, kw, word):
    with pytest.raises(ValueError, match=word):
        VideoWriter(str(tmp_path / "x.mp4"), None, **kw)


def test_discs_need_radii(tmp_path):
    w = VideoWriter(str(tmp_path / "x.mp4"), None, mode="discs", **SMALL)
    with pytest.raises(ValueError, match="r "):
        w.add([0.0], [0.0])
    empty = w.render([], [])  # no particles: the background alone
    np.testing.assert_array_equal(empty[w.pixel(0.0, 0.0)], empty[w.pixel(1.0, 1.0)])


def test_a_moving_world_is_drawn_at_each_frames_time(tmp_path):
    """A disc moving right at unit speed: its solid is drawn where the world is negative at the
    frame's time, and only there (pixel centres against the analytic disc)."""
    import fastsdf as sdf
    from fastsdf.viz.plotting import BACKGROUND_COLOR, SOLID_COLOR

    with sdf.transform(offset=[-1.0 + sdf.t, 0.0]):
        world = sdf.Circle(center=[0.0, 0.0], radius=0.5)
    writer = VideoWriter(str(tmp_path / "m.mp4"), world, BOUNDS, mode="discs", **SMALL)
    assert writer.moving
    solid = np.array(to_rgb(SOLID_COLOR)) * 255
    free = np.array(to_rgb(BACKGROUND_COLOR)) * 255
    x, y = np.array([5.0]), np.array([5.0])  # no particle on the axes
    for t in (0.0, 2.0):
        frame = writer.render(x, y, 0.01, t=t).astype(float)
        for px, py in [(-1.0, 0.0), (1.0, 0.0), (-1.0 + t + 0.3, 0.2), (0.0, 1.0)]:
            row, col = writer.pixel(px, py)
            inside = math.hypot(px - (-1.0 + t), py) < 0.45  # clear of the edge's pixels
            outside = math.hypot(px - (-1.0 + t), py) > 0.55
            if inside:
                np.testing.assert_allclose(frame[row, col], solid, atol=1.0)
            elif outside:
                np.testing.assert_allclose(frame[row, col], free, atol=3.0)
    with pytest.raises(ValueError, match="time t"):
        writer.render(x, y, 0.01)
