"""Where ffmpeg comes from: the binary of the ``imageio-ffmpeg`` package, else the system's.

``pip install 'fastsdf[video]'`` installs imageio-ffmpeg, which ships an ffmpeg executable; pointing
matplotlib's ``animation.ffmpeg_path`` at it makes MP4 output work on a machine without ffmpeg.
"""

from __future__ import annotations

import shutil

__all__ = ["ffmpeg_available", "ffmpeg_exe"]


def ffmpeg_exe() -> str:
    """The ffmpeg binary: that of ``imageio-ffmpeg`` (``pip install 'fastsdf[video]'``; it
    has libx264), else the system's. Raises ``RuntimeError`` saying what to install when
    there is none."""
    try:
        import imageio_ffmpeg

        return str(imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError):  # the extra is absent, or ships no binary here
        pass
    exe = shutil.which("ffmpeg")
    if exe is None:
        raise RuntimeError(
            "writing a video needs ffmpeg: pip install 'fastsdf[video]' (it "
            "installs imageio-ffmpeg, which ships one), or install ffmpeg"
        )
    return exe


def ffmpeg_available() -> bool:
    """True if matplotlib can write MP4: a system ffmpeg, or :func:`ffmpeg_exe`'s (configured
    here as matplotlib's ``animation.ffmpeg_path``)."""
    import matplotlib
    from matplotlib import animation

    if animation.writers.is_available("ffmpeg"):
        return True
    try:
        matplotlib.rcParams["animation.ffmpeg_path"] = ffmpeg_exe()
    except RuntimeError:
        return False
    return animation.writers.is_available("ffmpeg")
