"""Sampled SDFs: the dense GridSDF and the NarrowBandGridSDF, each with its own samplers."""

__all__: list[str] = []
