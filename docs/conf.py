"""Sphinx configuration of fastsdf's documentation (``make docs``; warnings are errors there).

Sphinx, because the API reference comes from the docstrings, which are reST/numpy style
(autodoc + napoleon read them as written); MyST, so the prose pages stay Markdown (the
existing docs/*.md are included as they are); myst-nb renders the seed notebook, executed
during the build; sphinx-gallery runs ``examples/*.py`` at small sizes and shows what each
writes (pictures, and videos with a frame as the thumbnail).
"""

import base64
import os
import shutil
import sys
import warnings
from pathlib import Path

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
sys.path.insert(0, str(REPO))
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
html_static_path: list[str] = []

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
GALLERY_OUT = DOCS / "_build" / "gallery-files"
MEDIA = (".png", ".mp4", ".gif")


def example_argv(gallery_conf, script_vars):
    """Each example writes into its own folder (the two gallery scripts take a file name)."""
    name = Path(script_vars["src_file"]).stem
    out = GALLERY_OUT / name
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    if name in ("gallery", "geometry_gallery"):
        return [str(out / f"{name}.png")]
    return [str(out)]


def _video_frame(video: Path, png: Path) -> None:
    """The last frame of a video as a PNG (the entry's picture and thumbnail)."""
    import imageio_ffmpeg
    import matplotlib.image as mpimg
    import numpy as np

    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    width, height = meta["size"]
    last = None
    for frame in reader:
        last = frame
    assert last is not None, video
    mpimg.imsave(png, np.frombuffer(last, np.uint8).reshape(height, width, 3))


def files_scraper(block, block_vars, gallery_conf):
    """Shows the pictures and videos an example wrote into its folder."""
    from sphinx_gallery.scrapers import figure_rst

    name = Path(block_vars["src_file"]).stem
    out = GALLERY_OUT / name
    if not out.is_dir():
        return ""
    images, videos = [], []
    for path in sorted(out.iterdir()):
        if path.suffix not in MEDIA:
            continue
        if path.suffix == ".mp4":
            videos.append(path)
            target = next(block_vars["image_path_iterator"])
            _video_frame(path, Path(target))
            images.append(target)
        else:
            target = next(block_vars["image_path_iterator"])
            shutil.copyfile(path, target)
            images.append(target)
    rst = figure_rst(images, gallery_conf["src_dir"]) if images else ""
    for video in videos:
        data = base64.b64encode(video.read_bytes()).decode()
        rst += (
            f"\n\n.. raw:: html\n\n    <p>{video.name}:</p>\n"
            f'    <video controls loop style="max-width: 100%" '
            f'src="data:video/mp4;base64,{data}"></video>\n\n'
        )
    shutil.rmtree(out, ignore_errors=True)
    return rst


def close_figures(gallery_conf, fname):
    import matplotlib.pyplot as plt

    plt.close("all")


sphinx_gallery_conf = {
    "examples_dirs": str(REPO / "examples"),
    "gallery_dirs": "gallery",
    "filename_pattern": r"/(?!seed_notebook)\w+\.py$",
    "ignore_pattern": r"seed_notebook\.py$",
    "reset_argv": example_argv,
    "image_scrapers": (files_scraper,),
    "reset_modules": (close_figures,),
    "download_all_examples": False,
    "remove_config_comments": True,
    "min_reported_time": 1,
    "within_subsection_order": "FileNameSortKey",
}

warnings.filterwarnings("ignore", message="Matplotlib is currently using agg")


def _gallery_done(app):
    if _SET_SMALL:
        os.environ.pop("FASTSDF_EXAMPLE_SMALL", None)


def setup(app):
    # after sphinx-gallery's own builder-inited handler, which runs the examples
    app.connect("builder-inited", _gallery_done, priority=900)
