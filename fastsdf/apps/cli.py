"""The ``fastsdf`` command: ``fastsdf demo [options]``, ``fastsdf --version`` (see ``--help``).

Installed as the ``fastsdf`` console script; ``python -m fastsdf`` is the same. Every error is
one line on stderr (``fastsdf demo: error: ...``) with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from fastsdf.expr.validate import shown

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line (no usage block) and exit with 2."""

    _demo: argparse.ArgumentParser  # the demo subcommand's parser (set by build_parser)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _count(text: str, low: int) -> int:
    """An integer >= ``low``; ``1e6`` is accepted (an integral float)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an integer >= {low}, got {shown(text)}"
        ) from None
    if not value.is_integer() or value < low:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {shown(text)}")
    return int(value)


def _positive_int(text: str) -> int:
    return _count(text, 1)


def _grid_size(text: str) -> int:
    return _count(text, 2)


def build_parser() -> argparse.ArgumentParser:
    """The command line parser (``fastsdf`` and its ``demo`` subcommand)."""
    from fastsdf.apps.demo import DEFAULT_FPS, DEFAULT_FRAMES, WORLDS
    from fastsdf.version import __version__

    parser = _Parser(
        prog="fastsdf",
        description="fastsdf: 2D signed distance functions compiled to parallel machine code, "
        "and particles colliding with them.",
    )
    parser.add_argument("--version", action="version", version=f"fastsdf {__version__}")
    sub = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", parser_class=_Parser
    )
    demo = sub.add_parser(
        "demo",
        help="simulate particles in one of the notebook's worlds; write a video and a PNG",
        description="Build one of the notebook's worlds, sample it into a GridSDF (or query it "
        "exactly), spawn particles in free space, let them fall under gravity with "
        "the fused compiled step, and write a video and a PNG of the last frame. "
        "Prints what it simulated, the rate, and why the rate is what it is.",
    )
    demo.add_argument(
        "--scene",
        choices=("particles", "sand"),
        default="particles",
        help="'particles': particles that meet only the world (the default); 'sand': "
        "grains that also collide with each other pour into the world and heap up "
        "(writes sand.mp4 and sand_last_frame.png)",
    )
    demo.add_argument(
        "--world",
        choices=sorted(WORLDS),
        default="seed",
        help="'seed': the funnel and a cut disc (cell 21), the scene of the "
        "headline figures (README, docs/performance.md); 'boxes': the notebook's final world, the "
        "funnel and 20 random boxes (cell 13), slower: its exact SDF, which "
        "answers queries outside the grid, costs over 100 grid queries "
        "(default: seed)",
    )
    demo.add_argument(
        "--mode",
        choices=("exact", "nearest"),
        default="exact",
        help="what the grid answers outside its bounds: 'exact' asks the exact "
        "compiled SDF (right distances, slower), 'nearest' clamps to the "
        "grid's edge like the notebook (default: exact)",
    )
    demo.add_argument(
        "--particles",
        type=_positive_int,
        default=None,
        help="number of particles (default 1000000, for --scene sand 2000; 1e6 is accepted)",
    )
    demo.add_argument(
        "--steps",
        type=_positive_int,
        default=None,
        help="time steps of 1/30 s (default 300, for --scene sand 60)",
    )
    demo.add_argument(
        "--grid", type=_grid_size, default=400, help="GridSDF samples per axis, >= 2 (default 400)"
    )
    demo.add_argument(
        "--exact", action="store_true", help="query the exact compiled SDF instead of a GridSDF"
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument(
        "--frames",
        type=_positive_int,
        default=None,
        help=f"video frames, at most --steps (default {DEFAULT_FRAMES}, or --steps if fewer)",
    )
    demo.add_argument(
        "--fps",
        type=_positive_int,
        default=DEFAULT_FPS,
        help=f"video frames per second (default {DEFAULT_FPS})",
    )
    demo.add_argument(
        "--no-history",
        action="store_true",
        help="--scene sand: grains collide by the history-free ContactLaw() (no static "
        "friction, no rolling resistance: the heap spreads flat) instead of "
        "ContactLaw(history=True, rolling_friction=0.3), which keeps a slope",
    )
    demo.add_argument("--no-animation", action="store_true", help="write only the last frame")
    demo.add_argument("--out", default="demo-out", help="output folder (default ./demo-out)")
    demo.add_argument(
        "--workers",
        type=_positive_int,
        default=None,
        help="run the particles on a local Dask cluster of this many worker "
        "processes (needs the 'distributed' extra)",
    )
    parser._demo = demo  # for errors found after parsing (they name the demo's usage)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status (0,
    or 2 after a one-line error)."""
    parser = build_parser()
    assert isinstance(parser, _Parser)
    args = parser.parse_args(argv)
    if args.command == "demo":
        demo = parser._demo
        from fastsdf.apps.demo import DEFAULT_FRAMES, SAND_GRAINS, SAND_STEPS

        sand = args.scene == "sand"
        if args.particles is None:
            args.particles = SAND_GRAINS if sand else 1_000_000
        if args.steps is None:
            args.steps = SAND_STEPS if sand else 300
        if args.frames is None:
            args.frames = min(DEFAULT_FRAMES, args.steps)
        if sand and args.workers:
            demo.error(
                "--workers shards non-interacting particles; grains that collide "
                "(--scene sand) would need a halo exchange between shards: run it without "
                "--workers"
            )
        if args.no_history and not sand:
            demo.error(
                "--no-history chooses the grains' contact law: it applies to --scene sand only"
            )
        if args.frames > args.steps and not args.no_animation:
            demo.error(
                f"--frames {args.frames} is more than --steps {args.steps} (every frame "
                f"advances at least one step)"
            )
        from fastsdf.apps.demo import check_output_dir, run_demo, summary

        extra = {}
        runner: Callable[..., Any] = run_demo
        if args.workers:
            from fastsdf.apps.distributed import run_demo as run_distributed_demo

            runner = run_distributed_demo
            extra["workers"] = args.workers
        try:
            check_output_dir(args.out)
        except OSError as exc:
            demo.error(f"--out {args.out!r} is not a writable folder: {exc.strerror or exc}")
        # Said at once: the imports and the first compiles that follow take seconds.
        sys.stderr.write(
            f"fastsdf demo: {args.particles:,} {'grains' if sand else 'particles'}, "
            f"{args.steps} steps in the {args.world} world, writing to {args.out}/ ...\n"
        )
        sys.stderr.flush()
        common = dict(
            steps=args.steps,
            grid=args.grid,
            exact=args.exact,
            seed=args.seed,
            out=args.out,
            frames=args.frames,
            fps=args.fps,
            world=args.world,
            animate=not args.no_animation,
        )
        try:
            if sand:
                from fastsdf.apps.demo import SAND_ROLLING_FRICTION, run_sand_demo, sand_summary

                rolling = 0.0 if args.no_history else SAND_ROLLING_FRICTION
                print(
                    sand_summary(
                        run_sand_demo(
                            grains=args.particles,
                            history=not args.no_history,
                            rolling_friction=rolling,
                            **common,
                        )
                    )
                )
                return 0
            res = runner(particles=args.particles, mode=args.mode, **common, **extra)
        except OSError as exc:
            demo.error(f"could not write to --out {args.out!r}: {exc.strerror or exc}")
        print(summary(res))
        if not args.workers:
            from fastsdf.apps.demo import warm_readme_kernels

            warm_readme_kernels()
        return 0
    return 2  # pragma: no cover - argparse rejects unknown commands


if __name__ == "__main__":
    sys.exit(main())
