"""Pictures: SDF plots, particle drawing and animations, progress bars, and video frames drawn
at the speed of the physics (:mod:`fastsdf.viz.frames`: a static background once, a compiled
particle layer per frame). :func:`record_video` films any simulation of the particle family
(it reads ``sim.p["x"]``, ``sim.p["r"]``, ``sim.t``, ``sim.dt`` and its world, and calls
``sim.run``)."""

from fastsdf.viz.frames import VideoWriter, record_video

__all__: list[str] = ["VideoWriter", "record_video"]
