"""The benchmark plots' helpers: Pareto fronts and plain tick labels."""

import matplotlib

matplotlib.use("Agg")

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.plots import _plain, pareto_front, plain_log_ticks

pairs = st.lists(st.tuples(st.floats(1e-6, 1.0), st.floats(1.0, 1e3)), min_size=1, max_size=30)


@settings(max_examples=200, deadline=None)
@given(pairs)
def test_pareto_front_is_exactly_the_non_dominated_points(points):
    front = pareto_front(points)

    def dominated(p):
        return any((q[0] <= p[0] and q[1] > p[1]) or (q[0] < p[0] and q[1] >= p[1]) for q in points)

    expected = {p for p in points if not dominated(p)}
    assert set(front) == expected
    errs, speeds = [p[0] for p in front], [p[1] for p in front]
    assert errs == sorted(errs) and speeds == sorted(speeds)  # faster costs accuracy


def test_plain_labels_have_no_powers_of_ten():
    for v in [1e-4, 2e-4, 1e-3, 0.05, 1, 20, 300, 1000, 1e4, 1e5, 4e6, 1e7, 2e8]:
        text = _plain(v)
        assert "^" not in text and "times" not in text and "e+" not in text, text
    assert [_plain(v) for v in (0.001, 20, 1e4, 1e6)] == ["0.001", "20", "10k", "1M"]


def test_log_axes_get_plain_tick_labels():
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    ax.loglog([1e3, 1e7], [3e1, 6e1])
    plain_log_ticks(ax)
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_yticklabels(minor=True) + ax.get_yticklabels()]
    assert any(labels) and not any("times" in t or "^" in t for t in labels), labels
    assert "10k" in [t.get_text() for t in ax.get_xticklabels()]
    assert np.isfinite(ax.get_ylim()).all()
