"""README.md is the front door: every Python block runs pasted alone into a fresh ``python``.

Each block runs in its own fresh process (as a reader pasting it into a new session would), in a
temporary working directory (files it writes land there), with matplotlib's Agg backend. Large
sizes are written in the README as underscore literals (``1_000_000``, ``n=100_000``); the test
scales each of those down by 1000 (at least 16), so the blocks run in seconds.

"""

import os
import re
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(REPO, "README.md")
MAX_LINES = 250
MAX_PICTURE_BYTES = 200_000

# A fenced block: ```python (or ```py) ... ``` at the start of lines; other languages are skipped.
_FENCE = re.compile(r"^```[ \t]*(python|py|python3)[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
# An integer literal with digit-group underscores: 1_000_000, 200_000, 4_096.
_BIG = re.compile(r"(?<![\w.])(\d{1,3}(?:_\d{3})+)(?![\w.])")
# Modules that only an extra installs, and the extra's name.
EXTRA_OF_MODULE = {
    "h5py": "io",
    "dask": "distributed",
    "svgelements": "geometry",
    "ezdxf": "geometry",
    "imageio_ffmpeg": "video",
}
_IMPORT = re.compile(r"^\s*(?:from|import)\s+([A-Za-z_][\w]*)", re.M)
_PIP = re.compile(r"#\s*pip install\s+'fastsdf\[([\w,]+)\]'")


def python_blocks(text):
    """``[(line_number, source)]`` of the README's Python blocks, in order."""
    return [(text.count("\n", 0, m.start()) + 2, m.group(2)) for m in _FENCE.finditer(text)]


def scale_down(source):
    """Replace each underscore integer literal by a thousandth of it (at least 16)."""
    return _BIG.sub(lambda m: str(max(16, int(m.group(1).replace("_", "")) // 1000)), source)


def extras_needed(source):
    """The extras a block's imports need (sorted)."""
    mods = set(_IMPORT.findall(source))
    return sorted({EXTRA_OF_MODULE[m] for m in mods if m in EXTRA_OF_MODULE})


def extras_named(source):
    """The extras a block names in ``# pip install 'fastsdf[...]'`` comments (sorted)."""
    return sorted({e for m in _PIP.findall(source) for e in m.split(",")})


def _readme():
    with open(README, encoding="utf-8") as fh:
        return fh.read()


def test_block_extraction_scaling_and_extras():
    text = (
        "intro\n```python\nx = 1_000_000\n```\n\n```bash\nmake demo\n```\n"
        "```py\ny = f(n=200_000, k=3_000)  # 1_000 and 12_345.5 and a_1_000\n```\n"
    )
    blocks = python_blocks(text)
    assert [line for line, _ in blocks] == [3, 10]
    assert scale_down(blocks[0][1]) == "x = 1000\n"
    assert scale_down(blocks[1][1]) == "y = f(n=200, k=16)  # 16 and 12_345.5 and a_1_000\n"
    block = "# pip install 'fastsdf[io,video]'\nimport h5py\nfrom dask import array\n"
    assert extras_needed(block) == ["distributed", "io"]
    assert extras_named(block) == ["io", "video"]


def test_readme_is_a_front_door():
    text = _readme()
    assert text.count("\n") <= MAX_LINES, f"README.md has {text.count(chr(10))} lines"
    assert len(python_blocks(text)) >= 4
    # the two commands come before any example
    first_block = text.index("```python")
    assert text.index("make demo") < first_block and text.index("make test") < first_block


def test_readme_pictures_exist_and_are_small():
    pictures = re.findall(r"!\[[^\]]*\]\(([^)\s]+\.png)\)", _readme())
    assert pictures, "the README shows no picture"
    for rel in pictures:
        path = os.path.join(REPO, rel)
        assert os.path.isfile(path), f"README.md shows {rel}, which does not exist"
        size = os.path.getsize(path)
        assert size < MAX_PICTURE_BYTES, f"{rel} is {size} bytes (limit {MAX_PICTURE_BYTES})"


BLOCKS = python_blocks(_readme())
BLOCK_IDS = [f"line{line}" for line, _ in BLOCKS]


@pytest.mark.parametrize("line,source", BLOCKS, ids=BLOCK_IDS)
def test_readme_blocks_name_their_extras(line, source):
    missing = set(extras_needed(source)) - set(extras_named(source))
    assert not missing, (
        f"README.md block at line {line} imports modules of the extras {sorted(missing)} "
        f"without a comment such as # pip install 'fastsdf[{','.join(sorted(missing))}]'"
    )


# Appended to a block that makes grains (run in the same process, after it): its grains have
# landed within the block's simulated time: all at rest, each touching the world or a grain.
GRAINS_AT_REST = """
import numpy as _np
_v = _np.hypot(*sim.p["v"].T)
assert _v.max() < 1e-2, f"grains still moving at t = {sim.t}: up to {_v.max()} length/s"
_x, _r = _np.asarray(sim.p["x"]), _np.asarray(sim.p["r"])
_gap = _np.hypot(*(_x[:, None] - _x[None]).transpose(2, 0, 1)) - (_r[:, None] + _r[None])
_np.fill_diagonal(_gap, _np.inf)
_wall = _np.asarray(sim.world(_x[:, 0], _x[:, 1])).reshape(-1) - _r
_free = (_wall > 1e-3 * _r) & (_gap.min(axis=1) > 1e-3 * _r)
assert not _free.any(), f"{_free.sum()} grains touch nothing at t = {sim.t}"
"""


@pytest.mark.slow
@pytest.mark.parametrize("line,source", BLOCKS, ids=BLOCK_IDS)
def test_readme_block_runs_pasted_alone(line, source, tmp_path):
    script = tmp_path / "block.py"
    check = GRAINS_AT_REST if "contacts=" in source else ""
    script.write_text(scale_down(source) + check, encoding="utf-8")
    env = dict(os.environ, MPLBACKEND="Agg")
    # this checkout's fastsdf, as `make demo`'s editable installation provides it
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, env.get("PYTHONPATH")) if p)
    run = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, (
        f"README.md block at line {line} failed pasted alone:\n{source}\n"
        f"--- stderr ---\n{run.stderr[-4000:]}"
    )


@pytest.mark.slow
def test_readme_pictures_script_runs_at_small_size(tmp_path):
    """``examples/readme_pictures.py`` makes every picture the README shows from docs/images."""
    env = dict(os.environ, MPLBACKEND="Agg", FASTSDF_EXAMPLE_SMALL="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, env.get("PYTHONPATH")) if p)
    script = os.path.join(REPO, "examples", "readme_pictures.py")
    run = subprocess.run(
        [sys.executable, script, str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    shown = {
        os.path.basename(p)
        for p in re.findall(r"!\[[^\]]*\]\((docs/images/[^)\s]+\.png)\)", _readme())
    }
    made = {name for name in os.listdir(tmp_path) if name.endswith(".png")}
    assert shown and shown <= made, f"the README shows {sorted(shown - made)}, not made"
    for name in made:  # a picture, not an empty canvas
        from matplotlib.image import imread

        img = imread(tmp_path / name)[..., :3]
        assert img.std() > 0.05, name


@pytest.mark.slow
def test_readme_particle_block_queries_the_demos_world_and_grid():
    """After ``make demo`` the README's particle block finds its kernels cached: it builds the
    demo's world (the same generated scene module) and the demo's grid (same bounds, samples,
    mode and storage, the same node values bit for bit), so the step it compiles is the one the
    demo compiled."""
    import inspect

    import numpy as np

    from fastsdf.apps import demo
    from fastsdf.fields.grid import GridSDF

    (line, source), *_ = [b for b in BLOCKS if "ParticleSimulation(grid" in b[1]]
    # the block up to its grid (the world and the grid, not the simulation)
    upto = source[: source.index("\n", source.index("grid = "))]
    namespace: dict = {}
    exec(compile(upto, f"README.md:{line}", "exec"), namespace)
    grid = namespace["grid"]
    defaults = inspect.signature(demo.run_demo).parameters
    n, mode = defaults["grid"].default, defaults["mode"].default
    world = demo.WORLDS[defaults["world"].default][0]()
    theirs = GridSDF(world, bounds=demo.BOUNDS, samples=[n * 1j, n * 1j], mode=mode)
    assert grid.exact.compiled.module.__name__ == world.compiled.module.__name__
    assert (grid.bounds, grid.shape, grid.mode, grid.gradient, grid.dtype) == (
        theirs.bounds,
        theirs.shape,
        theirs.mode,
        theirs.gradient,
        theirs.dtype,
    )
    np.testing.assert_array_equal(grid.data, theirs.data)


def test_headline_table_names_each_worlds_exactness_as_the_code_reports():
    """The headline table's words for the SDF rows are what ``f.exactness`` says of those
    worlds (the notebook's world is a smooth union: a distance bound, not exact)."""
    from fastsdf.shapes.scenes import box_world, seed_world

    text = _readme()
    start = text.index("## Headline figures")
    table = text[start : text.index("\n## ", start + 1)]
    rows = {
        "notebook's world": seed_world().exactness,
        "20 smoothly joined boxes": box_world().exactness,
    }
    for words, exactness in rows.items():
        (row,) = [line for line in table.splitlines() if words in line]
        what = row.split("|")[1]
        assert f"'{exactness}'" in what, (words, exactness, what)
        if exactness != "exact":
            assert not re.search(r"\bexact\b", what), what
