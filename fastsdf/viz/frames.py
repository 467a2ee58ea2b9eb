"""Video frames at the speed of the physics: a static background and a compiled particle layer.

Matplotlib is the right tool for a still picture, and too slow to redraw a whole figure per
frame of a video of millions of particles. :class:`VideoWriter` draws everything
that does not change (the world, the axes, their labels, the title, the colour bar) once with
Matplotlib into an RGB background; each frame then only

1. splats the particles into an integer image covering the axes (a numba kernel): counts of
   particle centres per pixel (``mode='density'``) or discs of the particles' own radii
   (``mode='discs'``);
2. composites that image over a copy of the background through a colour table (the colour
   map evaluated once per count, so the colours are exactly those of the colour bar);
3. writes the simulated time from a small glyph atlas (rendered once by Matplotlib, in a
   monospaced font so the line never jitters);
4. pipes the raw RGB bytes to ffmpeg, which encodes in its own process.

The colour scale is fixed for the whole video: given (``vmax``), or taken from the first
``scale_frames`` frames (buffered until then); counts above it take the top colour and the colour
bar shows an arrow for them. The axes never move: the background is drawn once.

The file appears complete or not at all: ffmpeg writes a hidden temporary file beside ``path``,
renamed over ``path`` only after ffmpeg finished without error.

Pixel convention: the particle image covers ``bounds`` exactly; pixel ``(i, j)`` of it (row 0 at
the top) holds the points with ``x0 + j/sx <= x < x0 + (j+1)/sx`` and
``y1 - (i+1)/sy < y <= y1 - i/sy`` (``sx``, ``sy``: pixels per data unit). Points outside, or
with a non-finite coordinate, are dropped.
"""

from __future__ import annotations

import math
import os
import subprocess
import tempfile
from typing import Any

import numpy as np
from numba import njit

from fastsdf.expr.validate import check_bounds, count, positive, reals, shown, vec2
from fastsdf.files import commit, temporary_sibling
from fastsdf.viz.video import ffmpeg_exe

__all__ = [
    "VideoWriter",
    "record_video",
    "splat_counts",
    "splat_discs",
    "composite",
    "ffmpeg_exe",
    "color_table",
    "DEFAULT_SIZE",
    "MODES",
]

#: Frame size ``(width, height)`` in pixels by default (720p).
DEFAULT_SIZE = (1280, 720)
#: Values of ``mode``: ``'auto'`` picks discs up to ``max_discs`` particles, density above.
MODES = ("auto", "density", "discs")
_TIME_CHARS = "0123456789.-+e tsp=()inaf"


# ---------------------------------------------------------------------------------------------
# Kernels (plain @njit functions; the NumPy references are in the tests).


@njit(cache=True, nogil=True)
def splat_counts(
    xs: np.ndarray, ys: np.ndarray, x0: float, y1: float, sx: float, sy: float, counts: np.ndarray
) -> None:
    """Add one to ``counts[i, j]`` for each point ``(xs[p], ys[p])`` in pixel ``(i, j)``.

    ``counts`` is an ``(H, W)`` integer image whose row 0 is at the top: pixel ``(i, j)`` covers
    ``j <= (x - x0) * sx < j + 1`` and ``i <= (y1 - y) * sy < i + 1``. Points outside and
    non-finite points (the comparisons fail for NaN) are dropped. A count saturates at the
    largest value of the image's dtype (a uint16 image, small enough to stay in cache, holds
    up to 65535 per pixel).
    """
    h, w = counts.shape
    top = np.iinfo(counts.dtype).max
    for p in range(xs.shape[0]):
        fx = (xs[p] - x0) * sx
        fy = (y1 - ys[p]) * sy
        if fx >= 0.0 and fx < w and fy >= 0.0 and fy < h:
            i = int(fy)
            j = int(fx)
            if counts[i, j] < top:
                counts[i, j] += 1


@njit(cache=True, nogil=True)
def splat_discs(
    xs: np.ndarray,
    ys: np.ndarray,
    rs: np.ndarray,
    x0: float,
    y1: float,
    sx: float,
    sy: float,
    counts: np.ndarray,
) -> None:
    """Mark (set to 1) the pixels of ``counts`` covered by the discs ``(xs, ys, rs)``.

    A pixel is covered when its centre lies in the disc (in data units, so a disc stays round
    when ``sx == sy``); the pixel holding a disc's centre is always marked, so discs smaller than
    a pixel remain visible. Same pixel convention as :func:`splat_counts`; a disc with a
    non-finite centre or radius is dropped, a negative radius counts as 0. ``rs`` may hold one
    radius for all (length 1) or one per disc.
    """
    h, w = counts.shape
    one_r = rs.shape[0] == 1
    for p in range(xs.shape[0]):
        cx = (xs[p] - x0) * sx
        cy = (y1 - ys[p]) * sy
        r = rs[0] if one_r else rs[p]
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)):
            continue
        if r < 0.0:
            r = 0.0
        if cx >= 0.0 and cx < w and cy >= 0.0 and cy < h:
            counts[int(cy), int(cx)] = 1
        rx = r * sx
        ry = r * sy
        if rx <= 0.0 or ry <= 0.0:
            continue
        j0 = max(0, int(math.floor(cx - rx)))
        j1 = min(w - 1, int(math.floor(cx + rx)))
        i0 = max(0, int(math.floor(cy - ry)))
        i1 = min(h - 1, int(math.floor(cy + ry)))
        for i in range(i0, i1 + 1):
            dy = (i + 0.5 - cy) / ry
            dy2 = dy * dy
            if dy2 > 1.0:
                continue
            for j in range(j0, j1 + 1):
                dx = (j + 0.5 - cx) / rx
                if dx * dx + dy2 <= 1.0:
                    counts[i, j] = 1


@njit(cache=True, nogil=True)
def composite(
    counts: np.ndarray, table: np.ndarray, keep: int, frame: np.ndarray, row0: int, col0: int
) -> None:
    """Blend the colours of ``counts`` into ``frame[row0:, col0:]`` (an RGB uint8 image).

    A pixel with count ``c > 0`` becomes ``(frame * keep + table[min(c, len(table) - 1)]) >> 8``
    per channel: ``table`` holds the colours premultiplied by ``256 - keep`` (the layer's
    opacity times 256), see :func:`color_table`. Pixels with count 0 are left as they are.
    """
    h, w = counts.shape
    top = table.shape[0] - 1
    for i in range(h):
        for j in range(w):
            c = counts[i, j]
            if c > 0:
                k = c if c < top else top
                for ch in range(3):
                    v = np.int32(frame[row0 + i, col0 + j, ch]) * keep + table[k, ch]
                    frame[row0 + i, col0 + j, ch] = v >> 8


def color_table(colors: np.ndarray, alpha: float) -> tuple:
    """``(table, keep)`` for :func:`composite`: ``colors`` ``(k, 3)`` in [0, 1] drawn at opacity
    ``alpha`` over the background: ``table = round(256 alpha) * 255 colors`` (int32) and
    ``keep = 256 - round(256 alpha)``."""
    a = int(round(256 * float(alpha)))
    table = np.rint(np.asarray(colors, dtype=np.float64)[:, :3] * 255.0).astype(np.int32) * a
    return np.ascontiguousarray(table), 256 - a


def time_label(t: float | None, step: int | None) -> str:
    """The frame's clock line, ``'t = 1.23 s (step 37)'`` (parts that are ``None`` left out)."""
    parts = []
    if t is not None:
        parts.append(f"t = {float(t):.2f} s")
    if step is not None:
        parts.append(f"(step {int(step)})" if parts else f"step {int(step)}")
    return " ".join(parts)


# ---------------------------------------------------------------------------------------------
# The glyph atlas.


class _GlyphAtlas:
    """Coverage masks of a few characters in a monospaced font, rendered once by Matplotlib
    (every glyph in a cell of the same width, so strings are laid out by index)."""

    def __init__(self, chars: str, fontsize: float, dpi: float) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        px = fontsize * dpi / 72.0
        self.cell_w = int(math.ceil(0.62 * px))
        self.cell_h = int(math.ceil(1.4 * px))
        fig = Figure(figsize=(self.cell_w * len(chars) / dpi, self.cell_h / dpi), dpi=dpi)
        canvas = FigureCanvasAgg(fig)
        baseline = 0.3  # fraction of the cell below the baseline (descenders)
        for k, ch in enumerate(chars):
            fig.text(
                k / len(chars),
                baseline,
                ch,
                family="DejaVu Sans Mono",
                fontsize=fontsize,
                color="black",
                ha="left",
                va="baseline",
            )
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        ink = 255 - rgba[..., :3].min(axis=2)  # black on white: coverage
        self.glyphs = {
            ch: np.ascontiguousarray(ink[:, k * self.cell_w : (k + 1) * self.cell_w])
            for k, ch in enumerate(chars)
        }
        self.height = ink.shape[0]

    def draw(self, frame: np.ndarray, text: str, right: int, top: int) -> None:
        """Write ``text`` in black into ``frame``, right-aligned at column ``right``."""
        x = right - self.cell_w * len(text)
        for ch in text:
            g = self.glyphs.get(ch)
            if g is not None and ch != " ":
                h, w = g.shape
                r0, c0 = max(0, top), max(0, x)
                r1, c1 = min(frame.shape[0], top + h), min(frame.shape[1], x + w)
                if r1 > r0 and c1 > c0:
                    a = g[r0 - top : r1 - top, c0 - x : c1 - x, None].astype(np.uint16)
                    region = frame[r0:r1, c0:c1]
                    region[...] = (region * (255 - a) // 255).astype(np.uint8)
            x += self.cell_w


# ---------------------------------------------------------------------------------------------
# The writer.


class VideoWriter:
    """Write particle frames over a static picture of the world to a video file (MP4 etc.).

    ``VideoWriter(path, world, bounds)`` used as a context manager; call :meth:`add` (positions)
    or :meth:`add_simulation` (a :class:`fastsdf.particles.ParticleSimulation`'s current state
    and clock) once per frame. The file at ``path`` is written when the writer closes, complete,
    or not at all (an error while writing leaves any older file at ``path`` untouched).

    ``world``: the SDF drawn as the static background (filled solid and free space and the zero
    contour, as :func:`fastsdf.viz.render.render_frame`; ``None``: an empty axes over ``bounds``).
    A world that moves (built with ``sdf.t``: ``world.time_dependent``) is drawn at each frame's
    time instead: its solid pixels are filled anew per frame (the world evaluated at the pixel
    centres, in compiled code), so each frame then needs its time ``t``.
    ``bounds``: ``[(x0, x1), (y0, y1)]`` shown (data units). ``size``: ``(width, height)``
    pixels, both even (the H.264 colour format needs it). ``fps``: frames per second.
    ``mode``: ``'density'`` (particle centres per pixel through a logarithmic colour map, with a
    colour bar), ``'discs'`` (every particle a disc of its radius), or ``'auto'``: discs for up
    to ``max_discs`` particles, density above; chosen at the first frame for the whole video.
    ``vmax``: top of the density colour scale (particles per pixel, > 1); ``None`` takes the
    largest count of the first ``scale_frames`` frames. ``title``: a static line above the axes;
    the simulated time (``t``/``step`` given to :meth:`add`) is written at its right.
    ``samples``: grid samples per axis of the world's picture. ``crf``, ``preset``: libx264's
    quality (lower is better) and speed settings. ``alpha``: opacity of the particle layer.
    ``dpi``: the figure's dots per inch (the picture's fonts scale with it).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        world: Any = None,
        bounds: Any = ((-2.0, 2.0), (-2.0, 2.0)),
        size: tuple = DEFAULT_SIZE,
        fps: float = 30,
        mode: str = "auto",
        max_discs: int | None = None,
        vmax: float | None = None,
        scale_frames: int = 1,
        title: str | None = None,
        samples: int = 400,
        crf: int = 20,
        preset: str = "veryfast",
        alpha: float = 0.8,
        dpi: float = 100,
    ) -> None:
        from fastsdf.viz.render import DEFAULT_MAX_CIRCLES

        self.path = os.path.abspath(os.fspath(path))
        self.bounds = check_bounds(bounds)
        width, height = (int(v) for v in vec2(size, "size"))
        if width < 64 or height < 64 or width % 2 or height % 2 or (width, height) != tuple(size):
            raise ValueError(
                f"size must be (width, height), both even and >= 64, got size={shown(size)}"
            )
        self.size = (width, height)
        self.fps = positive(fps, "fps")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got mode={shown(mode)}")
        self.mode = mode
        self.max_discs = (
            DEFAULT_MAX_CIRCLES if max_discs is None else count(max_discs, "max_discs", 0)
        )
        if vmax is not None:
            v = positive(vmax, "vmax")
            if v <= 1.0 or v > 1e8:
                raise ValueError(
                    f"vmax must be in (1, 1e8] particles per pixel, got vmax={shown(vmax)}"
                )
            vmax = v
        self.vmax = vmax
        #: The density colour scale, :func:`fastsdf.viz.render.density_norm` of ``vmax``, once the
        #: background is drawn (``None`` before, and for discs).
        self.norm: Any = None
        self.scale_frames = count(scale_frames, "scale_frames")
        self.title = title
        self.world = world
        #: The world moves: its solid is drawn per frame at the frame's time.
        self.moving = bool(getattr(world, "time_dependent", False))
        self.samples = count(samples, "samples", 2)
        self.crf = count(crf, "crf", 0)
        self.preset = str(preset)
        if not 0.0 < float(alpha) <= 1.0:
            raise ValueError(f"alpha must be in (0, 1], got alpha={shown(alpha)}")
        self.alpha = float(alpha)
        self.dpi = positive(dpi, "dpi")
        ext = os.path.splitext(self.path)[1].lower()
        if ext not in (".mp4", ".m4v", ".mov", ".mkv"):
            raise ValueError(f"path must end in .mp4, .m4v, .mov or .mkv, got path={shown(path)}")
        self._exe = ffmpeg_exe()
        self.frames_written = 0
        self._proc: subprocess.Popen | None = None
        self._tmp: str | None = None
        self._log: Any = None
        self._background: Any = None
        self._counts: Any = None
        self._pending: list = []  # (counts, label, walls) held until the colour scale is known
        # Two frame buffers: one is composed while ffmpeg reads the other (a writer thread).
        self._frames = [np.empty((height, width, 3), dtype=np.uint8) for _ in range(2)]
        self._frame = self._frames[0]
        self._pool: Any = None
        self._pending_write: Any = None
        self._closed = False

    # -- the static picture ----------------------------------------------------------------
    def _layout(self, n: int) -> None:
        """Choose the mode, lay out the figure (world, axes, title) and fix the pixel mapping;
        the colour bar and the drawing wait for the colour scale (:meth:`_paint`)."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        from fastsdf.viz.render import world_figure

        width, height = self.size
        if self.mode == "auto":
            self.mode = "discs" if n <= self.max_discs else "density"
        figsize = (width / self.dpi, height / self.dpi)
        world = self.world
        if world is None or self.moving:  # free space (a moving world is drawn per frame)
            world = lambda x, y: np.ones_like(x)
        fig, ax, cax = world_figure(world, self.bounds, self.samples, figsize, self.dpi)
        FigureCanvasAgg(fig)
        # world_figure packs the axes and the colour bar to the left; centre them in a wide
        # frame (the 0.85 inch right of the bar hold its ticks and label).
        used = cax.get_position().x1 + 0.85 / figsize[0]
        shift = max(0.0, (1.0 - used) / 2.0)
        for a in (ax, cax):
            box = a.get_position()
            a.set_position((box.x0 + shift, box.y0, box.width, box.height))
        if self.title:
            ax.set_title(self.title, loc="left")
        ax.apply_aspect()
        self._fig, self._ax, self._cax = fig, ax, cax
        (x0, x1), (y0, y1) = self.bounds
        (dx0, dy0), (dx1, dy1) = ax.transData.transform([(x0, y0), (x1, y1)])
        col0, col1 = int(round(dx0)), int(round(dx1))
        row0, row1 = height - int(round(dy1)), height - int(round(dy0))
        self._row0, self._col0 = row0, col0
        self._counts = np.zeros((row1 - row0, col1 - col0), dtype=np.uint16)
        self._sx = (col1 - col0) / (x1 - x0)
        self._sy = (row1 - row0) / (y1 - y0)
        # The clock line: right-aligned above the axes' top right corner.
        self._atlas = _GlyphAtlas(_TIME_CHARS, 10.0, self.dpi)
        self._text_right = col1
        self._text_top = max(0, row0 - self._atlas.height - 2)
        if self.moving:
            from matplotlib.colors import to_rgb

            from fastsdf.viz.plotting import SOLID_COLOR

            # pixel centres of the particle image, where the moving world is evaluated
            self._px = np.ascontiguousarray(
                np.broadcast_to(x0 + (np.arange(col1 - col0) + 0.5) / self._sx, self._counts.shape)
            )
            self._py = np.ascontiguousarray(
                np.broadcast_to(
                    (y1 - (np.arange(row1 - row0) + 0.5) / self._sy)[:, None], self._counts.shape
                )
            )
            self._solid = (np.array(to_rgb(SOLID_COLOR)) * 255.0 + 0.5).astype(np.uint8)

    def _paint(self) -> None:
        """Draw the static picture once (with the colour bar of the now fixed scale)."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        from fastsdf.viz.render import PARTICLE_COLOR, _particle_cmap, plain_log_ticks

        width, height = self.size
        fig, cax = self._fig, self._cax
        cmap = _particle_cmap()
        if self.mode == "density":
            from matplotlib.cm import ScalarMappable

            from fastsdf.viz.render import density_norm

            assert self.vmax is not None
            norm = self.norm = density_norm(self.vmax)
            cax.set_visible(True)
            bar = fig.colorbar(
                ScalarMappable(norm=norm, cmap=cmap),
                cax=cax,
                extend="max",
                label="particles per pixel",
                alpha=self.alpha,
            )
            plain_log_ticks(bar)
            top = int(math.ceil(self.vmax))
            colors = cmap(norm(np.arange(top + 1, dtype=np.float64).clip(1.0, None)))
        else:
            from matplotlib.colors import to_rgb

            colors = np.array([to_rgb(PARTICLE_COLOR)] * 2)
        self._table, self._keep = color_table(colors, self.alpha)
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        if rgba.shape[:2] != (height, width):
            raise RuntimeError(
                f"the background came out {rgba.shape[1]}x{rgba.shape[0]} "
                f"pixels, not {width}x{height} (dpi={self.dpi})"
            )
        self._background = np.ascontiguousarray(rgba[..., :3])
        self._fig = self._ax = self._cax = None  # the figure is not needed any more

    def _start(self) -> None:
        width, height = self.size
        self._tmp = temporary_sibling(self.path)
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 (closed in close())
        cmd = [
            self._exe,
            "-y",
            "-loglevel",
            "error",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-s",
            f"{width}x{height}",
            "-r",
            f"{self.fps:g}",
            "-i",
            "-",
            "-an",
            "-c:v",
            "libx264",
            "-preset",
            self.preset,
            "-crf",
            str(self.crf),
            "-pix_fmt",
            "yuv420p",
            "-movflags",
            "+faststart",
            self._tmp,
        ]
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._log
        )

    # -- frames ----------------------------------------------------------------------------
    def render(
        self, x: Any, y: Any, r: Any = None, t: float | None = None, step: int | None = None
    ) -> np.ndarray:
        """The frame for particles at ``(x, y)`` (radii ``r``, data units, scalar or one per
        particle; needed for discs) at simulated time ``t`` / ``step``, as an ``(H, W, 3)``
        uint8 array (a buffer reused by the next call: copy it to keep it). Nothing is
        written; the colour scale must be known (``vmax`` given, or after the first frames)."""
        counts = self._splat(x, y, r)
        if self.mode == "density" and self.vmax is None:
            raise RuntimeError("the colour scale is not fixed yet: give vmax, or add frames")
        return self._compose(counts, time_label(t, step), self._walls(t))

    def pixel(self, x: float, y: float) -> tuple:
        """``(row, column)`` of the frame pixel holding the data point ``(x, y)`` (row 0 at the
        top), once the first frame fixed the layout."""
        if self._counts is None:
            raise RuntimeError("the layout is fixed by the first frame: add or render one first")
        (x0, _), (_, y1) = self.bounds
        return (
            self._row0 + int(math.floor((y1 - y) * self._sy)),
            self._col0 + int(math.floor((x - x0) * self._sx)),
        )

    def _splat(self, x: Any, y: Any, r: Any) -> np.ndarray:
        xs, ys = reals(x, "x"), reals(y, "y")
        if xs.shape != ys.shape:
            raise ValueError(
                f"x and y must have the same number of points, got {xs.size} and {ys.size}"
            )
        if self._counts is None:
            self._layout(xs.size)
        if self._background is None and (self.mode == "discs" or self.vmax is not None):
            self._paint()
        (x0, _), (_, y1) = self.bounds
        counts = self._counts
        counts.fill(0)
        if self.mode == "density":
            splat_counts(xs, ys, x0, y1, self._sx, self._sy, counts)
        else:
            if r is None:
                if xs.size == 0:
                    return counts
                raise ValueError("r (the particles' radii) is needed to draw discs")
            rs = reals(r, "r")
            if rs.size not in (1, xs.size):
                raise ValueError(
                    f"r must be a scalar or one radius per particle ({xs.size}), "
                    f"got {rs.size} radii"
                )
            splat_discs(xs, ys, rs, x0, y1, self._sx, self._sy, counts)
        return counts

    def _walls(self, t: float | None) -> Any:
        """The solid pixels of a moving world at time ``t`` (None for a static world)."""
        if not self.moving:
            return None
        if t is None:
            raise ValueError("a moving world (world.time_dependent) needs each frame's time t")
        return self.world(self._px, self._py, t=float(t)) < 0.0

    def _compose(self, counts: np.ndarray, label: str, walls: Any = None) -> np.ndarray:
        frame = self._frame
        np.copyto(frame, self._background)
        if walls is not None:
            h, w = walls.shape
            frame[self._row0 : self._row0 + h, self._col0 : self._col0 + w][walls] = self._solid
        composite(counts, self._table, self._keep, frame, self._row0, self._col0)
        if label:
            self._atlas.draw(frame, label, self._text_right, self._text_top)
        return frame

    def add(
        self, x: Any, y: Any, r: Any = None, t: float | None = None, step: int | None = None
    ) -> None:
        """Append the frame of particles at ``(x, y)``, radii ``r``, simulated time ``t`` and
        ``step`` (see :meth:`render`)."""
        if self._closed:
            raise RuntimeError("this VideoWriter is closed")
        counts = self._splat(x, y, r)
        label = time_label(t, step)
        walls = self._walls(t)
        if self.mode == "density" and self.vmax is None:
            self._pending.append((counts.copy(), label, walls))
            if len(self._pending) < self.scale_frames:
                return
            self._fix_scale()
            return
        self._write(self._compose(counts, label, walls))

    def add_simulation(self, sim: Any) -> None:
        """Append the frame of ``sim``'s current particles (``sim.p['x']``, ``sim.p['r']``) at
        its clock ``sim.t`` (and step ``round(t / dt)``)."""
        x = np.asarray(sim.p["x"])
        t = float(sim.t)
        dt = float(getattr(sim, "dt", 0.0) or 0.0)
        self.add(x[:, 0], x[:, 1], sim.p["r"], t=t, step=int(round(t / dt)) if dt > 0 else None)

    def _fix_scale(self) -> None:
        top = max(int(c.max()) for c, _, _ in self._pending)
        self.vmax = float(max(top, 2))
        self._paint()
        for counts, label, walls in self._pending:
            self._write(self._compose(counts, label, walls))
        self._pending = []

    def _write(self, frame: np.ndarray) -> None:
        """Hand ``frame`` (one of the two buffers) to the writer thread and compose the next
        frame into the other buffer meanwhile."""
        if self._proc is None:
            from concurrent.futures import ThreadPoolExecutor

            self._start()
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="fastsdf-video")
        assert self._proc is not None and self._proc.stdin is not None
        self._wait_write()
        self._pending_write = self._pool.submit(self._proc.stdin.write, frame.reshape(-1).data)
        self._frame = self._frames[1] if frame is self._frames[0] else self._frames[0]
        self.frames_written += 1

    def _wait_write(self) -> None:
        job, self._pending_write = self._pending_write, None
        if job is None:
            return
        try:
            job.result()
        except (BrokenPipeError, OSError):
            self._abort()
            raise RuntimeError(
                f"ffmpeg stopped while writing {self.path}: {self._ffmpeg_log()}"
            ) from None

    # -- closing ---------------------------------------------------------------------------
    def _ffmpeg_log(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        return self._log.read().decode(errors="replace").strip()[-2000:]

    def _abort(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        self._pending_write = None
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait()
            self._proc = None
        if self._tmp is not None and os.path.exists(self._tmp):
            os.remove(self._tmp)
        self._tmp = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def close(self) -> str:
        """Finish the video: encode any frames still held, wait for ffmpeg, move the file into
        place. Returns the path written. Raises ``RuntimeError`` if no frame was added or
        ffmpeg failed (no file is left behind then)."""
        if self._closed:
            return self.path
        try:
            if self._pending:
                self._fix_scale()
            if self.frames_written == 0:
                raise RuntimeError(f"no frames were added; {self.path} was not written")
            assert self._proc is not None and self._proc.stdin is not None
            self._wait_write()
            self._pool.shutdown()
            self._pool = None
            self._proc.stdin.close()
            code = self._proc.wait()
            if code != 0:
                raise RuntimeError(
                    f"ffmpeg failed (exit {code}) writing {self.path}: {self._ffmpeg_log()}"
                )
            assert self._tmp is not None
            commit(self._tmp, self.path)
            self._tmp = None
            self._proc = None
        except BaseException:
            self._abort()
            raise
        finally:
            self._closed = True
            if self._log is not None:
                self._log.close()
                self._log = None
        return self.path

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, kind: Any, value: Any, tb: Any) -> None:
        if kind is None:
            self.close()
        else:  # an error inside the block: leave no partial file
            self._closed = True
            self._abort()

    def __del__(self) -> None:
        if getattr(self, "_proc", None) is not None:
            self._abort()


def record_video(
    sim: Any,
    path: str | os.PathLike,
    frames: int,
    steps_per_frame: int = 1,
    world: Any = None,
    advance: Any = None,
    **writer_options: Any,
) -> str:
    """Run ``sim`` and write a video of it: frame 0 is its current state, each later frame
    follows ``steps_per_frame`` more steps (``sim.run``, or ``advance(k)`` if given).

    ``frames``: how many (>= 1). ``world``: the picture's SDF (default ``sim.sdf``).
    ``writer_options`` go to
    :class:`VideoWriter` (``bounds``, ``size``, ``fps``, ``mode``, ``vmax``, ``title``, ...).
    Returns the path written.
    """
    frames = count(frames, "frames")
    steps_per_frame = count(steps_per_frame, "steps_per_frame", 0)
    run = advance if advance is not None else sim.run
    with VideoWriter(path, sim.sdf if world is None else world, **writer_options) as writer:
        for i in range(frames):
            if i > 0 and steps_per_frame:
                run(steps_per_frame)
            writer.add_simulation(sim)
    return writer.path
