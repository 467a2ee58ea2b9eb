"""The granular engine on the GPU: the dense bed of ``bench/bench_granular.py`` (hexagonal
lattice of spacing 0.99, discs of diameter 1 pressed on their six neighbours, a floor, x
periodic, ``gran/hooke`` with kn = 2e5 and LAMMPS's gamma_n = 300, dt = 1e-4, skin 0.2)
stepped by ``GranularSimulation(..., device='cuda')``, with and without contact history.

    python -m bench.cuda_granular                     # 1e6, 1e7, 1e8 discs on the GPU
    python -m bench.cuda_granular --sizes 1e6 1e7 --history
    python -m bench.cuda_granular --sim               # tiny, under numba-cuda's simulator
    python -m bench.cuda_granular --ptx               # every kernel compiled for sm_90, no GPU

:func:`rows` is called by ``bench/bench_cuda.py``. Each size: one warm-up run of the substeps
(compiling, and the first rebuilds), then timed runs with ``cuda.synchronize()`` around each
(median); grain-steps/s, the device bytes per grain, rebuilds per substep. At the first size
(1e6 by default) the CPU engine runs the same bed on every core in the same process, for the
ratio and for the largest difference of positions after the same substeps (the two agree to
rounding: the force sums run in another order).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from typing import Any

if "--sim" in sys.argv:  # read by numba when numba.cuda is first imported
    os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
if "--ptx" in sys.argv:
    os.environ["NUMBA_ENABLE_CUDASIM"] = "0"

import numpy as np

COMMAND = "python -m bench.cuda_granular"


def bed(n: int, history: bool, device: str) -> tuple:
    """The dense bed of ``bench.bench_granular`` (about ``n`` discs) on ``device``, and the
    number of discs (reading the simulation's positions would copy its state)."""
    from .bench_granular import ours

    rows = max(round(math.sqrt(n)), 4)  # the lattice of bench_granular.hex_bed
    return ours(n, history, device), rows * (rows + rows % 2)


def _timed(sim: Any, n: int, steps: int, repeats: int) -> list:
    from fastsdf.device import cuda

    cu = cuda()
    rates = []
    for _ in range(repeats):
        cu.synchronize()
        t0 = time.perf_counter()
        sim.advance(steps)
        cu.synchronize()
        rates.append(n * steps / (time.perf_counter() - t0))
    return rates


def _fits(n: int, history: bool) -> str | None:
    """Why ``n`` grains would not fit on the GPU (None when they do, or under the simulator)."""
    from fastsdf.device import cuda, simulated

    if simulated():
        return None
    free, _ = cuda().current_context().get_memory_info()
    need = n * (300 if history else 160) * 1.1
    if need > free:
        return f"needs about {need / 2**30:.1f} GiB, {free / 2**30:.1f} GiB free"
    return None


def rows(
    sizes: tuple = (10**6, 10**7, 10**8),
    history: tuple = (False, True),
    sim: bool = False,
) -> list[dict]:
    """One row per (size, history): grain-steps/s on the GPU (median and best), bytes per
    grain on the device, rebuilds per substep; at the first size also the CPU engine on all
    cores (grain-steps/s, the GPU's ratio, the largest difference of positions). ``sim``:
    tiny sizes and few steps (under the simulator: a smoke test, no meaningful figures)."""
    import numba

    from fastsdf.device import simulated

    if sim or simulated():
        sizes, steps, repeats, warm = (150,), 6, 2, 4
    else:
        steps, repeats, warm = 0, 3, 0
    out = []
    for n in sizes:
        for hist in history:
            row: dict = {"section": "grains", "n": int(n), "history": bool(hist)}
            why = _fits(int(n), bool(hist))
            if why is not None:
                row["skipped"] = why
                out.append(row)
                print(json.dumps(row), flush=True)
                continue
            t0 = time.perf_counter()
            gpu, n_real = bed(int(n), bool(hist), "cuda")
            row["setup_s"] = time.perf_counter() - t0
            row["n"] = int(n_real)
            k = steps or max(20, min(500, int(2e9 // n_real)))  # about 0.5 s a run at 4 G/s
            t0 = time.perf_counter()
            gpu.advance(warm or k)
            row["warmup_s"] = time.perf_counter() - t0
            rebuilds = gpu.rebuilds
            rates = _timed(gpu, n_real, k, repeats)
            row.update(
                substeps=k,
                grain_steps_per_s=float(np.median(rates)),
                best_grain_steps_per_s=float(max(rates)),
                bytes_per_grain=float(gpu.memory_per_grain()),
                max_neighbours=int(gpu.max_neighbours),
                rebuilds_per_substep=(gpu.rebuilds - rebuilds) / (k * repeats),
            )
            if n == sizes[0]:
                cpu, _ = bed(int(n), bool(hist), "cpu")
                again, _ = bed(int(n), bool(hist), "cuda")
                kc = steps or max(10, min(100, int(2e8 // n_real)))
                cpu.advance(warm or kc)
                again.advance(warm or kc)
                t0 = time.perf_counter()
                cpu.advance(kc)
                cpu_rate = n_real * kc / (time.perf_counter() - t0)
                again.advance(kc)
                diff = np.abs(again.positions - cpu.positions).max()
                row.update(
                    cpu_threads=numba.get_num_threads(),
                    cpu_grain_steps_per_s=float(cpu_rate),
                    gpu_over_cpu=row["grain_steps_per_s"] / cpu_rate,
                    max_abs_diff_positions_vs_cpu=float(diff),
                    cpu_bytes_per_grain=float(cpu.memory_per_grain()),
                )
                del cpu, again
            del gpu
            out.append(row)
            print(json.dumps(row), flush=True)
    return out


def ptx_check(cc: tuple = (9, 0)) -> list:
    """Compile every kernel of :mod:`fastsdf.granular.cuda` (each contact model; no world, a
    scene, a GridSDF with and without its exact fallback) to PTX for compute capability ``cc``
    on a machine without a GPU: numba-cuda's typing, lowering and NVVM, which the simulator
    skips (it runs the kernels as Python). Needs libnvvm and libdevice (``CUDA_HOME``); numba-cuda
    asks a device or NVRTC for facts a compile to PTX does not need, patched here for this
    check only. Returns ``(kernel, PTX characters)``; an error propagates."""
    import numba.cuda.cudadrv.libs as libs
    import numba.cuda.cudadrv.nvrtc as nvrtc
    import numba.cuda.cudadrv.nvvm as nvvm
    import numba.cuda.dispatcher as dispatcher
    from numba import cuda as nbcuda

    home = os.environ.get("CUDA_HOME", "/usr/local/cuda")
    libdevice = os.path.join(home, "nvvm", "libdevice", "libdevice.10.bc")
    nvrtc.get_supported_ccs = lambda: (cc,)
    libs.get_libdevice = nvvm.get_libdevice = lambda: libdevice  # type: ignore[attr-defined]

    def read_libdevice() -> bytes:
        with open(libdevice, "rb") as fh:
            return fh.read()

    libs.open_libdevice = nvvm.open_libdevice = read_libdevice  # type: ignore[attr-defined]
    dispatcher.get_current_device = lambda: type("Device", (), {"compute_capability": cc})()
    nbcuda.is_available = lambda: True

    import numba

    import fastsdf as fs
    import fastsdf.granular.cuda as gc
    from fastsdf.granular.cells import CellGrid
    from fastsdf.granular.kernels import Bulk, Law

    gc._load()
    fs.GridSDF.device_sampler_data = lambda grid: grid.sampler_data  # the device copy's types
    n, slots = 64, 7
    a = {
        "st": np.zeros((12, n)),
        "f32": np.zeros(n, np.float32),
        "i32": np.zeros(n, np.int32),
        "nbr": np.zeros((slots, n), np.uint32),
        "i8": np.zeros(n, np.int8),
        "flag": np.zeros(3, np.int32),
        "f64": np.zeros(n),
    }
    cell = CellGrid(0.0, 0.0, 1.0, 1.0, 5, 5, 0.0)
    done = []

    def ptx(kernel: Any, *args: Any) -> None:
        sig = tuple(numba.typeof(v) for v in args)
        fn = getattr(kernel, "py_func", None) or kernel._fn
        code, _ = nbcuda.compile_ptx(fn, sig, cc=cc)
        done.append((fn.__name__, len(code)))

    st, i32, f32, nbr, flag = a["st"], a["i32"], a["f32"], a["nbr"], a["flag"]
    ptx(gc._fill_i32, i32, 0)
    ptx(gc._fill_u32, nbr.reshape(-1), gc.EMPTY)
    ptx(gc._bounds, st, np.zeros(5))
    ptx(gc._keys, st, cell, i32, i32, i32)
    ptx(gc._scan_runs, i32, 5, i32, 64)
    ptx(gc._add_offsets, i32, 5, i32, 64)
    ptx(gc._scatter, i32, i32, i32, i32)
    ptx(gc._order_cells, i32, 5, i32)
    ptx(gc._gather_row, st, 3, i32, a["f64"])
    ptx(gc._put_row, st, 3, a["f64"])
    ptx(gc._gather_i32, i32, i32, i32)
    ptx(gc._copy_i32, i32, i32)
    ptx(gc._build, st, i32, cell, 0.2, nbr, flag)
    ptx(gc._carry, i32, nbr, np.zeros((1, slots, n)), nbr, np.zeros((1, slots, n)))
    ptx(gc._set_refs, st, f32, f32)
    floor = fs.Halfspace((0.0, 1.0), 0.0)
    bounds = [(-1.0, 9.0), (-1.0, 5.0)]
    worlds = [
        None,
        floor,
        fs.GridSDF(floor, bounds=bounds, samples=[11, 7]),
        fs.GridSDF(floor, bounds=bounds, samples=[11, 7], mode="nearest"),
    ]
    law = Law(*(1.0,) * 9)
    bulk = Bulk(1.0, 0.0, -1.0, 0.0, 0.0)
    ptx(gc._drift, 3, flag, st, f32, f32, 0.5, 1e-4, 1.0, 0.01)
    for world in worlds:
        at, data = gc._world_point(world)
        for hist, roll in ((False, False), (True, False), (True, True)):
            _, forces, mark_near, energy = gc._kernels(at, gc.Model(hist, roll, hist, roll))
            mem = np.zeros((2 if roll else 1, slots if hist else 1, n if hist else 1))
            wmem = np.zeros((2 if roll else int(hist), n))
            dev = gc.DeviceWorld(a["i8"], wmem, data, np.zeros(2))
            ptx(forces, flag, st, nbr, mem, dev, law, law, bulk)
            ptx(mark_near, st, dev, 0.2)
            ptx(energy, st, nbr, dev, 1.0, 1.0, 0.0, np.zeros((4, n)))
    return done


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=None)
    ap.add_argument("--history", action="store_true", help="with contact history only")
    ap.add_argument("--sim", action="store_true", help="tiny sizes under the simulator")
    ap.add_argument("--ptx", action="store_true", help="compile every kernel to PTX (no GPU)")
    a = ap.parse_args(argv)
    if a.ptx:
        done = ptx_check()
        print(f"{len(done)} kernels compiled to PTX for sm_90: " + ", ".join(k for k, _ in done))
        return 0
    sizes = tuple(int(s) for s in a.sizes) if a.sizes else (10**6, 10**7, 10**8)
    hist = (True,) if a.history else (False, True)
    rows(sizes, hist, sim=a.sim)
    return 0


if __name__ == "__main__":
    sys.exit(main())
