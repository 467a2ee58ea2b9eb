"""Constants of the particle step: tuning (re-exported and documented by
:mod:`fastsdf.particles`) and the freeze codes a kernel writes into ``FLAGS``."""

__all__ = [
    "TRACE_FRACTION",
    "MIN_STEP",
    "CONTACT_TOL",
    "MAX_MARCH",
    "MAX_BOUNCES",
    "FORCE_BATCH",
    "ASLEEP",
    "FLAG_INPUT",
    "FLAG_NONFINITE",
    "FLAG_COEFF",
    "FLAG_RESUME",
]

# Tuning constants (documented in fastsdf.particles, which re-exports them).
TRACE_FRACTION = 0.5
MIN_STEP = 0.02
CONTACT_TOL = 1e-3
MAX_MARCH = 64
MAX_BOUNCES = 3
#: Particles whose user forces are evaluated together ahead of their steps.
FORCE_BATCH = 32

#: ``clear[k]`` of a particle asleep for the rest of a call (its state is a fixed point).
ASLEEP = -0.5

FLAG_INPUT = 1
FLAG_NONFINITE = 2
FLAG_COEFF = 3
#: FLAGS[i] = FLAG_RESUME + step: the particle stopped before ``step`` because it came near the
#: edge of a grid whose exact fallback is not bound yet; the caller binds it and resumes.
FLAG_RESUME = 16
