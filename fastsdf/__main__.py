"""Command line: ``python -m fastsdf demo [options]`` (see ``--help``)."""

from __future__ import annotations

import argparse
import sys


def _positive_int(text: str) -> int:
    try:
        value = int(float(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0 or value != float(text):
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m fastsdf",
        description="fastsdf: 2D signed distance functions compiled to parallel machine code.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser(
        "demo", help="simulate particles in the notebook's world; write an animation and a PNG",
        description="Build the notebook's final world (funnel + 20 random boxes, cell 13), sample "
                    "it into a GridSDF, drop particles into it under gravity, and write an "
                    "animation and a PNG of the last frame. Prints throughput and grid error.")
    demo.add_argument("--particles", type=_positive_int, default=1_000_000,
                      help="number of particles (default 1000000; 1e6 is accepted)")
    demo.add_argument("--steps", type=_positive_int, default=300,
                      help="time steps of 1/30 s (default 300)")
    demo.add_argument("--grid", type=_positive_int, default=400,
                      help="GridSDF samples per axis (default 400)")
    demo.add_argument("--exact", action="store_true",
                      help="query the exact compiled SDF instead of a GridSDF")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--frames", type=_positive_int, default=60,
                      help="animation frames (default 60)")
    demo.add_argument("--no-animation", action="store_true", help="write only the last frame")
    demo.add_argument("--out", default="demo-out", help="output folder (default ./demo-out)")
    demo.add_argument("--workers", type=_positive_int, default=None,
                      help="run the particles on a local Dask cluster of this many worker "
                           "processes (needs the 'distributed' extra)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "demo":
        if args.grid < 2:
            parser.error(f"--grid must be at least 2, got {args.grid}")
        from .demo import run_demo, summary
        if args.workers:
            from .distributed import run_demo
        res = run_demo(particles=args.particles, steps=args.steps, grid=args.grid,
                       exact=args.exact, seed=args.seed, out=args.out, frames=args.frames,
                       animate=not args.no_animation,
                       **({"workers": args.workers} if args.workers else {}))
        print(summary(res))
        return 0
    return 2  # pragma: no cover - argparse rejects unknown commands


if __name__ == "__main__":
    sys.exit(main())
