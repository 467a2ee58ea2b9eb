"""Every Python block of README.md runs, in order, as a reader would paste them into one session.

Large sizes are written in the README as underscore literals (``1_000_000``, ``n=200_000``); the
test scales each of those down by 1000 (at least 16), so the blocks run in seconds. Blocks run in
a temporary working directory (files they write land there) with matplotlib's Agg backend.
"""

import os
import re

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(REPO, "README.md")

# A fenced block: ```python (or ```py) ... ``` at the start of lines; other languages are skipped.
_FENCE = re.compile(r"^```[ \t]*(python|py|python3)[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
# An integer literal with digit-group underscores: 1_000_000, 200_000, 4_096.
_BIG = re.compile(r"(?<![\w.])(\d{1,3}(?:_\d{3})+)(?![\w.])")


def python_blocks(text):
    """``[(line_number, source)]`` of the README's Python blocks, in order."""
    return [(text.count("\n", 0, m.start()) + 2, m.group(2)) for m in _FENCE.finditer(text)]


def scale_down(source):
    """Replace each underscore integer literal by a thousandth of it (at least 16)."""
    return _BIG.sub(lambda m: str(max(16, int(m.group(1).replace("_", "")) // 1000)), source)


def test_block_extraction_and_scaling():
    text = (
        "intro\n```python\nx = 1_000_000\n```\n\n```bash\nmake demo\n```\n"
        "```py\ny = f(n=200_000, k=3_000)  # 1_000 and 12_345.5 and a_1_000\n```\n"
    )
    blocks = python_blocks(text)
    assert [line for line, _ in blocks] == [3, 10]
    assert scale_down(blocks[0][1]) == "x = 1000\n"
    assert scale_down(blocks[1][1]) == "y = f(n=200, k=16)  # 16 and 12_345.5 and a_1_000\n"


def test_readme_has_python_blocks():
    with open(README, encoding="utf-8") as fh:
        blocks = python_blocks(fh.read())
    assert len(blocks) >= 2


@pytest.mark.slow
def test_every_readme_python_block_runs(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(README, encoding="utf-8") as fh:
        blocks = python_blocks(fh.read())
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__readme__"}
    try:
        for line, source in blocks:
            code = compile(scale_down(source), f"README.md:{line}", "exec")
            try:
                exec(code, namespace)
            except Exception as exc:  # name the block that failed
                raise AssertionError(
                    f"README.md block at line {line} failed: {type(exc).__name__}: {exc}\n{source}"
                ) from exc
    finally:
        plt.close("all")
