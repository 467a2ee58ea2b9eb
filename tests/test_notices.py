"""Waits that announce themselves: compile notices, the progress of long runs, and the warning
of a granular simulation whose frames take very many substeps."""

import io
import warnings

import numpy as np
import pytest
from numba import njit

import fastsdf.granular.simulation as granular_simulation
import fastsdf.notice as notice
from fastsdf.granular import ContactLaw, GranularSimulation, SubstepWarning
from fastsdf.granular.simulation import SUBSTEPS_WARNING


@pytest.fixture(autouse=True)
def _loud(monkeypatch):
    monkeypatch.delenv("FASTSDF_QUIET", raising=False)


def test_compiling_first_announces_the_first_call_only(capsys):
    @njit
    def twice(x):
        return 2 * x

    cm = notice.compiling_first("a test kernel", twice, after=0.0)
    with cm:
        assert twice(3) == 6  # compiles here
    err = capsys.readouterr().err
    assert "fastsdf: compiling a test kernel (once" in err and "...done in" in err
    # compiled now: a later call is not announced, however long it takes
    with notice.compiling_first("a test kernel", twice, after=0.0):
        assert twice(4) == 8
    assert capsys.readouterr().err == ""


def test_every_wait_is_said_not_only_the_first_of_a_message(capsys):
    """Two new scenes are two waits: the same words are printed again."""
    for value in (1, 2):

        @njit
        def k(x, value=value):
            return x + value

        with notice.compiling("a scene", after=0.0):
            k(1)
    assert capsys.readouterr().err.count("compiling a scene") == 2


def test_run_progress_shows_an_estimate_past_its_threshold_only():
    shown = io.StringIO()
    with notice.RunProgress(10, "ten things", "things", after=0.0, stream=shown) as bar:
        for k in range(10):
            bar.update(k + 1)
    text = shown.getvalue()
    assert text.startswith("fastsdf: ten things: 1 of 10 things in ")
    assert "left" in text.splitlines()[0]
    assert text.splitlines()[-1].startswith("fastsdf: ten things: 10 of 10 things in ")
    quiet = io.StringIO()
    with notice.RunProgress(10, "ten things", after=1e9, stream=quiet) as bar:
        for k in range(10):
            bar.update(k + 1)
    assert quiet.getvalue() == "" and not bar.shown


def test_run_progress_is_silenced_by_fastsdf_quiet(monkeypatch):
    monkeypatch.setenv("FASTSDF_QUIET", "1")
    out = io.StringIO()
    with notice.RunProgress(3, "x", after=0.0, stream=out) as bar:
        bar.update(1)
    assert out.getvalue() == ""


def _column(n: int, radius: float, height: float) -> np.ndarray:
    """``n`` grains apart in a column spanning ``height``."""
    return np.column_stack([np.zeros(n), np.linspace(0.0, height, n)])


def test_substep_warning_names_the_cause_and_fires_once(monkeypatch):
    """Small grains and a stiff law: thousands of substeps per frame; the warning says why
    (radius, mass, stiffness: the contact time) and what to change, once. (Three grains make
    a quick frame however many substeps: the work threshold is lowered to theirs.)"""
    sim = GranularSimulation(
        None,
        positions=_column(3, 0.002, 0.1),
        radius=0.002,
        contacts=ContactLaw(stiffness=1e4),
        gravity=(0, -9.81),
    )
    assert sim.substeps_per_frame > SUBSTEPS_WARNING
    with warnings.catch_warnings():
        warnings.simplefilter("error", SubstepWarning)
        sim.run(1)  # a quick frame: no warning at the default work threshold
    monkeypatch.setattr(granular_simulation, "SUBSTEPS_WARNING_WORK", 3)
    with pytest.warns(SubstepWarning) as caught:
        sim.run(1)
    text = str(caught[0].message)
    assert caught[0].filename == __file__  # the user's line, not the library's
    assert f"{sim.substeps_per_frame:,} substeps per frame" in text
    for words in (
        "two grains of radius 0.002",
        "stiffness 1e+04, as given",
        "t_c = pi sqrt(m_eff / k)",
        "a softer contact law",
        "bigger grains",
    ):
        assert words in text, words
    # the contact time printed is the one the substep resolves
    assert f"{sim.contact_time:.3g} s" in text
    with warnings.catch_warnings():
        warnings.simplefilter("error", SubstepWarning)
        sim.run(1)  # said once per simulation


def test_substep_warning_says_what_set_the_substep(monkeypatch):
    """A derived stiffness: the world's height it was derived for; a substep given: that."""
    monkeypatch.setattr(granular_simulation, "SUBSTEPS_WARNING_WORK", 3)
    derived = GranularSimulation(
        None, positions=_column(3, 0.002, 0.5), radius=0.002, gravity=(0, -9.81)
    )
    given = GranularSimulation(
        None, positions=_column(3, 0.02, 0.5), radius=0.02, substep=1e-5, gravity=(0, -9.81)
    )
    for sim, words in (
        (derived, "derived for a column of grains as tall as the world, H = 0.5"),
        (given, "the substep given, 1e-05 s"),
    ):
        assert sim.substeps_per_frame > SUBSTEPS_WARNING
        with pytest.warns(SubstepWarning, match="substeps per frame") as caught:
            sim.run(1)
        assert words in str(caught[0].message)


def test_default_grains_run_without_the_warning(monkeypatch):
    """The library's default grains (radius 0.02, a derived stiffness) in a world 4 high, as
    its scenes are: fewer substeps than the threshold, no warning (whatever their number:
    the work threshold is lowered so that the substeps alone decide)."""
    monkeypatch.setattr(granular_simulation, "SUBSTEPS_WARNING_WORK", 0)
    sim = GranularSimulation(
        None, positions=_column(20, 0.02, 4.0), radius=0.02, gravity=(0, -9.81)
    )
    assert sim.substeps_per_frame <= SUBSTEPS_WARNING
    with warnings.catch_warnings():
        warnings.simplefilter("error", SubstepWarning)
        sim.run(1)


def test_a_long_granular_run_shows_its_progress_on_stderr(monkeypatch, capsys):
    monkeypatch.setattr(notice, "PROGRESS_AFTER_S", 0.0)
    sim = GranularSimulation(
        None, positions=_column(20, 0.02, 4.0), radius=0.02, gravity=(0, -9.81)
    )
    sim.run(3)
    err = capsys.readouterr().err
    assert f"fastsdf: 20 grains, run(3) at {sim.substeps_per_frame:,} substeps per frame:" in err
    assert "left" in err and "3 of 3 frames in" in err
    monkeypatch.setattr(notice, "PROGRESS_AFTER_S", 1e9)
    sim.run(3)
    assert capsys.readouterr().err == ""


def test_a_long_particle_run_goes_in_pieces_with_progress_and_the_same_bits(monkeypatch, capsys):
    """A run long enough to show progress goes in pieces; particles do not interact, so the
    pieces give the bits of one call."""
    import fastsdf as sdf
    import fastsdf.particles as phys
    import fastsdf.particles.simulation as simulation

    floor = sdf.Halfspace(normal=[0, 1], d=0.0)

    def make():
        sim = phys.ParticleSimulation(floor, n=500, seed=3)
        sim.force_generators += [phys.Gravity()]
        return sim

    whole = make()
    whole.run(40)
    assert capsys.readouterr().err.count("particles, run(") == 0
    monkeypatch.setattr(notice, "PROGRESS_AFTER_S", 0.0)
    monkeypatch.setattr(simulation, "PROGRESS_MIN_PARTICLE_STEPS", 0)
    monkeypatch.setattr(simulation, "_PROGRESS_FIRST_PIECE", 500 * 7)  # 7 steps
    monkeypatch.setattr(simulation, "_PROGRESS_PIECE_S", 0.0)  # then one step a piece
    pieces = make()
    pieces.run(40)
    err = capsys.readouterr().err
    assert "fastsdf: 500 particles, run(40): 7 of 40 steps in" in err
    assert "40 of 40 steps in" in err
    for name in ("x", "v"):
        np.testing.assert_array_equal(pieces.p[name], whole.p[name])
    assert pieces.t == pytest.approx(whole.t, rel=1e-14)


def test_the_demo_warms_the_grains_and_image_kernels_of_the_readme():
    """``make demo`` ends by compiling (or loading) what the README's particle, grain and
    image blocks use: afterwards this process has the particle step's entry point for long
    calls, the granular kernels (their contacts with the world too: after the demo the grain
    block once compiled them for 4.4 s) and the distance transform."""
    import fastsdf.particles.simulation as simulation
    from fastsdf.apps.demo import warm_readme_kernels
    from fastsdf.geometry.edt import edt_kernel
    from fastsdf.granular.kernels import kick_drift, pair_forces, substep_pass, wall_forces
    from fastsdf.particles.engine import LONG_CALL

    long_calls = []
    real_run = simulation.ParticleSimulation.run

    def run(self, steps, record=None):
        long_calls.append(
            self.n * steps >= LONG_CALL and type(self) is simulation.ParticleSimulation
        )
        return real_run(self, steps, record)

    said = io.StringIO()
    simulation.ParticleSimulation.run = run
    try:
        warm_readme_kernels(said)
    finally:
        simulation.ParticleSimulation.run = real_run
    assert said.getvalue().startswith("fastsdf demo: compiling the kernels of the README's")
    assert "ready in" in said.getvalue()
    assert any(long_calls)
    for kernel in (pair_forces, kick_drift, substep_pass, wall_forces, edt_kernel):
        assert kernel.signatures, kernel


def test_the_demo_warms_the_law_of_the_readme_grain_block():
    """The law the warm-up pours with is the README grain block's (its compiled variant)."""
    import os
    import re

    from fastsdf.apps.demo import README_GRAIN_LAW

    with open(os.path.join(os.path.dirname(__file__), "..", "README.md"), encoding="utf-8") as fh:
        readme = fh.read()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    (block,) = [b for b in blocks if "contacts=law" in b]
    line = next(x for x in block.splitlines() if x.startswith("law = "))
    namespace: dict = {"ContactLaw": ContactLaw}
    exec(line, namespace)
    assert namespace["law"] == ContactLaw(**README_GRAIN_LAW)


def test_a_recorded_run_shows_one_progress_for_all_its_blocks(monkeypatch, capsys):
    """A recorder runs the simulation in blocks; their runs report to the recorded run's
    progress (one line of it, counting every block), not each their own."""
    import fastsdf as sdf
    import fastsdf.particles as phys

    class EveryFive:
        def run(self, sim, steps):
            for _ in range(steps // 5):
                sim.run(5)

    sim = phys.ParticleSimulation(sdf.Halfspace(normal=[0, 1], d=0.0), n=50, seed=1)
    sim.force_generators += [phys.Gravity()]
    monkeypatch.setattr(notice, "PROGRESS_AFTER_S", 0.0)
    sim.run(20, record=EveryFive())
    err = capsys.readouterr().err
    assert "fastsdf: 50 particles, run(20, record=...): 5 of 20 steps in" in err
    assert "fastsdf: 50 particles, run(20, record=...): 20 of 20 steps in" in err
    assert "run(5)" not in err  # the blocks report to the recorded run
    assert sim.t == pytest.approx(20 * sim.dt)


# -- the time left, on a fake clock ---------------------------------------------------------


class _Clock:
    """A clock the test moves: ``clock.wait(seconds)``."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now

    def wait(self, seconds):
        self.now += seconds


def _compile(clock, seconds):
    """``seconds`` in numba's compiler, as numba announces it (the events its lock fires)."""
    from numba.core import event

    event.start_event("numba:compiler_lock")
    clock.wait(seconds)
    event.end_event("numba:compiler_lock")


def _first_estimate(monkeypatch, costs, compiles=None, updates=1):
    """Run ``RunProgress`` over frames costing ``costs`` seconds each (``compiles``: frame ->
    seconds of compiling before it) on a fake clock, ``updates`` per frame; return the clock
    and the true time left when the first estimate was shown, its estimate, and the text."""
    clock = _Clock()
    monkeypatch.setattr(notice, "_clock", clock)
    out = io.StringIO()
    compiles = compiles or {}
    start = clock.now
    first = None
    with notice.RunProgress(len(costs), "frames of a test", "frames", stream=out) as bar:
        for k, cost in enumerate(costs):
            if k in compiles:
                _compile(clock, compiles[k])
            for s in range(updates):
                clock.wait(cost / updates)
                bar.update(k + (s + 1) / updates)
                if bar.shown and first is None:
                    first = (clock.now - start, bar.remaining(), sum(costs[k + 1 :]))
                    first += ((1 - (s + 1) / updates) * cost,)
    shown_at, estimate, later, rest_of_frame = first
    return shown_at, estimate, later + rest_of_frame, out.getvalue()


def test_the_readme_grain_blocks_first_estimate_leaves_its_compiling_out(monkeypatch):
    """The README's grain block as the issue saw it: grains fall freely for 18 frames, the
    first grain to reach the world compiles the wall contacts (4.4 s), frames then cost
    what grains on a heap do (measured per frame: 0.012 s falling, 0.043 s landing, 0.03 s at
    rest). The old estimate, "18 of 600 frames in 5 s, about 2 min 34 s left", counted the
    compiling as work; the first estimate now comes within 10 s and within 2x of the truth."""
    costs = [0.012] * 18 + [0.043] * 232 + [0.03] * 350
    shown_at, estimate, truth, text = _first_estimate(monkeypatch, costs, {18: 4.4})
    assert shown_at <= 10.0
    assert 0.5 <= estimate / truth <= 2.0, (estimate, truth)
    first = text.splitlines()[0]
    assert "(4 s of it compiling)" in first, first
    assert text.splitlines()[-1].startswith("fastsdf: frames of a test: 600 of 600 frames in")


def test_the_estimate_follows_the_latest_half_of_the_work(monkeypatch):
    """Frames that become twice as slow: once the latest half of the work is all slow frames,
    the estimate is exactly the slow frames' rate times the frames left."""
    clock = _Clock()
    monkeypatch.setattr(notice, "_clock", clock)
    with notice.RunProgress(400, "x", "frames", after=1e9, stream=io.StringIO()) as bar:
        for k in range(100):
            clock.wait(0.01)
            bar.update(k + 1)
        for k in range(100, 300):
            clock.wait(0.02)
            bar.update(k + 1)
        # work 5 s: the latest half, from 2.5 s, is slow frames only
        assert bar.remaining() == pytest.approx(100 * 0.02, rel=1e-9)
        _compile(clock, 30.0)  # compiling is no work: the estimate stands
        assert bar.remaining(clock.now) == pytest.approx(100 * 0.02, rel=1e-9)
        assert bar.compiled() == pytest.approx(30.0)


def test_a_run_whose_frames_get_slower_says_so(monkeypatch):
    """The estimate cannot know that frames will keep getting slower (grains landing): it
    says that they are."""
    costs = [0.01 * 1.04**k for k in range(100)]
    shown_at, estimate, truth, text = _first_estimate(monkeypatch, costs)
    assert "(the frames are getting slower)" in text.splitlines()[0]
    steady = _first_estimate(monkeypatch, [0.03] * 300)
    assert "getting" not in steady[3] and steady[1] == pytest.approx(steady[2], rel=1e-6)


def test_compiling_in_another_thread_is_work_of_this_one(monkeypatch):
    """Only this thread's time in numba's compiler is left out: a background compile while
    this thread works does not stop its clock."""
    import threading

    clock = _Clock()
    monkeypatch.setattr(notice, "_clock", clock)
    with notice.RunProgress(10, "x", after=1e9, stream=io.StringIO()) as bar:
        worker = threading.Thread(target=_compile, args=(clock, 5.0))
        worker.start()
        worker.join()
        clock.wait(1.0)
        bar.update(5)
        assert bar.compiled() == 0.0
        assert bar.remaining() == pytest.approx(6.0)


def test_a_real_compile_is_left_out_of_the_work():
    """numba compiling a new function inside a run is seen as compiling (its lock's events)."""

    @njit
    def fresh(x):
        return x + 1.5

    with notice.RunProgress(2, "x", after=1e9, stream=io.StringIO()) as bar:
        fresh(1.0)
        bar.update(1)
        assert bar.compiled() > 0.0


def test_a_slow_block_is_announced_only_when_numba_compiles_for_it(capsys):
    """A block that takes long without numba compiling says nothing, nor one where numba
    only loads compiled kernels (its lock held, no compile: a second simulation was said to
    compile the granular kernels again); one that waits for another thread's compile says
    "compiling"."""
    import threading
    import time

    from numba.core import event

    with notice.compiling("a slow block", after=0.0):
        time.sleep(0.4)
    with notice.compiling("some kernels", after=0.0):
        event.start_event("numba:compiler_lock")
        time.sleep(0.4)
        event.end_event("numba:compiler_lock")
    assert capsys.readouterr().err == ""

    def compile_elsewhere():
        event.start_event("numba:compile", data={})
        event.end_event("numba:compile", data={})

    with notice.compiling("a scene", after=0.0):
        event.start_event("numba:compiler_lock")  # waiting for it...
        other = threading.Thread(target=compile_elsewhere)
        other.start()
        other.join()
        time.sleep(0.4)
        event.end_event("numba:compiler_lock")
    err = capsys.readouterr().err
    assert "fastsdf: compiling a scene (once" in err and "...done in" in err
