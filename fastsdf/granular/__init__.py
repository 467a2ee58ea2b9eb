"""Grains that collide with each other and with an SDF world: soft-sphere DEM in 2D.

The engine of the particle family's grains: ``fastsdf.particles.ParticleSimulation(world,
positions=..., radius=..., contacts=ContactLaw())`` steps with it under the family's names and
tools. ``ContactLaw()`` without a stiffness derives one from the grains (see
:class:`ContactLaw`).

``GranularSimulation(world, positions=..., radius=..., contacts=ContactLaw(...))`` (the family's
arguments, with ``gravity=`` in place of a force generator) steps discs with
the ``gran/hooke`` contact law (linear spring, restitution-set dashpot, Coulomb-capped viscous
friction, rotation), or with ``ContactLaw(history=True)`` LAMMPS's ``gran/hooke/history`` (a
Cundall-Strack tangential spring per contact: static friction; optional rolling resistance), by
velocity Verlet, substepping each frame to resolve the contact time, with
a parallel cell list and Verlet list (no atomics). The kernels live in :mod:`.kernels` and
:mod:`.cells` and are usable on their own. Which model to choose, their parameters and units:
``docs/granular_models.md``. :func:`repose_angle` measures a heap's angle of repose,
:func:`flow_rate` a silo's discharge, and :func:`beverloo_fit` fits Beverloo's law to the
discharges through slots of several widths.

Distribution (not implemented): grains interact, so sharding them across machines as
independent batches (as plain particles are) would be wrong. The way to distribute is by
spatial domains with halo exchange: each machine owns the grains of one region and, every
substep, receives the positions and predicted velocities of the grains within one cutoff
(``2 max(R) + skin``) of its border. For 1e8 discs of diameter 1 in a dense square packing
(about 1.15 per unit area, side about 9,300) and a cutoff of 1.2, a border of length ``L``
carries about ``1.4 L`` halo grains per side: cut into N strips, each machine receives about
26,000 grains (1.2 MB at 48 bytes each) per substep whatever N; cut into ``p x p`` tiles,
about ``51,000 / p`` grains (2.5 MB / p). A machine holding ``1e8 / N`` grains at 10 M
particle-steps/s spends ``10 / N`` s per substep, so strips need about ``0.12 N`` MB/s: bandwidth
is no limit; the two messages per substep (their latency) are, once ``10 / N`` s shrinks toward
a network round trip (N in the thousands).
"""

# (registers the GPU engine as GranularSimulation's device='cuda'; loads no numba-cuda)
import fastsdf.granular.cuda  # noqa: F401
from fastsdf.granular.analysis import (
    BeverlooFit,
    ReposeAngle,
    beverloo_fit,
    flow_rate,
    repose_angle,
)
from fastsdf.granular.cells import CellGrid, brute_force_pairs, list_pairs
from fastsdf.granular.checks import StartingStateWarning
from fastsdf.granular.kernels import Bulk, Grains
from fastsdf.granular.params import (
    ContactLaw,
    check_contact_law,
    contact_time,
    damping_ratio,
    derived_stiffness,
    restitution_from_damping,
)
from fastsdf.granular.simulation import (
    DEFAULT_SUBSTEPS_PER_CONTACT,
    GranularSimulation,
    SubstepWarning,
)

__all__ = [
    "DEFAULT_SUBSTEPS_PER_CONTACT",
    "BeverlooFit",
    "Bulk",
    "CellGrid",
    "ContactLaw",
    "Grains",
    "GranularSimulation",
    "ReposeAngle",
    "StartingStateWarning",
    "SubstepWarning",
    "beverloo_fit",
    "brute_force_pairs",
    "check_contact_law",
    "contact_time",
    "damping_ratio",
    "derived_stiffness",
    "flow_rate",
    "list_pairs",
    "repose_angle",
    "restitution_from_damping",
]
