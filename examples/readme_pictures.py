"""The README's pictures, each made by the README block it stands under.

    python examples/readme_pictures.py [DIR] [--small] [--only NAME ...]

Every Python block of ``README.md`` that a picture follows (``![...](docs/images/NAME.png)``)
runs as a reader runs it: pasted alone into a fresh ``python``, in an empty folder. The one PNG
it writes becomes ``DIR/NAME.png`` (``DIR`` defaults to ``docs/images``), so each picture is
exactly what its block draws; ``tests/test_readme.py`` runs the blocks again and compares what
they draw with the committed pictures. The page's top picture, ``readme_hero.png`` (a word as a
world, grains poured on it), stands under no block and is drawn here.

``--small`` (or ``FASTSDF_EXAMPLE_SMALL=1``, as for the other examples) runs the blocks with
their large sizes (the underscore literals: ``n=100_000``) divided by 1000, as the test suite
does, and the hero's pour small; the committed pictures are the full size.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import fastsdf as sdf
from fastsdf.geometry import Text
from fastsdf.particles import ContactLaw, Gravity, ParticleSimulation

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
README = os.path.join(REPO, "README.md")
OUT = os.path.join(REPO, "docs", "images")
HERO = "readme_hero.png"

# A fenced block: ```python (or ```py) ... ``` at the start of lines; other languages are skipped.
_FENCE = re.compile(r"^```[ \t]*(python|py|python3)[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
# An integer literal with digit-group underscores: 1_000_000, 200_000, 4_096.
_BIG = re.compile(r"(?<![\w.])(\d{1,3}(?:_\d{3})+)(?![\w.])")
# A picture on the first non-blank line after a block.
_PICTURE = re.compile(r"\s*!\[[^\]]*\]\(([^)\s]+\.png)\)")


def python_blocks(text: str) -> list[tuple[int, str, str | None]]:
    """``[(line_number, source, picture)]`` of the README's Python blocks, in order: the first
    line of each block's code, its code, and the path of the picture right under it (relative
    to the repository) or ``None``."""
    blocks = []
    for m in _FENCE.finditer(text):
        picture = _PICTURE.match(text, m.end())
        line = text.count("\n", 0, m.start()) + 2
        blocks.append((line, m.group(2), picture.group(1) if picture else None))
    return blocks


def scale_down(source: str) -> str:
    """Replace each underscore integer literal by a thousandth of it (at least 16)."""
    return _BIG.sub(lambda m: str(max(16, int(m.group(1).replace("_", "")) // 1000)), source)


def run_block(source: str, folder: str, timeout: float = 900) -> subprocess.CompletedProcess:
    """Run ``source`` as a reader would paste it into a fresh ``python``: a new process whose
    working folder is ``folder``, matplotlib's Agg backend, this checkout's fastsdf."""
    script = os.path.join(folder, "block.py")
    with open(script, "w", encoding="utf-8") as fh:
        fh.write(source)
    env = dict(os.environ, MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, env.get("PYTHONPATH")) if p)
    return subprocess.run(
        [sys.executable, script],
        cwd=folder,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def written_picture(folder: str) -> str:
    """The one PNG a block wrote into ``folder``; ``RuntimeError`` unless it wrote exactly one."""
    pngs = sorted(n for n in os.listdir(folder) if n.endswith(".png"))
    if len(pngs) != 1:
        raise RuntimeError(f"a block under a picture must write one PNG, it wrote {pngs}")
    return os.path.join(folder, pngs[0])


def block_pictures(out: str, small: bool, only: list[str] | None = None) -> list[str]:
    """Run every README block that a picture follows (whose picture ``only`` names, if given)
    and keep its PNG as that picture."""
    with open(README, encoding="utf-8") as fh:
        blocks = python_blocks(fh.read())
    paths = []
    for line, source, picture in blocks:
        if picture is None or (only is not None and os.path.basename(picture) not in only):
            continue
        with tempfile.TemporaryDirectory() as folder:
            run = run_block(scale_down(source) if small else source, folder)
            if run.returncode != 0:
                raise RuntimeError(f"README.md block at line {line} failed:\n{run.stderr[-3000:]}")
            target = os.path.join(out, os.path.basename(picture))
            part = target + ".part"  # the picture is replaced whole or not at all
            shutil.copyfile(written_picture(folder), part)
            os.replace(part, target)
        paths.append(target)
    return paths


def picture_hero(out: str, small: bool) -> str:
    """A word as a world (an exact SDF of its glyphs, standing on a floor), grains poured on it."""
    word = Text("fastsdf", size=1.05, position=(-1.9, -0.75))
    world = word | sdf.Halfspace([0, 1], -0.7)  # the floor's top just above the baseline
    bounds = [(-2.0, 2.0), (-1.0, 1.2)]
    # grains meet a 400 x 240 grid of the world (a bilinear query instead of 400 glyph segments)
    grid = sdf.GridSDF(world, bounds=[(-2.2, 2.2), (-1.2, 1.4)], samples=[400j, 240j])
    r = 0.03 if small else 0.016
    nx, ny = (40, 4) if small else (110, 12)
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    xy = np.column_stack([-1.9 + gx.ravel() * 3.8 / (nx - 1), 0.7 + gy.ravel() * 2.1 * r])
    xy[:, 0] += np.random.default_rng(2).uniform(-0.08, 0.08, len(xy)) * r  # (never overlapping)
    m = np.pi * r * r
    sim = ParticleSimulation(
        grid,
        positions=xy,
        radius=r,
        contacts=ContactLaw(stiffness=100 * m / (0.01 * 2 * r)),
        timestep=1 / 30,
    )
    sim.force_generators.append(Gravity())
    sim.run(40 if small else 120)
    fig, ax = plt.subplots(figsize=(6.4, 3.3), dpi=110, layout="compressed")
    # lines at distances clear of half the gaps between letters (which would ring their
    # middles), each labelled with its distance
    lines = sdf.plot_sdf(
        world,
        ax=ax,
        bounds=bounds,
        samples=(400, 220),
        show_quiver=False,
        show_isolabels=True,
        filled=True,
        colorbar=False,
        levels=[0.2, 0.4, 0.6, 0.8],
    )
    from matplotlib.collections import EllipseCollection

    speed = np.linalg.norm(sim.p["v"], axis=1)
    grains = ax.add_collection(
        EllipseCollection(
            2 * sim.p["r"],
            2 * sim.p["r"],
            0.0,
            units="xy",
            offsets=sim.p["x"],
            offset_transform=ax.transData,
            array=speed,
            cmap="YlOrBr_r",
            clim=(0.0, 1.5),
            edgecolors="#5a3a12",
            linewidths=0.3,
            zorder=5,
        )
    )
    for label in lines.get("labels", []):  # above the grains, on a patch of free space
        label.set_zorder(6)
        label.set_bbox(dict(facecolor=sdf.viz.plotting.BACKGROUND_COLOR, edgecolor="none", pad=0.5))
    fig.colorbar(grains, ax=ax, label="grain speed (length/s)", fraction=0.05, aspect=20, pad=0.02)
    ax.set_title(
        f"Text('fastsdf') as an SDF (lines: its distance), {len(xy):,} grains poured on it",
        fontsize=10,
    )
    path = os.path.join(out, HERO)
    fig.savefig(path + ".part.png")
    os.replace(path + ".part.png", path)
    plt.close(fig)
    return path


def main(out: str = OUT, small: bool = False, only: list[str] | None = None) -> list[str]:
    """Write the pictures (those named in ``only``, or every one) into ``out``; returns their
    paths."""
    os.makedirs(out, exist_ok=True)
    paths = []
    if only is None or HERO in only:
        paths.append(picture_hero(out, small))
    if only is None or set(only) - {HERO}:
        paths += block_pictures(out, small, only)
    return paths


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    parser.add_argument("out", nargs="?", default=OUT, help="output folder (default docs/images)")
    parser.add_argument("--small", action="store_true", help="small sizes (as the tests run)")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="these pictures (readme_sdf.png)")
    args = parser.parse_args()
    small = args.small or os.environ.get("FASTSDF_EXAMPLE_SMALL", "") not in ("", "0")
    for path in main(args.out, small, args.only):
        print(path)
