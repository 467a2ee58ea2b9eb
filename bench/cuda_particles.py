"""Particles on the GPU (``ParticleSimulation(..., device='cuda')``) against the same machine's
CPU on all cores.

    python -m bench.cuda_particles            # on a CUDA GPU: the sizes below
    python -m bench.cuda_particles --sim      # tiny sizes under numba-cuda's simulator (no GPU)
    python -m bench.cuda_particles --ptx      # compile the step kernels for sm_90 without a GPU
                                              # (needs libnvvm and ptxas): registers, spills

Scenario: the notebook's drop (``x ~ N([0, 1.5], 0.05 I)``, ``v ~ N(0, 0.1 I)``, ``m ~ U(1,
10)``, ``r = 0.01 m``, gravity ``(0, -1)``, ``timestep = 1/30``, seed 0) in the seed world (the
funnel and a cut disc, :func:`fastsdf.shapes.scenes.seed_world`), sampled by the demo's
400x400 GridSDF over ``[-2, 2]**2`` (mode 'exact'), or queried exactly (the scene's point
function). Phases as in ``bench/bench_particles.py``: **fall** (the steps after step 1: free
fall, then the impact on the disc and the funnel) and **settled** (after 200 steps: most
particles rest or slide in the funnel). Each timed call is ``run(steps)`` (default 100) after a
warm-up step, between ``cuda.synchronize()`` calls; the rate is particle-steps per second.
The CPU rows run the package's default path (query skipping, tunnelling check, the block
kernel) on all cores with ``cpu_n`` particles.

:func:`rows` returns one dict per measurement; the lead's ``bench/bench_cuda.py`` calls it.
"""

from __future__ import annotations

import os
import re
import sys
import time
from typing import Any

SETTLE = 200
#: The demo's grid over the demo's bounds.
GRID = 400
BOUNDS = ((-2.0, 2.0), (-2.0, 2.0))


def _world(kind: str) -> Any:
    from fastsdf import GridSDF
    from fastsdf.shapes.scenes import seed_world

    f = seed_world()
    if kind == "exact":
        return f
    return GridSDF(f, bounds=BOUNDS, samples=[GRID * 1j, GRID * 1j], mode="exact")


def _sim(world: Any, n: int, device: str) -> Any:
    from fastsdf.particles import Gravity, ParticleSimulation

    sim = ParticleSimulation(world, n=n, timestep=1 / 30, seed=0, device=device)
    sim.force_generators.append(Gravity(acceleration=(0.0, -1.0)))
    return sim


def _sync(device: str) -> None:
    if device == "cuda":
        from fastsdf.device import cuda

        cuda().synchronize()


def _phases(
    world: Any, name: str, n: int, device: str, steps: int, settle: int, paths: tuple
) -> list[dict]:
    """Fall and settled rates of ``n`` particles in ``world`` on ``device``, for each step
    path (``'sweep'``: the default, with the tunnelling sweep; ``'plain'``: without), each
    timed from the same state."""
    out = []
    t0 = time.perf_counter()
    sim = _sim(world, n, device)
    made = time.perf_counter() - t0
    start, t_start = sim.p.copy(), sim.t
    for path in paths:  # warm-up: compiles (or loads) each path's kernel
        sim.prevent_tunnelling = path == "sweep"
        sim.run(1)
        sim.p, sim.t = start.copy(), t_start
    for phase in ("fall", "settled"):
        if phase == "settled":
            sim.p, sim.t = start, t_start
            sim.prevent_tunnelling = True
            sim.run(settle)
            _sync(device)
            start, t_start = sim.p.copy(), sim.t
        for path in paths:
            sim.p, sim.t = start.copy(), t_start
            sim.prevent_tunnelling = path == "sweep"
            _sync(device)
            t0 = time.perf_counter()
            sim.run(steps)
            _sync(device)
            seconds = time.perf_counter() - t0
            sim.check()
            out.append(
                {
                    "device": device,
                    "world": name,
                    "phase": phase,
                    "step": path,
                    "particles": n,
                    "steps": steps,
                    "seconds": seconds,
                    "rate": n * steps / seconds,
                    "setup_seconds": made,
                }
            )
    return out


def rows(
    sim: bool = False,
    n: int | None = None,
    big: int | None = None,
    cpu_n: int | None = None,
    steps: int | None = None,
    settle: int | None = None,
) -> list[dict]:
    """The measurements: the GPU with ``n`` particles (default 1e7) on the grid and the exact
    world (fall and settled), ``big`` particles (1e8; 0: none) in one simulation on the grid,
    and the CPU on all cores with ``cpu_n`` particles (1e6) on the grid; ``steps`` timed steps
    (100) after ``settle`` (200). Each GPU row carries ``vs_cpu``, its rate over the CPU's on
    the grid in the same phase. ``sim``: tiny sizes (for numba-cuda's simulator)."""
    small = {"n": 64, "big": 96, "cpu_n": 256, "steps": 3, "settle": 6}
    full = {"n": 10**7, "big": 10**8, "cpu_n": 10**6, "steps": 100, "settle": SETTLE}
    given = {"n": n, "big": big, "cpu_n": cpu_n, "steps": steps, "settle": settle}
    size = {k: v if v is not None else (small if sim else full)[k] for k, v in given.items()}
    n, big, cpu_n, steps, settle = (int(size[k]) for k in ("n", "big", "cpu_n", "steps", "settle"))
    import numba

    from fastsdf.device import cuda

    cu = cuda()
    grid, exact = _world("grid"), _world("exact")
    gname, ename = f"seed grid {GRID}x{GRID}", "seed exact"
    both = ("sweep", "plain")
    out = _phases(grid, gname, n, "cuda", steps, settle, both)
    out += _phases(exact, ename, n, "cuda", steps, settle, both)
    if big:
        out += _phases(grid, gname, big, "cuda", steps, settle, both)
    cpu = _phases(grid, gname, cpu_n, "cpu", steps, settle, ("sweep",))
    threads = numba.get_num_threads()
    for row in cpu:
        row["threads"] = threads
    base = {row["phase"]: row["rate"] for row in cpu}
    name = "simulator" if _simulated() else _gpu_name(cu)
    for row in out:
        row["vs_cpu"] = row["rate"] / base[row["phase"]]
        row["gpu"] = name
    return out + cpu


def _simulated() -> bool:
    from fastsdf.device import simulated

    return simulated()


def _gpu_name(cu: Any) -> str:
    try:
        name = cu.get_current_device().name
        return name.decode() if isinstance(name, bytes) else str(name)
    except Exception:  # a label only
        return "cuda"


def table(results: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = [
        "| device | world | phase | step | particles | particle-steps/s | vs CPU |",
        "|---|---|---|---|---:|---:|---:|",
    ]
    for r in results:
        vs = f"{r['vs_cpu']:.3g}x" if "vs_cpu" in r else f"({r.get('threads', '?')} threads)"
        lines.append(
            f"| {r['device']} | {r['world']} | {r['phase']} | {r['step']} | {r['particles']:,} | "
            f"{r['rate'] / 1e9:.3g} G | {vs} |"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Compiling the kernels for a GPU without one (a development check).


def toolkit() -> tuple[str, str] | None:
    """``(libdevice, ptxas)`` of the CUDA toolkit at ``CUDA_HOME`` (or /usr/local/cuda*), or
    None."""
    import glob

    home = os.environ.get("CUDA_HOME") or "/usr/local/cuda"
    for libdevice in sorted(glob.glob(f"{home}*/nvvm/libdevice/libdevice*.bc"), reverse=True):
        ptxas = os.path.join(libdevice.split("/nvvm/")[0], "bin", "ptxas")
        if os.path.exists(ptxas):
            return libdevice, ptxas
    return None


def ptx_report(cc: tuple[int, int] = (9, 0), names: tuple | None = None) -> list[dict]:
    """Compile the step kernel for the grid and the exact world (the grid with an ``@njit``
    force, a moving world) to PTX for compute capability ``cc`` without a GPU, and assemble it with
    ``ptxas``: registers, spills and FMA instructions per kernel (as compiled, and as NVVM
    would contract them by default); ``names``: only these kernels (see the list below).
    Needs the CUDA toolkit's libnvvm, libdevice and ptxas (``CUDA_HOME``, default
    /usr/local/cuda); stands in for the device's compute capability and the toolkit's list
    of architectures (numba-cuda asks the driver and NVRTC for them)."""
    import subprocess
    import tempfile

    found = toolkit()
    if found is None:
        raise RuntimeError("no CUDA toolkit (libdevice, ptxas) found: set CUDA_HOME")
    libdevice, ptxas = found

    import fastsdf.device as dv

    dv._patch_numpy()
    from numba import cuda as cu
    from numba.cuda import dispatcher as disp
    from numba.cuda.cudadrv import libs, nvrtc, nvvm

    class _Device:
        compute_capability = cc

    disp.get_current_device = lambda: _Device()  # type: ignore[attr-defined]
    nvrtc.get_supported_ccs = lambda: [(7, 5), (8, 0), (8, 6), (9, 0), (10, 0), (12, 0)]
    nvvm.get_libdevice = lambda: libdevice  # type: ignore[attr-defined]
    with open(libdevice, "rb") as fh:
        code = fh.read()
    nvvm.open_libdevice = lambda: code  # type: ignore[attr-defined]
    libs.get_libdevice = nvvm.get_libdevice
    dv.cuda = lambda: cu

    from numba import njit

    from fastsdf.particles import cuda as pc

    @njit
    def wind(x, y, vx, vy, m, t):
        return 0.1 * y, -0.05 * vx

    import fastsdf as sdf

    grid, exact = _world("grid"), _world("exact")
    piston = sdf.Halfspace(normal=[1, 0], d=sdf.Param("x0", -1.0) + sdf.Param("u", 0.5) * sdf.t)
    moving = piston | sdf.Halfspace(normal=[0, 1], d=-1.0 + 0.4 * sdf.t)
    out = []
    for name, world, forces, trace in (
        ("grid", grid, (), False),
        ("grid+sweep", grid, (), True),
        ("exact+sweep", exact, (), True),
        ("grid+force", grid, (wind,), False),
        ("moving", moving, (), False),
    ):
        if names is not None and name not in names:
            continue
        module, key, _ = pc.device_module(world, forces)
        kernel = pc.step_kernel(module, trace, key + (trace,))
        arg = tuple(grid.sampler_data) if world is grid else (0.0,)
        if world is moving:
            arg = tuple(float(v) for v in moving.param_tuple())
        sig = pc.kernel_signature(arg)
        with pc.ieee_compile():
            ptx, _ = cu.compile_ptx(kernel.py_func, sig, cc=cc)
        contracted, _ = cu.compile_ptx(kernel.py_func, sig, cc=cc)  # NVVM's default: -fma=1
        with tempfile.TemporaryDirectory() as tmp:
            src = os.path.join(tmp, "k.ptx")
            with open(src, "w") as fh:
                fh.write(ptx)
            res = subprocess.run(
                [ptxas, f"-arch=sm_{cc[0]}{cc[1]}", "-v", src, "-o", os.path.join(tmp, "k.cubin")],
                capture_output=True,
                text=True,
                check=True,
            )
        regs = re.search(r"Used (\d+) registers", res.stderr)
        spill = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", res.stderr)
        out.append(
            {
                "kernel": name,
                "cc": f"{cc[0]}.{cc[1]}",
                "registers": int(regs.group(1)) if regs else None,
                "spill_bytes": [int(b) for b in spill.groups()] if spill else None,
                "fma_in_ptx": ptx.count("fma.rn.f64"),
                "fma_if_contracted": contracted.count("fma.rn.f64"),
                "ptx_lines": ptx.count("\n"),
            }
        )
    return out


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if "--ptx" in args:
        import json

        # --ptx [name,name,...]: only those kernels
        at = args.index("--ptx") + 1
        names = tuple(args[at].split(",")) if at < len(args) else None
        for row in ptx_report(names=names):
            print(json.dumps(row))
        return
    if "--sim" in args:
        os.environ["NUMBA_ENABLE_CUDASIM"] = "1"  # before numba.cuda is imported
        results = rows(sim=True)
    else:
        results = rows()
    print(table(results))


if __name__ == "__main__":
    main()
