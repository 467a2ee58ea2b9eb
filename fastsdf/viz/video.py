"""Where ffmpeg comes from: the system's, else the binary of the ``imageio-ffmpeg`` package.

``pip install 'fastsdf[video]'`` installs imageio-ffmpeg, which ships an ffmpeg executable; pointing
matplotlib's ``animation.ffmpeg_path`` at it makes MP4 output work on a machine without ffmpeg.
"""

from __future__ import annotations

import shutil

__all__ = ["ffmpeg_available"]


def ffmpeg_available() -> bool:
    """True if matplotlib can write MP4: a system ffmpeg, or imageio-ffmpeg's (configured here)."""
    import matplotlib
    from matplotlib import animation

    if animation.writers.is_available("ffmpeg"):
        return True
    exe = shutil.which("ffmpeg")
    if exe is None:
        try:
            import imageio_ffmpeg

            exe = imageio_ffmpeg.get_ffmpeg_exe()
        except (ImportError, RuntimeError):  # the extra is absent, or ships no binary here
            return False
    matplotlib.rcParams["animation.ffmpeg_path"] = exe
    return animation.writers.is_available("ffmpeg")
