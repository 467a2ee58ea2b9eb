"""Where compile time goes, per scene: graph build, code generation, numba (typing, lowering)
and LLVM; or print a scene's generated source.

    python -m bench.profile_compile                  # table for the standard scenes
    python -m bench.profile_compile --scene box20    # one scene
    python -m bench.profile_compile --source seed    # print the generated per-point code

Runs in this process with a private, empty kernel cache, so every number is a cold compile.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

SCENES = {
    "circle": ("one circle", lambda sdf, sc: sdf.Circle([0.1, 0.2], 0.5)),
    "seed": ("seed world (cell 21)", lambda sdf, sc: sc.seed_world()),
    "box20": ("20-box world (cell 13)", lambda sdf, sc: sc.box_world(20)),
    "box200": ("200-primitive world", lambda sdf, sc: sc.box_world(197)),
    "box1000": ("1000-primitive world", lambda sdf, sc: sc.box_world(997)),
    "mixed50": ("mixed ops, 50 primitives", lambda sdf, sc: _mixed(sdf, 50)),
    "mixed200": ("mixed ops, 200 primitives", lambda sdf, sc: _mixed(sdf, 200)),
    "mixed2000": ("mixed ops, 2000 primitives", lambda sdf, sc: _mixed(sdf, 2000)),
}


def _mixed(sdf, n):
    """bench_core's scene without repeated structure next to each other (the same draws)."""
    from fastsdf.shapes.scenes import mixed_scene

    return mixed_scene(n)


def _timers(dispatcher):
    """numba's own compile timers of the (single) compiled signature, in seconds."""
    total = {"compiler_lock": 0.0, "llvm_lock": 0.0}
    for sig in dispatcher.signatures:
        timers = dispatcher.get_metadata(sig).get("timers", {})
        for key in total:
            total[key] += timers.get(key, 0.0)
    return total


def profile(key: str):
    import numpy as np

    import fastsdf as sdf
    from fastsdf.shapes import scenes

    name, build = SCENES[key]
    t0 = time.perf_counter()
    f = build(sdf, scenes)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    src = f.compiled.module_source
    t_codegen = time.perf_counter() - t0
    t0 = time.perf_counter()
    mod = f.compiled.module
    t_import = time.perf_counter() - t0
    p = np.random.default_rng(0).uniform(-2, 2, (2, 8192))
    t0 = time.perf_counter()
    f(p[0], p[1], compute_gradient=True)
    t_first = time.perf_counter() - t0
    # The scene's compiled code is its block function (the parallel kernels that call it are
    # compiled once per installation); numba's timers split its compile into the whole
    # (under the compiler lock) and the LLVM part.
    tm = {"compiler_lock": 0.0, "llvm_lock": 0.0}
    # long scenes: _fold_vg, the loops over same-shape subexpressions (and for trees of blends
    # no _block_vg: the installation's interpreter runs them)
    for fn in ("_block_vg", "_fold_vg"):
        if hasattr(mod, fn):
            for key, value in _timers(getattr(mod, fn)).items():
                tm[key] += value
    return dict(
        name=name,
        lines=len(f.source().splitlines()),
        module_bytes=len(src),
        build=t_build,
        codegen=t_codegen,
        import_=t_import,
        first=t_first,
        numba=tm["compiler_lock"] - tm["llvm_lock"],
        llvm=tm["llvm_lock"],
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.profile_compile",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scene",
        choices=sorted(SCENES),
        action="append",
        help="scene(s) to profile (default: all but box1000 and mixed2000)",
    )
    parser.add_argument("--source", choices=sorted(SCENES), help="print a scene's generated code")
    parser.add_argument(
        "--module",
        action="store_true",
        help="with --source: print the whole module (tables, kernels)",
    )
    args = parser.parse_args(argv)
    os.environ["FASTSDF_CACHE_DIR"] = tempfile.mkdtemp(prefix="fastsdf-profile-")
    if args.source:
        import fastsdf as sdf
        from fastsdf.shapes import scenes

        f = SCENES[args.source][1](sdf, scenes)
        print(f.compiled.module_source if args.module else f.source())
        return 0
    t0 = time.perf_counter()
    import numba  # noqa: F401 - import cost shown separately

    import fastsdf.backends.kernel.codegen  # noqa: F401

    print(f"import numba + fastsdf: {time.perf_counter() - t0:.2f} s (once per process)")
    keys = args.scene or ["circle", "seed", "box20", "box200", "mixed50", "mixed200"]
    header = (
        "scene",
        "lines",
        "build graph",
        "codegen",
        "import module",
        "first call",
        "of which numba",
        "of which LLVM",
    )
    print(" | ".join(header))
    for key in keys:
        r = profile(key)
        print(
            f"{r['name']} | {r['lines']} | {r['build']:.3f} s | {r['codegen']:.3f} s | "
            f"{r['import_']:.3f} s | {r['first']:.2f} s | {r['numba']:.2f} s | {r['llvm']:.2f} s"
        )
    print(
        "\n'first call' compiles the scene's value+gradient block functions and their callees "
        "(the parallel kernel that calls them is compiled once per installation); the first "
        "scene also pays numba's one-time initialisation (~0.4 s). 'lines': the per-point "
        "function (long scenes' block kernels fold its same-shape parts into loops; scenes "
        "run as combine programs: their loops over tables, the blends being data)."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
