"""Keeping simulations: save and resume (:mod:`fastsdf.particles.checkpoint`, also
``sim.save(path)`` and ``ParticleSimulation.load(path)``), trajectory files in the H5MD layout
(:mod:`fastsdf.io.trajectory`; writing and reading them needs h5py, the ``io`` extra)."""

from fastsdf.io.trajectory import TrajectoryRecorder, read_trajectory
from fastsdf.particles.checkpoint import load_simulation, save_simulation

__all__ = ["save_simulation", "load_simulation", "TrajectoryRecorder", "read_trajectory"]
