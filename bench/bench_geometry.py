"""Geometry in and out: the distance transform against scipy, mask and image error tables.

    python -m bench --only geometry          # writes bench/results/geometry.md
    python -m bench.bench_geometry [--quick] # prints the section

Distance transform: fastsdf.geometry's parallel Felzenszwalb-Huttenlocher transform against
``scipy.ndimage.distance_transform_edt`` on the same mask in the same process (identical
distances checked). Error tables: analytic shapes rasterised at several resolutions, their
grids' node values against the exact SDF.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from .common import stamp, table, timeit


def _disc_mask(n: int, count: int = 300, seed: int = 1) -> np.ndarray:
    """A micrograph-like mask: random overlapping discs (True) on a void."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((n, n), dtype=bool)
    rows = np.arange(n)[:, None]
    cols = np.arange(n)[None, :]
    for cy, cx, r in zip(
        rng.uniform(0, n, count),
        rng.uniform(0, n, count),
        rng.uniform(0.005, 0.04, count) * n,
        strict=True,
    ):
        r0, r1 = max(0, int(cy - r)), min(n, int(cy + r) + 1)
        c0, c1 = max(0, int(cx - r)), min(n, int(cx + r) + 1)
        mask[r0:r1, c0:c1] |= (rows[r0:r1] - cy) ** 2 + (cols[:, c0:c1] - cx) ** 2 < r * r
    return mask


def _edt_section(n: int) -> str:
    from scipy import ndimage

    from fastsdf.geometry.edt import distance_transform, signed_distance_transform

    mask = _disc_mask(n)
    distance_transform(mask[:64, :64])
    signed_distance_transform(mask[:64, :64])

    def scipy_signed(m):
        return np.where(
            m, 0.5 - ndimage.distance_transform_edt(m), ndimage.distance_transform_edt(~m) - 0.5
        )

    rows = []
    load0 = os.getloadavg()[0]
    for name, ours, ref in (
        (
            "unsigned (True pixels to the nearest False)",
            distance_transform,
            ndimage.distance_transform_edt,
        ),
        ("signed (both phases, half-pixel shift)", signed_distance_transform, scipy_signed),
    ):
        same = bool(np.array_equal(ours(mask), ref(mask)))
        t_ours, s_ours = timeit(ours, mask, repeats=3, warmup=0)
        t_ref, s_ref = timeit(ref, mask, repeats=3, warmup=0)
        rows.append(
            [
                name,
                f"{t_ours:.3f} s ({s_ours:.0%})",
                f"{t_ref:.3f} s ({s_ref:.0%})",
                f"{t_ref / t_ours:.2f}x",
                "yes" if same else "NO",
            ]
        )
    load1 = os.getloadavg()[0]
    return (
        f"### Distance transform of a {n}x{n} mask (random discs, "
        f"{mask.mean():.0%} inside), 2 threads vs scipy (1 thread)\n\n"
        + table(["transform", "fastsdf", "scipy", "speed-up", "identical"], rows)
        + f"\n\nLoad average {load0:.1f} at the start, {load1:.1f} at the end (2 cores). "
        "Medians of 3 runs (spread in brackets).\n"
    )


def _raster(f, n: int, supersample: int = 1) -> np.ndarray:
    """Coverage of ``f < 0`` per pixel of an n x n image of [-1, 1]^2, row 0 at the top."""
    px = 2.0 / n
    xc = -1 + (np.arange(n) + 0.5) * px
    X, Y = np.meshgrid(xc, xc[::-1])
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    cov = np.zeros((n, n))
    for dy in sub:
        for dx in sub:
            cov += f(X + dx * px, Y + dy * px) < 0
    return cov / supersample**2


def _error_section(sizes) -> str:
    import fastsdf as sdf
    from fastsdf.geometry import from_image, from_mask

    shapes = {
        "circle r=0.6": sdf.Circle([0.1, -0.2], 0.6),
        "box 1.2 x 0.8": sdf.Box([-0.7, -0.5], [0.5, 0.3]),
    }
    rows = []
    for name, f in shapes.items():
        for n in sizes:
            px = 2.0 / n
            cov = _raster(f, n, supersample=16)
            gm = from_mask(cov > 0.5, [(-1, 1), (-1, 1)])
            gi = from_image((cov * 255).round().astype(np.uint8), [(-1, 1), (-1, 1)])
            X, Y = np.meshgrid(*gm.axes, indexing="ij")
            exact = f(X, Y)
            near = np.abs(exact) < 2 * px
            em = np.abs(gm.values - exact)
            ei = np.abs(gi.values - exact)
            rows.append(
                [
                    name,
                    n,
                    f"{px:.2e}",
                    f"{em[near].max() / px:.3f}",
                    f"{em.max() / px:.3f}",
                    f"{ei[near].max() / px:.3f}",
                    f"{ei.max() / px:.3f}",
                    f"{em.max():.2e}",
                    f"{ei[near].max():.2e}",
                ]
            )
    return (
        "### Distance error against pixel size (nodes at pixel centres, exact SDF as "
        "reference)\n\n"
        "Binary: `from_mask(coverage > 0.5)`; anti-aliased: `from_image` of the 8-bit "
        "coverage (16 x 16 supersampling). Errors in pixels unless stated; 'near' is "
        "within 2 pixels of the boundary.\n\n"
        + table(
            [
                "shape",
                "pixels",
                "pixel size",
                "binary near",
                "binary all",
                "anti-aliased near",
                "anti-aliased all",
                "binary all (abs)",
                "anti-aliased near (abs)",
            ],
            rows,
        )
        + "\n\nThe binary grid's error stays below half a pixel diagonal (0.71 px): first "
        "order in the pixel size. The anti-aliased grid places straight and gently curved "
        "edges to about a tenth of a pixel near the boundary, and finds the nearest edge "
        "point farther out by vector propagation (a few tenths of a pixel at worst on the "
        "circle); at the box's corners, where the straight-edge model fails, it is no "
        "better than the binary grid.\n"
    )


def _contour_section(sizes) -> str:
    import time

    from skimage.measure import find_contours

    import fastsdf as sdf
    from fastsdf.geometry import contours

    with sdf.smoothness(0.2, kind="quadratic"):
        smooth = sdf.Circle([-0.3, 0.0], 0.5) | sdf.Circle([0.4, 0.1], 0.4)
    scenes = {
        "circle r=0.6": sdf.Circle([0.1, -0.2], 0.6),
        "box 1.2 x 0.7": sdf.Box([-0.5, -0.3], [0.7, 0.4]),
        "smooth union of 2 circles": smooth,
    }
    (x0, x1), (y0, y1) = bounds = ((-1.0, 1.0), (-1.0, 1.0))
    rows = []
    for name, f in scenes.items():
        f(np.zeros(8), np.zeros(8))  # compile outside the timings
        for n in sizes:
            xs, ys = np.linspace(x0, x1, n), np.linspace(y0, y1, n)
            t0 = time.perf_counter()
            ours = contours(f, bounds=bounds, resolution=n)
            t_ours = time.perf_counter() - t0
            t0 = time.perf_counter()
            values = f(*np.meshgrid(xs, ys, indexing="ij"))
            theirs = find_contours(values, 0.0)
            t_sk = time.perf_counter() - t0
            p = np.concatenate([c.points for c in ours])
            q = np.concatenate(theirs)
            q = np.stack(
                [x0 + q[:, 0] * (x1 - x0) / (n - 1), y0 + q[:, 1] * (y1 - y0) / (n - 1)], axis=1
            )
            e_ours = np.abs(f(p[:, 0], p[:, 1]))
            e_sk = np.abs(f(q[:, 0], q[:, 1]))
            h = (x1 - x0) / (n - 1)
            rows.append(
                [
                    name,
                    n,
                    f"{h:.2e}",
                    len(ours),
                    len(theirs),
                    f"{e_ours.max():.1e}",
                    f"{np.median(e_ours):.1e}",
                    f"{e_sk.max():.1e}",
                    f"{np.median(e_sk):.1e}",
                    f"{t_ours * 1e3:.0f} / {t_sk * 1e3:.0f}",
                ]
            )
    return (
        "### Contour vertices: distance to the true zero set, fastsdf against "
        "scikit-image's `find_contours` on the same grid\n\n"
        "`contours(f, bounds=[(-1, 1), (-1, 1)], resolution=n)` refines every crossing on the "
        "exact SDF; `find_contours` interpolates the same samples linearly. Errors are "
        "`|f(vertex)|` (the distance to the zero set, for these exact SDFs); times include "
        "sampling the grid.\n\n"
        + table(
            [
                "scene",
                "n",
                "cell",
                "loops (ours)",
                "loops (skimage)",
                "max (ours)",
                "median (ours)",
                "max (skimage)",
                "median (skimage)",
                "ms (ours / skimage)",
            ],
            rows,
        )
        + "\n\nscikit-image's vertices are exact only where the SDF is linear along the "
        "cell edge (the box's faces, hence its zero median); near the box's corners their "
        "error is first order in the cell size, on curves second order. fastsdf's stay "
        "below the root finder's tolerance, 1e-12, at every resolution; the cost is a few more "
        "evaluations per crossing (times measured on a loaded machine: indicative only).\n"
    )


_TEXT = "fastsdf geometry 2026"  # 19 glyphs


def _text_section(n: int) -> str:
    import json

    import fastsdf as sdf
    from fastsdf.geometry import Text
    from fastsdf.geometry.outline import text_segments

    from .common import run_fresh_process

    word = Text(_TEXT, size=1.0)
    rows_total = sum(len(g) for g in text_segments(_TEXT, 1.0))
    ang = np.linspace(0, 2 * np.pi, rows_total, endpoint=False)
    radius = 1.0 + 0.3 * np.cos(7 * ang)
    poly = sdf.Polygon(
        np.stack([5 + 4 * radius * np.cos(ang), 0.35 + 0.6 * radius * np.sin(ang)], 1)
    )
    rng = np.random.default_rng(0)
    x, y = rng.uniform([-0.2, -0.4], [11.0, 1.1], (n, 2)).T
    word(x[:10], y[:10])
    poly(x[:10], y[:10])
    t_word, s_word = timeit(lambda: word(x, y, compute_gradient=True), repeats=5)
    t_poly, s_poly = timeit(lambda: poly(x, y, compute_gradient=True), repeats=5)
    code = (
        "import time, json, numpy as np\n"
        "t0 = time.perf_counter()\n"
        "from fastsdf.geometry import Text\n"
        f"f = Text({_TEXT!r}, size=1.0)\n"
        "x, y = np.random.default_rng(0).uniform([-0.2, -0.4], [11.0, 1.1], "
        f"({n}, 2)).T\n"
        "f(x, y)\n"
        "print(json.dumps(time.perf_counter() - t0))\n"
    )
    cold = json.loads(run_fresh_process(code).strip().splitlines()[-1])
    warm = [json.loads(run_fresh_process(code).strip().splitlines()[-1]) for _ in range(2)]
    load = os.getloadavg()[0]
    table_rows = [
        [
            f"Text({_TEXT!r}) ({rows_total} segments, one outline)",
            f"{t_word * 1e3:.0f} ms ({s_word:.0%})",
            f"{n / t_word / 1e6:.2f} M points/s",
        ],
        [
            f"Polygon of {rows_total} vertices",
            f"{t_poly * 1e3:.0f} ms ({s_poly:.0%})",
            f"{n / t_poly / 1e6:.2f} M points/s",
        ],
    ]
    return (
        f"### Text as an exact SDF: {n:,} points, value and gradient, compiled\n\n"
        + table(["scene", "time per call", "rate"], table_rows)
        + f"\n\nText / polygon of the same segment count: {t_word / t_poly:.2f}x. "
        f"First answer in a fresh process (import, build the text, {n:,} points, value "
        f"only): {cold:.2f} s with a cold kernel cache, {min(warm):.2f} s and "
        f"{max(warm):.2f} s warm. Load average {load:.1f} (2 cores).\n"
    )


def run(quick: bool = False) -> str:
    n = 1024 if quick else 4096
    sizes = (32, 128) if quick else (32, 64, 128, 256, 512, 1024)
    cmd = "python -m bench --only geometry" + (" --quick" if quick else "")
    return (
        "## Geometry\n\n"
        + stamp(cmd)
        + "\n\n"
        + _edt_section(n)
        + "\n"
        + _error_section(sizes)
        + "\n"
        + _contour_section((33, 129) if quick else (33, 129, 513))
        + "\n"
        + _text_section(20_000 if quick else 100_000)
    )


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
