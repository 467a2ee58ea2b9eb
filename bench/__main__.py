"""Run the benchmark suite and write bench/RESULTS.md.

    python -m bench                 # everything (make bench)
    python -m bench --quick         # reduced sizes, a smoke run (make bench-quick)
    python -m bench --only core     # one or more sections

Each section writes bench/results/<section>.md (and PNG plots in bench/); RESULTS.md is
assembled from all section files present, so a partial run keeps the other sections.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

from .common import HERE, machine_info

# (name, module, what it measures); each module has run(quick: bool) -> markdown str.
SECTIONS = [
    ("core", "bench.bench_core", "exact compiled SDFs: throughput and compile time"),
    ("grid", "bench.bench_grid", "GridSDF: build, memory, query speed and error vs resolution"),
    (
        "particles",
        "bench.bench_particles",
        "fused particle step vs the notebook's NumPy step, memory floor, tunnelling check, float32",
    ),
    (
        "params",
        "bench.bench_params",
        "runtime parameters: cost against constants; a 300-frame moving scene, compiles and speed",
    ),
    (
        "prune",
        "bench.bench_prune",
        "pruning per tile: hard unions of many shapes, exponential box worlds (tol), seed world",
    ),
    (
        "band",
        "bench.bench_band",
        "narrow-band grids: memory, error, query speed; particles' speed against error",
    ),
    (
        "distributed",
        "bench.bench_distributed",
        "particles sharded over Dask workers: 1 vs 2 processes, per-call overhead, client memory",
    ),
    (
        "build",
        "bench.bench_build",
        "building scenes: the modelling DSL, code generation and pruning plan per size",
    ),
    (
        "instant",
        "bench.bench_instant",
        "a new scene's first answer through the kernel, NumPy and the default call",
    ),
    (
        "simd",
        "bench.bench_simd",
        "SIMD block kernels and vectorizable exp/log vs the kernels before, math.*, Taichi",
    ),
    (
        "video",
        "bench.bench_video",
        "video frames of 1e6 particles at 720p: the compiled frame writer vs save_animation",
    ),
    (
        "io",
        "bench.bench_io",
        "trajectory files: recording 1e6 positions every 10 steps against the run alone",
    ),
    (
        "geometry",
        "bench.bench_geometry",
        "distance transform of a mask against scipy; mask and image grids' error tables",
    ),
    (
        "granular",
        "bench.bench_granular",
        "granular DEM: a dense bed in full contact against LAMMPS gran/hooke, same run",
    ),
]

HEADER = """# fastsdf benchmark results

Produced by `python -m bench` (`make bench`); each section states the command that produced it.
Speeds are medians of repeats after warm-up, each measured side by side with its baseline in the
same process; spreads are (max - min) / median over the repeats.

"""


def assemble() -> str:
    parts = [HEADER]
    # The sections, then the A/B of whole workloads against an earlier revision (bench.ab).
    for name in [s[0] for s in SECTIONS] + ["ab"]:
        path = os.path.join(HERE, "results", f"{name}.md")
        if os.path.exists(path):
            with open(path, encoding="utf-8") as fh:
                parts.append(fh.read().rstrip() + "\n\n")
    return "".join(parts)


def main(argv=None) -> int:
    names = [s[0] for s in SECTIONS]
    parser = argparse.ArgumentParser(
        prog="python -m bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quick", action="store_true", help="reduced sizes (a smoke run)")
    parser.add_argument("--only", nargs="+", choices=names, help="run only these sections")
    parser.add_argument("--no-write", action="store_true", help="print, do not write RESULTS.md")
    args = parser.parse_args(argv)
    chosen = [s for s in SECTIONS if not args.only or s[0] in args.only]
    info = machine_info()
    print(
        f"fastsdf bench: {info['cores']} cores ({info['cpu']}), numba {info['numba']}, "
        f"{info['numba_threads']} threads{' (quick)' if args.quick else ''}",
        file=sys.stderr,
    )
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    for name, module, what in chosen:
        t0 = time.perf_counter()
        print(f"== {name}: {what}", file=sys.stderr)
        text = importlib.import_module(module).run(quick=args.quick)
        print(text)
        if not args.no_write and not args.quick:
            with open(os.path.join(HERE, "results", f"{name}.md"), "w", encoding="utf-8") as fh:
                fh.write(text)
        print(f"== {name} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if not args.no_write and not args.quick:
        with open(os.path.join(HERE, "RESULTS.md"), "w", encoding="utf-8") as fh:
            fh.write(assemble())
        print(f"wrote {os.path.join(HERE, 'RESULTS.md')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
