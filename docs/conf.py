"""Sphinx configuration of fastsdf's documentation (``make docs``; warnings are errors there).

Sphinx, because the API reference comes from the docstrings, which are reST/numpy style
(autodoc + napoleon read them as written); MyST, so the prose pages stay Markdown (the
existing docs/*.md are included as they are); myst-nb renders the seed notebook, executed
during the build; sphinx-gallery runs ``examples/*.py`` at small sizes and shows what each
writes (pictures, and videos with a frame as the thumbnail).
"""

import os
import re
import shutil
import sys
import warnings
from pathlib import Path

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(DOCS))
# The examples read FASTSDF_EXAMPLE_SMALL: small particle counts and few frames, so the gallery
# runs in about a minute on a 2-core machine (the test suite runs them the same way). The
# notebook runs at its own sizes (half a minute): the variable is dropped once the gallery ran.
_SET_SMALL = "FASTSDF_EXAMPLE_SMALL" not in os.environ
if _SET_SMALL:
    os.environ["FASTSDF_EXAMPLE_SMALL"] = "1"
os.environ.setdefault("MPLBACKEND", "Agg")

import fastsdf  # noqa: E402

project = "fastsdf"
author = "fastsdf contributors"
copyright = "fastsdf contributors"
release = version = fastsdf.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_nb",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
root_doc = "index"
exclude_patterns = ["_build", "api/_generated", "gallery/*.ipynb", "gallery/*.py", "**.zip"]
html_theme = "furo"
html_title = f"fastsdf {release}"
html_static_path = ["_static"]
html_css_files = ["fastsdf.css"]  # code and tables that fit the page; the index's pictures

# --- mathematics ---------------------------------------------------------------------------------
# The pages write formulas as MyST math ($...$, $$...$$: dollarmath below). MathJax 2.7 renders
# them from the site's own copy (_static/mathjax), taken from the jupyter-server-mathjax package
# of the docs extra, so the pages need no network.
try:
    import jupyter_server_mathjax
except ImportError:  # pragma: no cover - the docs extra installs it
    raise ImportError(
        "the docs need jupyter-server-mathjax (MathJax served with the site): pip install '.[docs]'"
    ) from None
MATHJAX = Path(jupyter_server_mathjax.__file__).resolve().parent / "static"
mathjax_path = "mathjax/MathJax.js?config=TeX-AMS-MML_HTMLorMML-full"  # TeX in, HTML out
mathjax2_config = {
    "tex2jax": {"inlineMath": [["\\(", "\\)"]], "displayMath": [["\\[", "\\]"]]},
    # the package ships the STIX-Web fonts only
    "HTML-CSS": {
        "availableFonts": [],
        "preferredFont": None,
        "webFont": "STIX-Web",
        "imageFont": None,
    },
    "SVG": {"font": "STIX-Web"},
    "showMathMenu": False,
}
myst_update_mathjax = False  # its settings are for MathJax 3 and up

# --- MyST and the notebook ---------------------------------------------------------------------
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
# The notebook runs during the build (outputs are not stored in the repository, so what the
# page shows is what the code does today); a cell may take a while to draw its animation.
nb_execution_mode = os.environ.get("FASTSDF_DOCS_EXECUTE", "force")
nb_execution_timeout = 900
nb_execution_raise_on_error = True
nb_execution_show_tb = True
nb_merge_streams = True

# --- API reference -------------------------------------------------------------------------------
autodoc_default_options = {"members": True, "show-inheritance": False}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_rtype = False

# --- the gallery ---------------------------------------------------------------------------------
sphinx_gallery_conf = {
    "examples_dirs": str(REPO / "examples"),
    "gallery_dirs": "gallery",
    "filename_pattern": r"\.py$",  # run every example (the default runs only plot_*.py)
    # the README's picture maker writes docs/images (committed): a tool, not a gallery entry
    "ignore_pattern": r"readme_pictures\.py$",
    # the hooks live in a module (docs/gallery_hooks.py), named by strings: Sphinx caches the
    # configuration between builds and cannot pickle functions defined here
    "reset_argv": "gallery_hooks.example_argv",
    "image_scrapers": ("gallery_hooks.files_scraper",),
    "reset_modules": ("gallery_hooks.close_figures",),
    "download_all_examples": False,
    "remove_config_comments": True,
    "min_reported_time": 1,
    "within_subsection_order": "FileNameSortKey",
}

warnings.filterwarnings("ignore", message="Matplotlib is currently using agg")


# Numpy-style docstrings here often end with a paragraph after the last parameter (how a class
# behaves as a whole). Napoleon would read it as more parameters; numpy's convention puts such
# prose under "Notes", so a "Notes" header is inserted where a field section is followed by a
# paragraph at the left margin that is not a parameter line ("name" or "name : type").
_FIELD_SECTIONS = {"Parameters", "Returns", "Yields", "Raises", "Attributes", "Other Parameters"}
_PARAM_LINE = re.compile(r"^\*{0,2}\w+(\s*,\s*\*{0,2}\w+)*(\s+:.*)?$")


def _prose_after_fields(
    app: object, what: str, name: str, obj: object, options: object, lines: list[str]
) -> None:
    out, in_fields = [], False
    for i, line in enumerate(lines):
        if i + 1 < len(lines) and lines[i + 1].strip() and set(lines[i + 1].strip()) == {"-"}:
            in_fields = line.strip() in _FIELD_SECTIONS
        elif (
            in_fields
            and line
            and not line[0].isspace()
            and i > 0
            and not lines[i - 1].strip()
            and not set(line.strip()) <= {"-"}
            and not _PARAM_LINE.match(line)
        ):
            out += ["Notes", "-----"]
            in_fields = False
        out.append(line)
    lines[:] = out


def _gallery_done(app: object) -> None:
    if _SET_SMALL:
        os.environ.pop("FASTSDF_EXAMPLE_SMALL", None)


def _copy_mathjax(app: object, exception: Exception | None) -> None:
    """Copy MathJax into the built site's _static/mathjax (what ``mathjax_path`` names)."""
    builder = app.builder  # type: ignore[attr-defined]
    if exception is None and builder.format == "html":
        target = Path(builder.outdir) / "_static" / "mathjax"
        if not (target / "MathJax.js").exists():
            shutil.copytree(MATHJAX, target, dirs_exist_ok=True)


def setup(app: object) -> None:
    # after sphinx-gallery's own builder-inited handler, which runs the examples
    app.connect("builder-inited", _gallery_done, priority=900)
    # before napoleon's own handler (priority 500)
    app.connect("autodoc-process-docstring", _prose_after_fields, priority=400)
    app.connect("build-finished", _copy_mathjax)
