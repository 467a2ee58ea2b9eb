"""Particles colliding with signed distance functions: the notebook's ``phys`` module, compiled.

``import fastsdf.particles as phys`` gives the notebook's interface::

    sim = phys.ParticleSimulation(f, n=100, timestep=1/30, seed=0)
    sim.force_generators += [phys.Gravity()]          # fused into the compiled step
    anim = phys.create_animation(fig, ax, sim, frames=300, repeat=True, use_wall_time=False)
    sim.run(1000)                                     # 1000 steps in compiled code

Units and conventions. Lengths are in the SDF's coordinate units, time in seconds, mass in any
consistent unit; velocities are length/s, accelerations length/s**2, forces mass*length/s**2.
The SDF is negative inside solid matter and positive in free space; a particle is a disc of
radius ``r`` around ``x`` and is in contact where ``d(x) - r <= 0``. Particles do not interact
with each other and do not rotate.

One step (``timestep`` seconds), for every particle, in one fused compiled loop:

1. forces: fused :class:`Gravity` (``m * acceleration``), :class:`Drag` (``-c v``) and user
   forces written as numba functions ``@njit def f(x, y, vx, vy, m, t) -> (fx, fy)`` (in
   mass * length / s**2, at the particle's state before the step and the step's start time
   ``t``), compiled into the step; plus the sum of any Python force generators
   ``(p, t) -> (n, 2)`` (evaluated with NumPy before each compiled step: the slow path);
2. integration: semi-implicit (symplectic) Euler ``v += f/m dt; x += v dt`` (the default), or
   the notebook's explicit Euler ``x += v dt; v += f/m dt`` (``integrator='euler'``);
3. tunnelling check (``prevent_tunnelling=True``, the default): a particle moving farther than
   ``TRACE_FRACTION * r`` in the step, whose end point is not clear of every surface by the
   step's length, is swept along its displacement by conservative advancement (sphere tracing
   with the SDF's Lipschitz bound ``lipschitz``: 1 for SDFs, sqrt(2) for bilinear grids); at a
   contact the remaining displacement and the velocity are reflected with the response below,
   so it cannot pass through a thin wall. (A step shorter than half the radius cannot carry a
   disc that penetrates by less than half its radius across the middle of a wall, which is why
   short steps need no sweep);
4. collision response at the end point (House & Keyser): with ``s = d - r <= 0`` and
   ``n = grad d / |grad d|``: ``x -= (1 + cr) s n``; ``v = -cr v_n + (1 - cf) v_t``. By default
   the velocity responds only when ``v . n < 0`` (approaching; ``collision='approaching'``):
   a particle already separating is only pushed out, never turned back into the wall.
   ``collision='notebook'`` responds to the velocity whenever ``s <= 0``, as the notebook did.

``integrator='euler', collision='notebook', prevent_tunnelling=False`` reproduces the notebook's
``advance()`` (to rounding; :func:`reference_step` is that step in NumPy).

Why semi-implicit Euler is the default: it is symplectic, so its energy error stays bounded (of
the order of the work gravity does in one step) instead of accumulating, and a particle resting
on a floor stays within ``cr * g * dt**2`` of it. Explicit Euler moves a particle with the
previous step's velocity and gains energy at every bounce: at ``dt = 1/30`` a ball with
``cr = 0.8`` rebounds to 0.69-0.78 of its height instead of 0.64, and a "resting" particle with
``cr`` near 1 climbs without bound. Both cost the same.

Speed. The step skips the SDF query of a particle whose last query proved it clear of every
surface by more than it has moved since (a budget of ``(d - r) / lipschitz``, kept per
particle during one :meth:`ParticleSimulation.run` call); a skipped query is one that would have
found no contact, so the results are the same bits whatever the grouping of steps into calls.
:meth:`ParticleSimulation.run` runs all its steps on a block of :data:`DEFAULT_BLOCK` particles
while the block is in cache, so main memory is crossed about once per call, not once per step.

Memory: the state is structure-of-arrays (``x``, ``v``: (n, 2); ``m``, ``r``, ``cr``, ``cf``:
(n,)), 64 bytes per particle in float64 and 32 in float32 (``dtype=np.float32``; the arithmetic
is float64 either way). A step must read ``x``, ``v``, ``r`` and write ``x``, ``v``: 72 bytes
per particle in float64 (80 with drag, which reads ``m``), 36 in float32; ``cr`` and ``cf`` are
read only for particles in contact. The state is checked on the values a step loads anyway
(see :meth:`ParticleSimulation.run`); ``m``, ``cr``, ``cf`` are re-read in full only at the
first call after they were handed out through ``p`` (24 bytes per particle, once). The 8-byte
free-flight budget lives in a scratch array of one block.

The step kernels are the package :mod:`fastsdf.particles.kernels` (readable, tested directly);
each world gets a module of them with its query and fused forces in place
(:mod:`fastsdf.particles.world`), cached on disk by content hash. A grid world
with stored gradients and float64 state steps blocks of particles in vector passes (see
"Kernels" in :class:`ParticleSimulation`). A grid world's
kernel does not depend on the scene (its exact fallback is bound at run time), so it compiles
once per installation.

Grains: ``ParticleSimulation(world, positions=..., radius=..., contacts=ContactLaw())`` gives
particles that also collide with each other (a :class:`GrainSimulation`, stepped by the
granular engine :mod:`fastsdf.granular`); the names and tools above are the same.

Modules: :mod:`.family` (what every simulation of the family shares), :mod:`.simulation`
(particles), :mod:`.grains` (grains), :mod:`.engine` (the particles' fused step, the engine a
ParticleSimulation holds), :mod:`.state` (the states' arrays), :mod:`.forces`, :mod:`.world`
(what a step queries), :mod:`.reference` (the notebook's step in NumPy), :mod:`.kernels` and
:mod:`.cuda` (the GPU step).
"""

from fastsdf.granular.params import ContactLaw
from fastsdf.particles.forces import Drag, FieldForce, Gravity
from fastsdf.particles.grains import GrainSimulation, GrainState
from fastsdf.particles.kernels.constants import TRACE_FRACTION
from fastsdf.particles.reference import reference_step
from fastsdf.particles.simulation import (
    DEFAULT_BLOCK,
    PARALLEL_MIN_PARTICLES,
    ParticleSimulation,
    create_animation,
)
from fastsdf.particles.state import Particles
from fastsdf.particles.world import SimulationParams, _step_source

__all__ = [
    "SimulationParams",
    "ParticleSimulation",
    "GrainSimulation",
    "GrainState",
    "ContactLaw",
    "Particles",
    "Gravity",
    "Drag",
    "FieldForce",
    "create_animation",
    "reference_step",
    "TRACE_FRACTION",
    "PARALLEL_MIN_PARTICLES",
    "DEFAULT_BLOCK",
    "_step_source",
]
