"""The guide's pages (docs/*.md): their Python blocks are valid Python, and the pages the site's
index names exist (the site itself is built by `make docs`, warnings as errors)."""

import ast
import os
import re

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(REPO, "docs")


def _pages():
    return sorted(n for n in os.listdir(DOCS) if n.endswith(".md"))


def test_python_blocks_parse():
    blocks = 0
    for name in _pages():
        with open(os.path.join(DOCS, name), encoding="utf-8") as fh:
            text = fh.read()
        for i, code in enumerate(re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)):
            try:
                ast.parse(code)
            except SyntaxError as exc:  # pragma: no cover - the message names the block
                raise AssertionError(f"{name}, python block {i + 1}: {exc}") from exc
            blocks += 1
    assert blocks >= 10


def test_index_names_existing_pages():
    with open(os.path.join(DOCS, "index.md"), encoding="utf-8") as fh:
        index = fh.read()
    entries = re.findall(r"^([\w/-]+)$", index, re.M)
    assert len(entries) >= 15
    for entry in entries:
        found = [
            os.path.exists(os.path.join(DOCS, entry + ext)) for ext in (".md", ".rst", ".ipynb")
        ]
        generated = entry == "gallery/index"  # sphinx-gallery writes it from examples/
        assert any(found) or generated, entry
