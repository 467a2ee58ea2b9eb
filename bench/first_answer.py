"""A new scene's first answer on a warm installation, against another revision, in one run.

    python -m bench.first_answer --rev 9af86bd            # 20, 200, 2000 boxes, 3 rounds
    python -m bench.first_answer --rev HEAD~3 --sizes 20 --rounds 5
    python -m bench.first_answer --rev 9af86bd --new-structure   # no structure seen before

The scene is the notebook's world of smoothly joined rotated boxes (``box_world(n, seed)``)
with a seed never used before, so its kernel is in no cache: each measurement is a fresh
process that builds it and times the first ``f(x, y, compute_gradient=True)`` on 1e5 points,
from the built scene to the answer. The installation is warm: a first, unmeasured process per
side and size compiles what every scene shares (the drivers, and on revisions that have one
the tape interpreter) into that side's caches. Each side runs its default call; a baseline
that has the ``'tape'`` backend is also timed with ``backend='kernel'``. Rounds alternate the
sides, so both see the same machine load; the table gives the median of each.

Scenes that differ only in their numbers share their compiled block kernels, so a new seed of
a size measured before loads them from the cache. ``--new-structure`` measures scenes of a
structure never compiled before: round ``r`` of size ``n`` takes ``n + 2 r + 2`` boxes (the
warm-up ``n + 1``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from bench.ab import REPO, _export

_SCRIPT = """
import json, sys, time
import numpy as np
import fastsdf as sdf
from fastsdf.shapes.scenes import box_world
n, seed, backend = {n}, {seed}, {backend!r}
x, y = np.random.default_rng(1).uniform(-2, 2, (2, 100_000))
f = box_world(n, seed)
t0 = time.perf_counter()
if backend:
    f(x, y, compute_gradient=True, backend=backend)
else:
    f(x, y, compute_gradient=True)
print(json.dumps({{"s": time.perf_counter() - t0}}))
"""


def _time(tree: str, cache: str, n: int, seed: int, backend: str = "") -> float:
    env = dict(os.environ, PYTHONPATH=tree, FASTSDF_CACHE_DIR=cache, MPLBACKEND="Agg")
    code = _SCRIPT.format(n=n, seed=seed, backend=backend)
    res = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True, timeout=900
    )
    if res.returncode:
        raise RuntimeError(f"failed in {tree}:\n{res.stderr[-2000:]}")
    return float(json.loads(res.stdout.strip().splitlines()[-1])["s"])


def _has_tape(tree: str) -> bool:
    return os.path.exists(os.path.join(tree, "fastsdf", "backends", "vm.py"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.first_answer",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rev", required=True, help="git revision of the baseline")
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 200, 2000])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--new-structure",
        action="store_true",
        help="each measured scene has a box count never compiled before",
    )
    args = parser.parse_args(argv)
    seed = int.from_bytes(os.urandom(3), "little") * 1000
    with tempfile.TemporaryDirectory(prefix="fastsdf_first_") as tmp:
        base = _export(args.rev, tmp)
        paths = [("baseline", base, "")]
        if _has_tape(base):
            paths += [("baseline, kernel", base, "kernel")]
        paths += [("this", REPO, "")]
        caches = {tree: os.path.join(tmp, f"cache{i}") for i, tree in enumerate({base, REPO})}
        times: dict = {(p, n): [] for p, *_ in paths for n in args.sizes}
        load0 = os.getloadavg()
        new = args.new_structure
        for n in args.sizes:  # the warm installation: what every scene shares, compiled once
            for tree in caches:
                _time(tree, caches[tree], n + new, seed, "" if not _has_tape(tree) else "tape")
                _time(tree, caches[tree], n + new, seed + 1)
        for r in range(args.rounds):
            for n in args.sizes:
                count = n + 2 * r + 2 if new else n
                for name, tree, backend in paths:
                    seed += 2
                    times[name, n].append(_time(tree, caches[tree], count, seed, backend))
        load1 = os.getloadavg()
    print(
        f"First answer of a new scene{' of a new structure' if args.new_structure else ''}, "
        f"1e5 points, value and gradient: this checkout against "
        f"{args.rev}; median of {args.rounds} rounds (seconds). Load average (1, 5, 15 min) "
        f"before {load0[0]:.2f}, {load0[1]:.2f}, {load0[2]:.2f}; after {load1[0]:.2f}, "
        f"{load1[1]:.2f}, {load1[2]:.2f}.\n"
    )
    print("| boxes | " + " | ".join(p for p, *_ in paths) + " |")
    print("| --- |" + " --- |" * len(paths))
    for n in args.sizes:
        cells = [f"{sorted(times[p, n])[len(times[p, n]) // 2]:.2f}" for p, *_ in paths]
        print(f"| {n} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
