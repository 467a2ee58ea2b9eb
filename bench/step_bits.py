"""Bit-identity of the particle family's trajectories against another revision's particle engine.

    python -m bench.step_bits --rev 9af86bd                 # every case, 3000 particles
    python -m bench.step_bits --rev 9af86bd --only grid     # the cases whose name has "grid"
    python -m bench.step_bits --rev 9af86bd --list          # the cases' names
    python -m bench.step_bits --rev 9af86bd --whole         # the revision's whole package

The baseline is the revision's ``fastsdf/particles/`` package loaded beside the current one as
``fastsdf._ab_base`` (as in ``bench.step_ab``: the rest of fastsdf, the granular engine
included, is the current one). Each case builds the same simulation with both engines from
the same state and makes the same calls (by default 60 steps in 4 calls of 15), then
compares positions, velocities (grains: and angular velocities) and the clock bit for bit.
With ``--whole`` the baseline is the revision's whole package instead, run in a process of its
own (for a revision whose particle package does not run on the current function layer).

The cases cover every kernel a step can take:

- exact worlds: the seed world (the static sweep), a pruned scene (many operands in loops over
  tables: the plan header), a parametric world, and moving worlds (a thin bar rising through a
  box, a piston: the space-time march and sweep), each with and without the tunnelling check
  and query skipping;
- grid worlds (``GridSDF``): stored gradients (the block kernel, with and without skipping and
  the tunnelling check, fused ``@njit`` forces, a FieldForce and drag, explicit Euler with the
  notebook's collision rule, mode 'nearest', a float32 grid, particles leaving the grid so
  that the exact fallback is bound mid-call), finite-difference gradients, float32 state, and
  the threaded paths (slices on several threads, numba's parallel entry point);
- band worlds (``NarrowBandGridSDF``): the band the docs advise for particles, and one
  narrower than their radii (against revisions before 1641ec6 this case differs: they
  skipped queries that would have met a far tile's bound, so their bits depended on how
  the calls were cut; now skipping changes no result there either);
- resting contact (``rest_speed``) on a grid and on an exact world, Python force generators;
- grains: ``ContactLaw()`` and ``ContactLaw(history=True, rolling_friction=...)``, with fused
  forces.

A case fails if the two disagree in any bit, or if only one raises (then the messages must be
the same). Exit status 0 when every case is bit-identical.
"""

from __future__ import annotations

import argparse
import math
import os
import pickle
import subprocess
import sys
import tempfile
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit


@njit(cache=True)
def _gust(x, y, vx, vy, m, t):
    """A fused user force that depends on position, velocity, mass and time."""
    return 0.2 * (0.5 + 0.3 * y - vx) * m, -0.1 * vy + 0.05 * math.sin(3.0 * t)


def _python_drag(p, t):
    """A Python force generator (the slow path: one compiled step per evaluation)."""
    return -0.1 * np.asarray(p["v"], dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# The worlds.


def _box():
    import fastsdf as sdf

    return (
        sdf.Halfspace(normal=[0, 1], d=-1.2)
        | sdf.Halfspace(normal=[0, -1], d=-1.2)
        | sdf.Halfspace(normal=[1, 0], d=-1.2)
        | sdf.Halfspace(normal=[-1, 0], d=-1.2)
    )


def _moving_bar():
    import fastsdf as sdf

    lift = sdf.Param("y0", -1.1) + sdf.Param("u", 1.0) * sdf.t
    with sdf.transform(offset=[0.0, lift]):
        bar = sdf.Box(minc=[-1.15, -0.01], maxc=[1.15, 0.01])
    return _box() | bar


def _piston():
    import fastsdf as sdf

    return sdf.Halfspace(normal=[1, 0], d=-1.0 + sdf.Param("speed", 0.5) * sdf.t) | sdf.Circle(
        center=[0.5, 0.0], radius=0.2
    )


def _tilted_box():
    """A parametric world that does not move (its parameter is set per call)."""
    import fastsdf as sdf

    with sdf.transform(angle=sdf.Param("angle", 0.2)):
        ramp = sdf.Box(minc=[-0.8, -0.05], maxc=[0.8, 0.05])
    return _box() | ramp


def _pruned_scene():
    """Many small boxes folded into a loop over a table: the step prunes it per tile."""
    import fastsdf as sdf

    rng = np.random.default_rng(5)
    f = sdf.Halfspace([0.2, 1], -1.7)
    for _ in range(60):
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)):
            f = f | sdf.Box([-0.05, -0.03], [0.04, 0.06])
    return f | sdf.Circle([0.5, -0.5], 0.2)


def _grid(**kw):
    from fastsdf import GridSDF
    from fastsdf.shapes.scenes import seed_world

    bounds = kw.pop("bounds", [(-2, 2), (-2, 2)])
    return GridSDF(seed_world(), bounds=bounds, samples=[80j, 80j], **kw)


def _band(band=0.1):
    """The seed world on a band grid: ``band=0.1`` is narrower than the particles' largest
    radius (0.1, so they reach the far tiles: the wide free-flight margin), ``(-0.05, 0.15)``
    the band its docs advise for particles (the world's margin)."""
    from fastsdf import NarrowBandGridSDF
    from fastsdf.shapes.scenes import seed_world

    return NarrowBandGridSDF(
        seed_world(), bounds=[(-2, 2), (-2, 2)], band=band, samples=[257j, 257j]
    )


def _advised_band():
    return _band((-0.05, 0.15))


def _grain_box():
    import fastsdf as sdf

    walls = (
        sdf.Halfspace((0.0, 1.0), -0.3)
        | sdf.Halfspace((1.0, 0.0), -0.2)
        | sdf.Halfspace((-1.0, 0.0), -0.2)
    )
    return sdf.GridSDF(walls, bounds=[(-0.3, 0.3), (-0.4, 0.3)], samples=[81j, 81j])


# ---------------------------------------------------------------------------------------------
# Building and running a case with either engine.


class Case:
    """One comparison: ``build(engine)`` makes the simulation (its state set), ``calls`` are the
    step counts of the ``run`` calls, ``settings`` what the engine's defaults leave out (query
    skipping off, a shorter long call)."""

    def __init__(
        self,
        name: str,
        build: Callable[[Any], Any],
        calls: tuple = (15, 15, 15, 15),
        skip: bool = True,
        long_call: int | None = None,
    ) -> None:
        self.name, self.build, self.calls = name, build, calls
        self.skip, self.long_call = skip, long_call


def _particles(
    world_fn,
    n: int,
    params: dict | None = None,
    forces: tuple = ("gravity",),
    spread: float = 1.1,
    invalid: bool = False,
    **kw,
):
    """A builder of ``n`` particles in the world ``world_fn()`` (made once, shared by both
    engines), with the named forces, from the same random state."""
    world = []

    def build(engine):
        if not world:
            world.append(world_fn())
        sim = engine.ParticleSimulation(world[0], n=n, seed=3, **kw)
        for name in forces:
            sim.force_generators.append(_force(engine, name))
        for key, value in (params or {}).items():
            sim.params[key] = value
        rng = np.random.default_rng(1)
        sim.p["x"] = np.c_[rng.uniform(-spread, spread, n), rng.uniform(-0.9, spread, n)]
        sim.p["v"] = rng.normal(scale=3.0, size=(n, 2))
        if "rest_speed" in kw:
            sim.p["v"] = rng.normal(scale=0.3, size=(n, 2))
        if invalid:  # frozen and flagged: a non-finite start, cr and cf out of range
            sim.p["x"][7] = [math.nan, 0.0]
            sim.p["v"][8] = [math.inf, 0.0]
            sim.p["cr"][:40] = 1.5
            sim.p["cf"][n - 3] = -0.1
        return sim

    return build


def _force(engine, name: str):
    """The force ``name`` as ``engine``'s own class (the step fuses only its own)."""
    if name == "gravity":
        return engine.Gravity()
    if name == "drag":
        return engine.Drag(0.2)
    if name == "gust":
        return _gust
    if name == "python":
        return _python_drag
    if name == "field":
        from fastsdf.expr.graph import Symbol, sym_sqrt

        x, y = Symbol("x"), Symbol("y")
        return engine.FieldForce(
            potential=-0.02 / sym_sqrt(x * x + (y + 1.0) * (y + 1.0) + 0.1), per_mass=True
        )
    raise ValueError(name)


def _grains(law: dict, forces: tuple = ("gravity9",)):
    world = []

    def build(engine):
        if not world:
            world.append(_grain_box())
        r = 0.012
        i, j = np.meshgrid(np.arange(14), np.arange(10))
        pos = np.stack(
            [-0.19 + (2 * i.ravel() + 1) * r * 1.1, -0.29 + (2 * j.ravel() + 1) * r * 1.1], 1
        )
        pos = pos + np.random.default_rng(0).uniform(-0.1 * r, 0.1 * r, pos.shape)
        sim = engine.ParticleSimulation(
            world[0], positions=pos, radius=r, contacts=engine.ContactLaw(**law)
        )
        for name in forces:
            sim.force_generators.append(
                engine.Gravity((0.0, -9.81)) if name == "gravity9" else _force(engine, name)
            )
        sim.p["v"] = np.random.default_rng(2).normal(scale=0.05, size=pos.shape)
        return sim

    return build


def cases(n: int) -> list[Case]:
    """Every case, for ``n`` particles (grains: 140)."""
    from fastsdf.shapes.scenes import seed_world

    notrace = {"prevent_tunnelling": False}
    return [
        # exact worlds
        Case("moving bar", _particles(_moving_bar, n, {"u": 6.0, "y0": -1.1})),
        Case("piston", _particles(_piston, n)),
        Case("piston, no tunnelling check", _particles(_piston, n, **notrace)),
        Case("piston, no check, no skipping", _particles(_piston, n, **notrace), skip=False),
        Case("seed world (exact SDF)", _particles(seed_world, n)),
        Case("seed world, no skipping", _particles(seed_world, n), skip=False),
        Case("seed world, invalid particles", _particles(seed_world, n, invalid=True)),
        Case(
            "seed world, invalid particles, plain step",
            _particles(seed_world, n, invalid=True, **notrace),
            skip=False,
        ),
        Case("seed world, plain step", _particles(seed_world, n, **notrace), skip=False),
        Case(
            "seed world, plain step, drag and euler",
            _particles(
                seed_world,
                n,
                forces=("gravity", "drag"),
                integrator="euler",
                collision="notebook",
                **notrace,
            ),
            skip=False,
        ),
        Case("seed world, python force", _particles(seed_world, n, forces=("gravity", "python"))),
        Case(
            "seed world, fused forces",
            _particles(seed_world, n, forces=("gravity", "gust", "field")),
        ),
        Case("pruned scene", _particles(_pruned_scene, n, spread=2.0)),
        Case("parametric world", _particles(_tilted_box, n, {"angle": 0.3})),
        Case("seed world, rest_speed", _particles(seed_world, n, rest_speed=0.1)),
        # grid worlds
        Case("grid stored (block kernel)", _particles(_grid, n)),
        Case("grid stored, invalid particles", _particles(_grid, n, invalid=True)),
        Case(
            "grid stored, invalid particles, no skipping",
            _particles(_grid, n, invalid=True, **notrace),
            skip=False,
        ),
        Case("grid stored, no skipping", _particles(_grid, n), skip=False),
        Case("grid stored, no tunnelling check", _particles(_grid, n, **notrace)),
        Case("grid stored, plain step", _particles(_grid, n, **notrace), skip=False),
        Case(
            "grid stored, fused forces and drag",
            _particles(_grid, n, forces=("gravity", "gust", "field", "drag")),
        ),
        Case(
            "grid stored, fused forces, no skipping",
            _particles(_grid, n, forces=("gravity", "gust", "field", "drag")),
            skip=False,
        ),
        Case(
            "grid stored, euler and notebook collision",
            _particles(_grid, n, integrator="euler", collision="notebook"),
        ),
        Case("grid stored, mode nearest", _particles(lambda: _grid(mode="nearest"), n, spread=2.4)),
        Case("grid stored float32", _particles(lambda: _grid(dtype=np.float32), n)),
        Case(
            "grid stored, particles leave the grid",
            _particles(lambda: _grid(bounds=[(-1, 1), (-1, 1)]), n, spread=1.5),
            calls=(3, 15, 1, 25, 16),
        ),
        Case(
            "grid stored, leave the grid, no skipping",
            _particles(lambda: _grid(bounds=[(-1, 1), (-1, 1)]), n, spread=1.5, **notrace),
            skip=False,
        ),
        Case("grid stored, float32 state", _particles(_grid, n, dtype=np.float32)),
        Case("grid stored, rest_speed", _particles(_grid, n, rest_speed=0.1)),
        Case("grid stored, python force", _particles(_grid, n, forces=("gravity", "python"))),
        Case("grid stored, threads", _particles(_grid, 5000, block=300)),
        Case(
            "grid stored, parallel entry point",
            _particles(_grid, 5000, block=300),
            long_call=1000,
        ),
        Case(
            "grid stored, parallel entry point, no skipping",
            _particles(_grid, 5000, block=300, **notrace),
            skip=False,
            long_call=1000,
        ),
        Case("grid fd", _particles(lambda: _grid(gradient="fd"), n)),
        Case(
            "grid fd, plain step",
            _particles(lambda: _grid(gradient="fd"), n, **notrace),
            skip=False,
        ),
        Case(
            "seed world, threads, parallel entry point",
            _particles(seed_world, 5000, block=300),
            long_call=1000,
        ),
        Case(
            "seed world, plain step, parallel entry point",
            _particles(seed_world, 5000, block=300, **notrace),
            skip=False,
            long_call=1000,
        ),
        # band worlds
        Case("band grid", _particles(_band, n)),
        Case("band grid, band past the radii", _particles(_advised_band, n)),
        Case("band grid, plain step", _particles(_band, n, **notrace), skip=False),
        # grains
        Case("grains", _grains({}), calls=(2, 2, 2)),
        Case(
            "grains with history, rolling friction and fused forces",
            _grains(
                {"history": True, "rolling_friction": 0.3}, forces=("gravity9", "drag", "gust")
            ),
            calls=(2, 2, 2),
        ),
    ]


def _set_skip(sim: Any, skip: bool) -> None:
    """Turn query skipping off (as for a world without a known Lipschitz bound)."""
    if skip:
        return
    if "_skip" in vars(sim):  # (an earlier version: the simulation's own)
        sim._skip = False
    else:
        sim.engine.skip = False


def _set_long_call(engine: Any, value: int | None) -> list:
    """Set ``LONG_CALL`` in the engine's modules that define it; returns what to restore."""
    if value is None:
        return []
    saved = []
    prefix = engine.__name__ + "."
    for name, module in list(sys.modules.items()):
        if name.startswith(prefix) and hasattr(module, "LONG_CALL"):
            saved.append((module, module.LONG_CALL))
            module.LONG_CALL = value
    return saved


def run_case(engine: Any, case: Case) -> tuple:
    """The arrays, clock and errors after the case's calls with ``engine``."""
    sim = case.build(engine)
    _set_skip(sim, case.skip)
    saved = _set_long_call(engine, case.long_call)
    errors = []
    try:
        for steps in case.calls:
            try:
                sim.run(steps)
            except ValueError as exc:
                errors.append(str(exc))
    finally:
        for module, value in saved:
            module.LONG_CALL = value
    fields = [f for f in ("x", "v", "omega") if f in sim.p]
    return [np.array(sim.p[f]) for f in fields], sim.t, errors


def same_bits(a: tuple, b: tuple) -> bool:
    """Whether two results of :func:`run_case` agree bit for bit."""
    if len(a[0]) != len(b[0]) or a[1] != b[1] or a[2] != b[2]:
        return False
    for p, q in zip(a[0], b[0], strict=True):
        if p.dtype != q.dtype or p.shape != q.shape:
            return False
        if not np.array_equal(p.view(np.uint8), q.view(np.uint8)):
            return False
    return True


def _whole_baseline(args: argparse.Namespace, argv: list | None) -> dict:
    """The cases' results with the whole package of ``args.rev``, run in another process."""
    from .ab import _export

    with tempfile.TemporaryDirectory(prefix="fastsdf_bits_") as tmp:
        tree = _export(args.rev, tmp)
        out = os.path.join(tmp, "baseline.pkl")
        rest = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--whole"]
        env = dict(os.environ, PYTHONPATH=tree, MPLBACKEND="Agg")
        cmd = [sys.executable, os.path.abspath(__file__), *rest, "--save", out]
        subprocess.run(cmd, env=env, cwd=tree, check=True)
        with open(out, "rb") as fh:
            return pickle.load(fh)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.step_bits",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rev", help="git revision of the baseline (required unless --list)")
    parser.add_argument("--particles", type=int, default=3000)
    parser.add_argument("--only", help="run the cases whose name contains this text")
    parser.add_argument("--list", action="store_true", help="print the cases' names and exit")
    parser.add_argument(
        "--whole", action="store_true", help="the baseline is the revision's whole package"
    )
    parser.add_argument("--save", help=argparse.SUPPRESS)  # (--whole's baseline process)
    args = parser.parse_args(argv)
    chosen = [c for c in cases(args.particles) if not args.only or args.only in c.name]
    if args.list:
        print("\n".join(c.name for c in chosen))
        return 0
    import fastsdf.particles as phys

    if args.save:
        with open(args.save, "wb") as fh:
            pickle.dump({c.name: run_case(phys, c) for c in chosen}, fh)
        return 0
    if not args.rev:
        parser.error("--rev is required")
    baseline = _whole_baseline(args, argv) if args.whole else None
    if baseline is None:
        from .step_ab import _load_base

        base = _load_base(args.rev)
    failed = []
    for case in chosen:
        a = baseline[case.name] if baseline is not None else run_case(base, case)
        b = run_case(phys, case)
        same = same_bits(a, b)
        if not same:
            failed.append(case.name)
        steps = sum(case.calls)
        print(
            f"{case.name}: {len(a[0][0])} particles, {steps} steps in {len(case.calls)} calls"
            f"{f', {len(a[2])} error(s)' if a[2] else ''}: same bits {same}",
            flush=True,
        )
    print("all bit-identical" if not failed else f"DIFFERENCES in {len(failed)}: {failed}")
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
