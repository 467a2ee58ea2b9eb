"""Grains that collide with each other and with an SDF world: soft-sphere DEM in 2D.

``GranularSimulation(positions, radius, world=f, contact=ContactLaw(...))`` steps discs with
the ``gran/hooke`` contact law (linear spring, restitution-set dashpot, Coulomb-capped viscous
friction, rotation) by velocity Verlet, substepping each frame to resolve the contact time, with
a parallel cell list and Verlet list (no atomics). The kernels live in :mod:`.kernels` and
:mod:`.cells` and are usable on their own.
"""
from .cells import CellGrid, brute_force_pairs, list_pairs
from .kernels import Bulk, Grains
from .params import (
                     ContactLaw,
                     check_contact_law,
                     contact_time,
                     damping_ratio,
                     restitution_from_damping,
)
from .simulation import DEFAULT_SUBSTEPS_PER_CONTACT, GranularSimulation

__all__ = [
                     "DEFAULT_SUBSTEPS_PER_CONTACT",
                     "Bulk",
                     "CellGrid",
                     "ContactLaw",
                     "Grains",
                     "GranularSimulation",
                     "brute_force_pairs",
                     "check_contact_law",
                     "contact_time",
                     "damping_ratio",
                     "list_pairs",
                     "restitution_from_damping",
]
