"""Pictures: SDF plots, particle drawing and animations, video, progress bars."""

__all__: list[str] = []
