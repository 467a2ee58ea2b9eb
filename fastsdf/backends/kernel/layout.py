"""Constants of the SIMD block layout, shared by the generator and the run-time drivers."""

__all__ = ["BLOCK"]

#: Points per block: a multiple of every vector width, small enough that a block's scratch rows
#: stay in the L1/L2 cache.
BLOCK = 512
