"""Pictures and videos of simulations: :mod:`fastsdf.viz.frames`, video frames drawn at the
speed of the physics (a static background once, a compiled particle layer per frame)."""

__all__: list[str] = []
