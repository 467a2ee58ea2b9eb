"""Keeping simulations: save and resume (:mod:`fastsdf.io.state`), trajectory files in the H5MD
layout (:mod:`fastsdf.io.trajectory`; writing and reading them needs h5py, the ``io`` extra)."""

from fastsdf.io.state import load_simulation, save_simulation
from fastsdf.io.trajectory import TrajectoryRecorder, read_trajectory

__all__ = ["save_simulation", "load_simulation", "TrajectoryRecorder", "read_trajectory"]
