"""Command line: ``python -m fastsdf demo``."""

from __future__ import annotations

import argparse
import sys
import time


def _demo(args) -> int:
    import numpy as np

    from .scenes import box_world, seed_world

    rng = np.random.default_rng(args.seed)
    xs = rng.uniform(-2, 2, args.points)
    ys = rng.uniform(-2, 2, args.points)
    for name, build in (("seed world (notebook cell 21)", seed_world),
                        ("20-box world (notebook cell 13)", box_world)):
        f = build()
        t0 = time.perf_counter()
        f(xs[:2], ys[:2], compute_gradient=True)
        f(xs, ys, compute_gradient=True)
        ready = time.perf_counter() - t0
        t0 = time.perf_counter()
        d, _ = f(xs, ys, compute_gradient=True)
        dt = time.perf_counter() - t0
        print(f"{name}: compile + first call {ready:.2f} s; value + gradient at "
              f"{args.points:,} points: {dt * 1e3:.1f} ms = {args.points / dt / 1e6:.1f} M points/s; "
              f"{np.mean(d < 0):.1%} of points inside")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fastsdf",
                                     description="fastsdf: compiled 2D signed distance functions.")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="evaluate the notebook's worlds and print throughput")
    demo.add_argument("--points", type=int, default=1_000_000, help="query points (default 1e6)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    args = parser.parse_args(argv)
    if args.command == "demo":
        if args.points <= 0:
            parser.error(f"--points must be positive, got {args.points}")
        return _demo(args)
    return 2  # pragma: no cover - argparse rejects unknown commands


if __name__ == "__main__":
    sys.exit(main())
