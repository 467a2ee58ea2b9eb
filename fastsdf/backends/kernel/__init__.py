"""The compiled kernel: the code generator, its SIMD block layout, the scene-independent
drivers, compiled primitives, vectorisable math, and the one builder of generated modules."""

__all__: list[str] = []
