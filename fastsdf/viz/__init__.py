"""Pictures: SDF plots, particle drawing and animations, progress bars, and video frames drawn
at the speed of the physics (:mod:`fastsdf.viz.frames`: a static background once, a compiled
particle layer per frame)."""

__all__: list[str] = []
