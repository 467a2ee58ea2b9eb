"""A contact law checks its own values, however it is made: the constructor, ``_replace``,
``_make``, a pickle, a checkpoint; a simulation never sees a law out of range."""

import copy
import math
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fastsdf.granular import ContactLaw, GranularSimulation, check_contact_law

BAD = [
    ({"restitution": 2}, ValueError, r"restitution must be in \[0, 1\], got restitution=2"),
    ({"restitution": -0.1}, ValueError, r"restitution=-0\.1"),
    ({"restitution": float("nan")}, ValueError, r"restitution must be finite.*nan"),
    ({"friction": -1}, ValueError, r"friction must be >= 0, got friction=-1"),
    ({"friction": math.inf}, ValueError, r"friction must be finite, got friction=inf"),
    ({"friction": "high"}, TypeError, r"friction must be a real number, got friction='high'"),
    ({"friction": None}, TypeError, r"friction.*None"),
    ({"stiffness": -1.0}, ValueError, r"stiffness must be > 0.*stiffness=-1\.0"),
    ({"stiffness": 0}, ValueError, r"stiffness=0"),
    ({"stiffness": float("nan")}, ValueError, r"stiffness must be finite"),
    ({"stiffness": "stiff"}, TypeError, r"stiffness must be a real number.*'stiff'"),
    ({"stiffness": True}, TypeError, r"stiffness.*True"),
    ({"stiffness": np.array([1.0, 2.0])}, TypeError, r"stiffness.*\[1\.0, 2\.0\]"),
    ({"tangential_damping": -2}, ValueError, r"tangential_damping must be >= 0.*=-2"),
    ({"tangential_stiffness": 0.0}, ValueError, r"tangential_stiffness must be > 0.*=0\.0"),
    ({"tangential_stiffness": -math.inf}, ValueError, r"tangential_stiffness must be finite"),
    (
        {"rolling_friction": 0.3},
        ValueError,
        r"rolling_friction needs history=True.*rolling_friction=0\.3",
    ),
    ({"rolling_friction": -0.1, "history": True}, ValueError, r"rolling_friction=-0\.1"),
    ({"history": "yes"}, TypeError, r"history must be a bool, got history='yes'"),
    ({"history": 1}, TypeError, r"history=1"),
]


@pytest.mark.parametrize("kwargs, error, match", BAD)
def test_bad_values_are_named_at_construction(kwargs, error, match):
    with pytest.raises(error, match=match):
        ContactLaw(**kwargs)


@pytest.mark.parametrize("kwargs, error, match", BAD)
def test_no_way_around_the_check(kwargs, error, match):
    """``_replace`` and ``_make`` (which a NamedTuple's ``_replace`` uses) check as the
    constructor does; so do pickles and copies (they rebuild through the constructor)."""
    law = ContactLaw(stiffness=1e4)
    with pytest.raises(error, match=match):
        law._replace(**kwargs)
    fields = {**law._asdict(), **kwargs}
    with pytest.raises(error, match=match):
        ContactLaw._make(fields[f] for f in ContactLaw._fields)
    forged = tuple.__new__(ContactLaw, tuple(fields[f] for f in ContactLaw._fields))
    with pytest.raises(error, match=match):
        pickle.loads(pickle.dumps(forged))
    with pytest.raises(error, match=match):
        copy.deepcopy(forged)
    with pytest.raises(error, match=rf"contacts\.{next(iter(kwargs))}"):
        check_contact_law(forged, "contacts")


def test_a_forged_law_never_reaches_a_simulation():
    forged = tuple.__new__(ContactLaw, (1e4, 2.0, 0.5, 0.5, 0.5, 0.0, False))
    with pytest.raises(ValueError, match=r"wall_contacts\.restitution must be in \[0, 1\]"):
        GranularSimulation(None, positions=[[0.0, 0.0]], radius=0.5, wall_contacts=forged)


def test_replace_names_an_unknown_field():
    with pytest.raises(ValueError, match="ContactLaw has no field resitution.*resitution=0.5"):
        ContactLaw()._replace(resitution=0.5)


def test_values_are_stored_as_python_floats():
    law = ContactLaw(np.float32(1000), 1, np.int64(0), history=np.bool_(True))
    assert law == (1000.0, 1.0, 0.0, 0.5, 2.0 / 7.0, 0.0, True)
    assert [type(v) for v in law] == [float] * 6 + [bool]
    assert ContactLaw().stiffness is None


# Every law the docs, examples and tests write constructs.
GOOD = [
    {},
    {"stiffness": 2e5, "restitution": 0.0},
    {"stiffness": 1e4, "restitution": 1.0, "friction": 10.0, "history": True},
    {"history": True, "rolling_friction": 0.5},
    {"history": True, "rolling_friction": 0.2, "tangential_stiffness": 1.0},
    {"friction": 0.0, "tangential_damping": 0.0},
]


@pytest.mark.parametrize("kwargs", GOOD)
def test_valid_laws_construct_and_round_trip(kwargs):
    law = ContactLaw(**kwargs)
    assert pickle.loads(pickle.dumps(law)) == law
    assert type(pickle.loads(pickle.dumps(law))) is ContactLaw
    assert law._replace() == law
    assert ContactLaw._make(law) == law


finite = {"allow_nan": False, "allow_infinity": False}


@settings(max_examples=200, deadline=None)
@given(
    stiffness=st.none() | st.floats(min_value=1e-300, max_value=1e300, **finite),
    restitution=st.floats(min_value=0.0, max_value=1.0),
    friction=st.floats(min_value=0.0, max_value=1e300, **finite),
    tangential_damping=st.floats(min_value=0.0, max_value=1e300, **finite),
    tangential_stiffness=st.floats(min_value=1e-300, max_value=1e300, **finite),
    rolling_friction=st.floats(min_value=0.0, max_value=1e300, **finite),
    history=st.booleans(),
)
def test_every_value_in_range_is_accepted(
    stiffness,
    restitution,
    friction,
    tangential_damping,
    tangential_stiffness,
    rolling_friction,
    history,
):
    args = (
        stiffness,
        restitution,
        friction,
        tangential_damping,
        tangential_stiffness,
        rolling_friction,
        history,
    )
    if rolling_friction > 0 and not history:
        with pytest.raises(ValueError, match="rolling_friction needs history=True"):
            ContactLaw(*args)
        return
    law = ContactLaw(*args)
    assert tuple(law) == args
    assert law._replace(restitution=1.0 - restitution).restitution == 1.0 - restitution


@settings(max_examples=100, deadline=None)
@given(
    field=st.sampled_from(["restitution", "friction", "tangential_damping", "rolling_friction"]),
    value=st.floats(max_value=-1e-300, allow_nan=False),
)
def test_every_negative_value_is_refused(field, value):
    with pytest.raises(ValueError, match=field):
        ContactLaw(history=True, **{field: value})
