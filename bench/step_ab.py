"""A/B of the particle step: the simulation and kernels of another revision of fastsdf against the
current ones, with Taichi's fused kernel, side by side in one process.

    python -m bench.step_ab --rev main~3                 # settled phase, gravity
    python -m bench.step_ab --rev HEAD~1 --phase settled fall --force field
    python -m bench.step_ab --rev f8cd325 --peer-work --particles 200000

The baseline is the revision's particle engine (``fastsdf/particles.py`` with
``fastsdf/_step.py``, or the ``fastsdf/particles/`` package) loaded beside the current one as
``fastsdf._ab_base`` (the rest of fastsdf, grids included, is the current one). Both start from
the same saved state of the notebook scenario (1,000,000 particles by default, the seed world's
400x400 GridSDF, see ``bench/bench_particles.py``) and run ``run(20)`` in turns, repeat after
repeat; the output gives median (best) rates, the ratios, and whether the two versions'
results are bit-identical. ``--peer-work``: query skipping and the tunnelling check off (the
peers' work); ``--force wind|field``: the bench's fused user forces.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numba
import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.step_ab",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--rev", required=True, help="git revision whose particle engine is the baseline"
    )
    parser.add_argument(
        "--phase", nargs="+", default=["settled"], choices=["fall", "impact", "settled"]
    )
    parser.add_argument("--particles", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--peer-work", action="store_true")
    parser.add_argument("--force", choices=["wind", "field"])
    args = parser.parse_args(argv)

    from fastsdf import GridSDF
    from fastsdf.shapes.scenes import seed_world

    from . import peers
    from .bench_particles import Fused, Peer, _attractor, _states, cell, compare, wind

    base = _load_base(args.rev)
    grid = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    states = _states(grid, args.particles)
    kw = dict(skip=False, prevent_tunnelling=False) if args.peer_work else {}
    forces = {"wind": [wind], "field": [_attractor()], None: []}[args.force]
    ti, ti_err = peers.taichi_particles(grid, numba.get_num_threads())
    for phase in args.phase:
        state = states[phase]
        variants = [
            _BaseFused(base, grid, state, 20, forces, **kw),
            Fused(grid, state, 20, forces=forces, **kw),
        ]
        for v in variants:
            v.prepare()
            v()
        same = all(np.array_equal(variants[0].sim.p[f], variants[1].sim.p[f]) for f in ("x", "v"))
        if ti is not None:
            variants.append(Peer(ti, state, 20))
        load = os.getloadavg()[0]
        r = compare(variants, args.repeats)
        line = (
            f"{phase}: baseline {cell(r[0])}, current {cell(r[1])}, current / baseline "
            f"{r[1][0] / r[0][0]:.3f}, bit-identical: {same}"
        )
        if ti is not None:
            line += (
                f"; Taichi {cell(r[2])}, baseline / Taichi {r[0][0] / r[2][0]:.2f}, "
                f"current / Taichi {r[1][0] / r[2][0]:.2f}"
            )
        else:
            line += f"; Taichi skipped ({ti_err})"
        print(line + f" (load average {load:.1f})")
    return 0


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], check=True, capture_output=True, text=True).stdout


def _load_base(rev: str):
    """The particle engine of ``rev`` as the module ``fastsdf._ab_base``: its imports of its own
    modules (``fastsdf.particles.*``) are rewritten to name the copy, its imports of the rest of
    fastsdf resolve to the current package."""
    import importlib.util
    import tempfile

    import fastsdf

    root = tempfile.mkdtemp(prefix="fastsdf_ab_")
    name = "fastsdf._ab_base"
    files = _git("ls-tree", "-r", "--name-only", rev, "fastsdf/").split()
    if "fastsdf/particles.py" in files:
        # the flat layout: particles.py and the kernel module _step.py beside it
        step = _git("show", f"{rev}:fastsdf/_step.py")
        src = _git("show", f"{rev}:fastsdf/particles.py")
        src = src.replace("from . import _step\n", "from . import _ab_base_step as _step\n")
        src = src.replace("from ._step import", "from ._ab_base_step import")
        paths = {
            "fastsdf._ab_base_step": os.path.join(root, "_ab_base_step.py"),
            name: os.path.join(root, "_ab_base.py"),
        }
        for mod, text in (("fastsdf._ab_base_step", step), (name, src)):
            with open(paths[mod], "w") as fh:
                fh.write(text)
            spec = importlib.util.spec_from_file_location(mod, paths[mod])
            module = importlib.util.module_from_spec(spec)
            sys.modules[mod] = module
            spec.loader.exec_module(module)
        return sys.modules[name]
    pkg = os.path.join(root, "_ab_base")
    for path in files:
        if path.startswith("fastsdf/particles/") and path.endswith(".py"):
            out = os.path.join(pkg, path[len("fastsdf/particles/") :])
            os.makedirs(os.path.dirname(out), exist_ok=True)
            with open(out, "w") as fh:
                # its absolute imports of its own modules name the copy, not the current ones
                fh.write(_git("show", f"{rev}:{path}").replace("fastsdf.particles", name))
    spec = importlib.util.spec_from_file_location(
        name, os.path.join(pkg, "__init__.py"), submodule_search_locations=[pkg]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    fastsdf._ab_base = module
    spec.loader.exec_module(module)
    return module


class _BaseFused:
    """``bench_particles.Fused`` with the baseline's simulation (its own state class)."""

    def __init__(self, base, f, state, steps, forces, skip=True, **kw):
        self.base = base
        self.sim = base.ParticleSimulation(f, n=len(state), seed=0, **kw)
        self.sim.force_generators += [base.Gravity()] + [self._own(g) for g in forces]
        self.sim._skip = self.sim._skip and skip
        self.state, self.steps, self.work = state, steps, len(state) * steps
        self.prepare()
        self.sim.run(1)  # compile or load from the cache

    def _own(self, force):
        """A FieldForce as the baseline's class (it fuses only its own)."""
        parts = getattr(force, "parts", None)
        if parts is None:
            return force
        if force.potential:
            return self.base.FieldForce(potential=parts[0], per_mass=force.per_mass)
        return self.base.FieldForce(*parts, per_mass=force.per_mass)

    def prepare(self):
        p = self.base.Particles(len(self.state), self.state.dtype)
        for name in p.FIELDS:
            p[name] = self.state[name]
        self.sim.p = p

    def __call__(self):
        self.sim.run(self.steps)


if __name__ == "__main__":
    sys.exit(main())
