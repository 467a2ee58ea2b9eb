"""sphinx-gallery hooks of the docs build (docs/conf.py names them): each example writes into
its own folder, and the pictures and videos it wrote are shown on its page."""

import base64
import shutil
from pathlib import Path

DOCS = Path(__file__).resolve().parent
GALLERY_OUT = DOCS / "_build" / "gallery-files"
MEDIA = (".png", ".mp4", ".gif")


def example_argv(gallery_conf: dict, script_vars: dict) -> list[str]:
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


def files_scraper(block: object, block_vars: dict, gallery_conf: dict) -> str:
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


def close_figures(gallery_conf: dict, fname: str) -> None:
    import matplotlib.pyplot as plt

    plt.close("all")
