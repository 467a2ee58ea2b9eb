"""A/B of the particle step: the kernel built from another version of ``fastsdf/_step.py``
against the current one, with Taichi's fused kernel, side by side in one process.

    python -m bench.step_ab --rev main~3                 # settled phase, gravity
    python -m bench.step_ab --rev HEAD~1 --phase settled fall --force field
    python -m bench.step_ab --file /tmp/my_step.py --peer-work

Both kernels start from the same saved state of the notebook scenario (1,000,000 particles by
default, the seed world's 400x400 GridSDF, see ``bench/bench_particles.py``) and run ``run(20)``
in turns, repeat after repeat; the output gives median (best) rates, the ratios, and whether
the two versions' results are bit-identical. ``--peer-work``: query skipping and the tunnelling
check off (the peers' work); ``--force wind|field``: the bench's fused user forces.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numba
import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.step_ab", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--rev", help="git revision whose fastsdf/_step.py is the baseline")
    src.add_argument("--file", help="a file holding the baseline _step.py source")
    parser.add_argument("--phase", nargs="+", default=["settled"],
                        choices=["fall", "impact", "settled"])
    parser.add_argument("--particles", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--peer-work", action="store_true")
    parser.add_argument("--force", choices=["wind", "field"])
    args = parser.parse_args(argv)

    import fastsdf.particles as phys
    from fastsdf import GridSDF
    from fastsdf.shapes.scenes import seed_world

    from . import peers
    from .bench_particles import Fused, Peer, _attractor, _states, cell, compare, wind

    if args.rev:
        old = subprocess.run(["git", "show", f"{args.rev}:fastsdf/_step.py"], check=True,
                             capture_output=True, text=True).stdout
    else:
        with open(args.file) as fh:
            old = fh.read()
    new = phys._STEP_SOURCE
    grid = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    states = _states(grid, args.particles)
    kw = dict(skip=False, prevent_tunnelling=False) if args.peer_work else {}
    forces = {"wind": [wind], "field": [_attractor()], None: []}[args.force]
    ti, ti_err = peers.taichi_particles(grid, numba.get_num_threads())
    for phase in args.phase:
        state = states[phase]
        variants = []
        for source in (old, new):
            phys._STEP_SOURCE = source      # the kernel module is generated from this text
            variants.append(Fused(grid, state, 20, forces=forces, **kw))
        phys._STEP_SOURCE = new
        for v in variants:
            v.prepare()
            v()
        same = all(np.array_equal(variants[0].sim.p[f], variants[1].sim.p[f])
                   for f in ("x", "v"))
        if ti is not None:
            variants.append(Peer(ti, state, 20))
        load = os.getloadavg()[0]
        r = compare(variants, args.repeats)
        line = (f"{phase}: baseline {cell(r[0])}, current {cell(r[1])}, current / baseline "
                f"{r[1][0] / r[0][0]:.3f}, bit-identical: {same}")
        if ti is not None:
            line += (f"; Taichi {cell(r[2])}, baseline / Taichi {r[0][0] / r[2][0]:.2f}, "
                     f"current / Taichi {r[1][0] / r[2][0]:.2f}")
        else:
            line += f"; Taichi skipped ({ti_err})"
        print(line + f" (load average {load:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
