"""Named, validated parameters of the granular contact model (soft-sphere DEM).

Units are those of the world: lengths in the SDF's coordinate units, time in seconds, mass in
any consistent unit (``density`` is mass per unit *area*: the grains are discs).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, NamedTuple, TypeVar

import numpy as np

from fastsdf.expr.validate import real, shown
from fastsdf.introspect import show_field_types

__all__ = [
    "ContactLaw",
    "STANDARD_GRAVITY",
    "check_contact_law",
    "contact_time",
    "damping_ratio",
    "derived_stiffness",
    "restitution_from_damping",
]

#: The gravity (length / s**2) a derived stiffness assumes when the grains feel none.
STANDARD_GRAVITY = 9.81
#: A derived stiffness keeps the overlap under a column of grains as tall as the world
#: at most this fraction of the grains' diameter.
DERIVED_OVERLAP = 0.01


_Law = TypeVar("_Law", bound="ContactLaw")


class _ContactLawFields(NamedTuple):
    """The fields of :class:`ContactLaw`, unchecked (build a ContactLaw, which checks them)."""

    stiffness: float | None = None
    restitution: float = 0.5
    friction: float = 0.5
    tangential_damping: float = 0.5
    tangential_stiffness: float = 2.0 / 7.0
    rolling_friction: float = 0.0
    history: bool = False


@show_field_types
class ContactLaw(_ContactLawFields):
    """A linear spring-dashpot contact with Coulomb friction, viscous (LAMMPS ``gran/hooke``,
    the default) or with a tangential spring per contact (``history=True``, LAMMPS
    ``gran/hooke/history``), and optional rolling resistance; passed as it is to the compiled
    kernels.

    Parameters
    ----------
    stiffness : float > 0, or None (the default: derived)
        Normal spring constant ``k_n`` (force / length, i.e. mass / s**2). A grain pressed by
        a load ``F`` overlaps its neighbour by ``F / k_n``: keep ``F / (k_n d)`` (the overlap
        relative to the diameter ``d``) at most about 1%. ``None``: the simulation derives it
        from the grains' sizes, density and gravity (:func:`derived_stiffness`): the bottom
        grain of a column of grains as tall as the world overlaps by 1% of its diameter, ``k_n
        = (H / d) m g / (0.01 d)``; for discs (``m = density pi d**2 / 4``) the size cancels,
        ``k_n = 25 pi density g H``. ``H`` is the world's height along gravity: the bounds of
        a grid world (``world.bounds``), else the grains' extent at the start (at least 10
        diameters); ``g`` is the magnitude of gravity (:data:`STANDARD_GRAVITY` when there is
        none). As stiff as the figure needs and no stiffer: the substep follows the contact
        time ``pi sqrt(m_eff / k_n)``, so a law 30 times too stiff costs 5.5 times the
        substeps. Impacts overlap more than resting contacts: a grain landing at speed ``v``
        overlaps by about ``v sqrt(m_eff / k_n)``.
    restitution : float in [0, 1]
        Coefficient of restitution ``e`` of a head-on impact; the dashpot of each contact is
        ``gamma_n = 2 zeta sqrt(m_eff k_n)`` with ``zeta = -ln e / sqrt(pi**2 + ln(e)**2)``
        (equivalently ``gamma_n = -2 ln(e) sqrt(m_eff k_n) / sqrt(pi**2 + ln(e)**2)``), so
        every pair rebounds with ``e`` whatever the sizes of its grains (``e = 0``: critical
        damping, ``e = 1``: no dissipation).
    friction : float, >= 0
        Coulomb coefficient ``mu``: the tangential force is at most ``mu |F_n|``.
    tangential_damping : float, >= 0
        Tangential dashpot relative to the normal one, ``gamma_t = tangential_damping *
        gamma_n`` (force / velocity of sliding at the contact point); 0.5 is LAMMPS's default
        (``gamma_t = NULL``).
    tangential_stiffness : float, > 0
        With ``history``: the tangential spring ``k_t = tangential_stiffness * k_n``; 2/7 is
        LAMMPS's default (``k_t = NULL``). Unused without history.
    rolling_friction : float, >= 0
        Rolling resistance ``mu_r`` (dimensionless; needs ``history``): a rolling spring per
        contact, its torque growing against the contact's relative rotation with stiffness
        ``k_r = 2.25 k_n mu_r**2 R_eff**2`` and capped at ``mu_r R_eff |F_n|``, ``R_eff =
        R_i R_j / (R_i + R_j)`` (``R_i`` against the world): the elastic-plastic spring of Ai,
        Chen, Rotter & Ooi (Powder Technology 206 (2011) 269, model C) in the ``epsd2`` form
        of Wensrich & Katterfeld (Powder Technology 217 (2012) 409). 0: none. Discs roll too
        easily to hold a heap; ``mu_r`` stands for the shape of real grains (usually
        calibrated against a measured angle of repose).
    history : bool
        ``False``: the viscous friction above (``gran/hooke``, no memory, no static friction).
        ``True``: a tangential spring per contact (Cundall-Strack, LAMMPS
        ``gran/hooke/history``): the spring stretches with the sliding of the contact point,
        turns with the contact, pulls back with ``k_t``, and slips where ``k_t |xi| >
        mu |F_n|`` (its stretch truncated to the cap); grains then rest on slopes below
        ``atan(mu)``. The spring is kept across neighbour-list rebuilds and the reordering of
        grains, and against the world (one per grain).

    Every way of making one checks its values (the constructor, ``_replace``, ``_make``, a
    checkpoint or a pickle loaded): a value out of range is a ValueError, a value of the wrong
    type a TypeError, each naming the parameter and the value. Numbers are stored as Python
    floats.
    """

    __slots__ = ()

    def __new__(
        cls,
        stiffness: float | None = None,
        restitution: float = 0.5,
        friction: float = 0.5,
        tangential_damping: float = 0.5,
        tangential_stiffness: float = 2.0 / 7.0,
        rolling_friction: float = 0.0,
        history: bool = False,
    ) -> ContactLaw:
        k = None if stiffness is None else real(stiffness, "stiffness")
        if k is not None and not k > 0:
            raise ValueError(f"stiffness must be > 0 (or None), got stiffness={shown(stiffness)}")
        e = real(restitution, "restitution")
        if not 0.0 <= e <= 1.0:
            raise ValueError(f"restitution must be in [0, 1], got restitution={shown(restitution)}")
        mu = _at_least_zero(friction, "friction")
        gt = _at_least_zero(tangential_damping, "tangential_damping")
        kt = real(tangential_stiffness, "tangential_stiffness")
        if not kt > 0:
            raise ValueError(
                f"tangential_stiffness must be > 0, got tangential_stiffness="
                f"{shown(tangential_stiffness)}"
            )
        mu_r = _at_least_zero(rolling_friction, "rolling_friction")
        if not isinstance(history, (bool, np.bool_)):
            raise TypeError(f"history must be a bool, got history={shown(history)}")
        if mu_r > 0 and not history:
            raise ValueError(
                f"rolling_friction needs history=True (the rolling spring is memory of the "
                f"contact), got rolling_friction={shown(rolling_friction)} with history=False"
            )
        return super().__new__(cls, k, e, mu, gt, kt, mu_r, bool(history))

    @classmethod
    def _make(cls: type[_Law], iterable: Iterable[Any]) -> _Law:  # type: ignore[override]
        """A law from a sequence of its fields, checked (``_replace`` builds through here)."""
        return cls(*iterable)

    def _replace(self: _Law, **changes: Any) -> _Law:
        """This law with ``changes`` (field=value), checked as a new law is."""
        unknown = sorted(set(changes) - set(self._fields))
        if unknown:
            raise ValueError(
                f"ContactLaw has no field {unknown[0]} (its fields: {', '.join(self._fields)}), "
                f"got {unknown[0]}={shown(changes[unknown[0]])}"
            )
        return type(self)(**{**self._asdict(), **changes})


def derived_stiffness(density: float, gravity: float, height: float) -> float:
    """The stiffness ``k_n = 25 pi density g H`` (force / length) under which the bottom contact
    of a column of equal discs as tall as ``height`` overlaps by 1% of the diameter ``d``: the
    column holds ``H / d`` discs of mass ``density pi d**2 / 4``, its weight ``F`` compresses
    the bottom contact by ``F / k_n = 0.01 d`` (the diameter cancels). ``gravity`` is the
    magnitude ``g`` (length / s**2); values that are not > 0 are a ValueError."""
    for name, value in (("density", density), ("gravity", gravity), ("height", height)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be finite and > 0, got {name}={value!r}")
    return 0.25 * math.pi * density * gravity * height / DERIVED_OVERLAP


#: A finite real number as a float (the simulation's checks of its own arguments).
_real = real


def _at_least_zero(value: object, name: str) -> float:
    number = real(value, name)
    if not number >= 0.0:
        raise ValueError(f"{name} must be >= 0, got {name}={shown(value)}")
    return number


def check_contact_law(law: object, name: str = "contact") -> ContactLaw:
    """``law`` as a :class:`ContactLaw` with a stiffness, or a clear ValueError/TypeError
    naming ``name`` and the offending field and value."""
    if not isinstance(law, ContactLaw):
        raise TypeError(f"{name} must be a fastsdf.granular.ContactLaw, got {name}={shown(law)}")
    if law.stiffness is None:
        raise ValueError(
            f"{name}.stiffness is None (derived by a simulation from its grains, see "
            f"ContactLaw): pass it to a simulation, or give a stiffness"
        )
    try:  # checked again: a law built around its constructor (tuple.__new__) too
        return ContactLaw(*law)
    except (TypeError, ValueError) as err:
        raise type(err)(f"{name}.{err}") from None


def damping_ratio(restitution: float) -> float:
    """The dashpot's damping ratio ``zeta = gamma_n / (2 sqrt(m_eff k_n))`` that gives the
    coefficient of restitution ``e``: ``-ln e / sqrt(pi**2 + ln(e)**2)`` (1 at ``e = 0``)."""
    if restitution <= 0.0:
        return 1.0
    le = math.log(restitution)
    return -le / math.sqrt(math.pi * math.pi + le * le)


def contact_time(m_eff: float, law: ContactLaw, damped: bool = False) -> float:
    """Duration of a binary contact (s) of effective mass ``m_eff`` under ``law`` (its
    ``stiffness`` ``k_n`` resolved): ``t_c = pi sqrt(m_eff / k_n)`` (undamped); with
    ``damped=True`` the exact duration of the damped linear contact,
    ``t_c / sqrt(1 - zeta**2)`` (infinite at critical damping, ``e = 0``)."""
    if law.stiffness is None:
        raise ValueError("law.stiffness is None: resolve it first (see ContactLaw)")
    tc = math.pi * math.sqrt(m_eff / law.stiffness)
    if not damped:
        return tc
    z = damping_ratio(law.restitution)
    return math.inf if z >= 1.0 else tc / math.sqrt(1.0 - z * z)


def restitution_from_damping(gamma_per_mass: float, stiffness: float, m_eff: float) -> float:
    """The restitution of a pair of effective mass ``m_eff`` whose dashpot is ``m_eff *
    gamma_per_mass`` (LAMMPS's ``gamma_n``, in 1/s) and whose spring is ``stiffness`` (N/m,
    LAMMPS's ``k_n``): to state a LAMMPS ``gran/hooke`` model as a :class:`ContactLaw`
    (exactly, for grains of one size)."""
    z = m_eff * gamma_per_mass / (2.0 * math.sqrt(m_eff * stiffness))
    if z >= 1.0:
        return 0.0
    return math.exp(-z * math.pi / math.sqrt(1.0 - z * z))
