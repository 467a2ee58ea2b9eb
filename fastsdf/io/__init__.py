"""Keeping simulations: save and resume (:mod:`fastsdf.io.state`), trajectory files in the H5MD
layout (:mod:`fastsdf.io.trajectory`, needs the ``io`` extra: h5py)."""

from .state import load_simulation, save_simulation

__all__ = ["save_simulation", "load_simulation"]
