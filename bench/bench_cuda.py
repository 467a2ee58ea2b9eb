"""The CUDA target against its peers on one GPU machine, in one run.

``python -m bench.bench_cuda [--out DIR] [--sim] [--only expr,variants,grid,particles,grains]
[--scenes 0,1,2]``

Sections (each runs on its own: one failing prints its traceback and the next goes on):

* expressions: the notebook's world, 20 smoothly joined boxes, a hard union of 1,000 boxes
  (pruned per tile): value and gradient through ``f(x, y, compute_gradient=True,
  backend='cuda')`` on device arrays (1e8 points; 1e7 for the 1,000 boxes), the same with
  NumPy in and out (host round trip), JAX's ``jit(vmap(value_and_grad))`` on the same GPU
  (``bench.peers``) and this package's CPU kernel on every core of the machine; the largest
  difference from the CPU kernel, relative to ``max(1, |d|)``. ``--scenes`` picks some.
* variants: the notebook's world's point function under other launch shapes and output
  layouts, and the I/O floor (for tuning the generated kernels).
* grid: a 400 x 400 ``GridSDF`` of the notebook's world queried on the device.
* particles, grains: ``bench.cuda_particles.rows()`` and ``bench.cuda_granular.rows()`` (the
  dense bed at 1e6 and 1e7 discs with and without history, 1e8 with history).

Times are medians of 5 runs after a warm-up, with ``cuda.synchronize()`` around each. Figures
go to ``DIR/bench_cuda.json`` and ``DIR/bench_cuda.md`` (DIR: ``--out``, else ``$OUT``, else
the current folder); the table is printed last. ``--sim`` runs every section at tiny sizes under
numba-cuda's simulator (a smoke test: no figures).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import traceback

import numpy as np

if "--sim" in sys.argv:  # read by numba when it is first imported (below, through fastsdf)
    os.environ["NUMBA_ENABLE_CUDASIM"] = "1"

from fastsdf.device import to_host


def _median_time(fn, repeats: int = 5, warmup: int = 1) -> float:
    from fastsdf.device import cuda

    cu = cuda()
    for _ in range(warmup):
        fn()
    cu.synchronize()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        cu.synchronize()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _scenes(sim: bool) -> list:
    import fastsdf as sdf
    from fastsdf.shapes.scenes import box_world, seed_world

    rng = np.random.default_rng(0)
    boxes = []
    for _ in range(30 if sim else 1000):
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)):
            boxes.append(sdf.Box([-0.03, -0.02], [0.03, 0.04]))
    n_big = 2_000 if sim else 100_000_000
    return [
        ("notebook's world", seed_world(), n_big, None),
        ("20 smoothly joined boxes", box_world(20), n_big, None),
        ("1,000-box hard union, pruned", sdf.union(boxes), n_big // 10, True),
    ]


def expressions(sim: bool, scenes: str = "") -> list:
    from fastsdf.device import cuda

    cu = cuda()
    rows = []
    jax_ok = True
    chosen = {int(i) for i in scenes.split(",") if i.strip()}
    for i, (name, f, n, prune) in enumerate(_scenes(sim)):
        if chosen and i not in chosen:
            continue
        rng = np.random.default_rng(1)
        xh, yh = rng.uniform(-2.5, 2.5, (2, n))
        xd, yd = cu.to_device(xh), cu.to_device(yh)
        row: dict = {"scene": name, "points": n}
        t0 = time.perf_counter()
        f(xd[:1024], yd[:1024], compute_gradient=True, backend="cuda", prune=prune)
        cu.synchronize()
        row["first_call_s"] = time.perf_counter() - t0
        t = _median_time(lambda: f(xd, yd, compute_gradient=True, backend="cuda", prune=prune))
        row["cuda_points_per_s"] = n / t
        # agreement with the CPU kernel on a sample
        m = min(n, 1_000_000)
        d_gpu, g_gpu = f(xd[:m], yd[:m], compute_gradient=True, backend="cuda", prune=prune)
        d_gpu, g_gpu = to_host(d_gpu), to_host(g_gpu)
        d_cpu, g_cpu = f(xh[:m], yh[:m], compute_gradient=True, backend="kernel")
        scale = np.maximum(1.0, np.abs(d_cpu))
        row["max_rel_diff_value"] = float(np.max(np.abs(d_gpu - d_cpu) / scale))
        row["max_rel_diff_grad"] = float(np.max(np.abs(g_gpu - g_cpu)))
        # host round trip: NumPy in, NumPy out
        mh = min(n, 10_000_000)
        t = _median_time(
            lambda: f(xh[:mh], yh[:mh], compute_gradient=True, backend="cuda", prune=prune),
            repeats=3,
        )
        row["cuda_numpy_round_trip_points_per_s"] = mh / t
        # this package on every CPU core
        mc = min(n, 2_000_000 if sim else 20_000_000)
        f(xh[:4096], yh[:4096], compute_gradient=True, backend="kernel")
        t = _median_time(
            lambda: f(xh[:mc], yh[:mc], compute_gradient=True, backend="kernel"), repeats=3
        )
        row["cpu_points_per_s"] = mc / t
        # JAX on the same GPU (not on the 1,000-box union: tracing and compiling its graph
        # takes longer than this whole run may)
        if jax_ok and not sim and prune is None:
            try:
                row.update(_jax(f, xh, yh, n))
            except Exception as exc:
                row["jax_error"] = repr(exc)[:300]
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


_cuda = None  # numba.cuda, once kernel_variants has loaded it


def kernel_variants(sim: bool) -> list:
    """The notebook's world's point function under other launch shapes and output layouts
    (for tuning the generated kernels: one point per thread in blocks of 256 is the shipped
    shape)."""
    from fastsdf.device import cuda
    from fastsdf.shapes.scenes import seed_world

    global _cuda
    cu = _cuda = cuda()  # a module global: the simulator swaps it inside kernels
    f = seed_world()
    k = f.compiled.cuda
    point_vg = k.module.point_vg
    n = 2_000 if sim else 100_000_000
    rng = np.random.default_rng(3)
    xd, yd = (cu.to_device(a) for a in rng.uniform(-2.5, 2.5, (2, n)))
    out, grad = cu.device_array(n), cu.device_array((n, 2))
    gx, gy = cu.device_array(n), cu.device_array(n)
    (u,) = k.table_args()

    @cu.jit
    def grid_stride(xs, ys, out, grad, u):
        i = _cuda.grid(1)
        stride = _cuda.gridsize(1)
        while i < xs.shape[0]:
            d, a, b = point_vg(xs[i], ys[i], u)
            out[i] = d
            grad[i, 0] = a
            grad[i, 1] = b
            i += stride

    @cu.jit
    def one_per_thread(xs, ys, out, grad, u):
        i = _cuda.grid(1)
        if i < xs.shape[0]:
            d, a, b = point_vg(xs[i], ys[i], u)
            out[i] = d
            grad[i, 0] = a
            grad[i, 1] = b

    @cu.jit
    def split_gradient(xs, ys, out, gx, gy, u):
        i = _cuda.grid(1)
        if i < xs.shape[0]:
            d, a, b = point_vg(xs[i], ys[i], u)
            out[i] = d
            gx[i] = a
            gy[i] = b

    @cu.jit
    def value_only_io(xs, ys, out):
        i = _cuda.grid(1)
        if i < xs.shape[0]:
            out[i] = xs[i] + ys[i]

    rows = []
    shipped = k.module.batch_vg
    cap = 4 if sim else 65536  # (the simulator runs each thread as a Python thread)
    for name, run in (
        (
            "shipped: one point per thread, 256",
            lambda: shipped[-(-n // 256), 256](xd, yd, out, grad, u),
        ),
        ("grid-stride, 65536 x 256", lambda: grid_stride[cap, 256](xd, yd, out, grad, u)),
        (
            "one point per thread, 256 (kernel defined here)",
            lambda: one_per_thread[-(-n // 256), 256](xd, yd, out, grad, u),
        ),
        (
            "one point per thread, 128",
            lambda: one_per_thread[-(-n // 128), 128](xd, yd, out, grad, u),
        ),
        (
            "one point per thread, 512",
            lambda: one_per_thread[-(-n // 512), 512](xd, yd, out, grad, u),
        ),
        (
            "gradient as two arrays, 256",
            lambda: split_gradient[-(-n // 256), 256](xd, yd, out, gx, gy, u),
        ),
        (
            "I/O floor: read x, y, write one value",
            lambda: value_only_io[-(-n // 256), 256](xd, yd, out),
        ),
    ):
        try:
            t = _median_time(run)
            rows.append({"variant": name, "points_per_s": n / t})
        except Exception as exc:
            rows.append({"variant": name, "error": repr(exc)[:300]})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def _jax(f, xh, yh, n) -> dict:
    import jax
    import jax.numpy as jnp

    from bench.peers import jax_value_and_grad

    fn, err = jax_value_and_grad(f.f)
    if fn is None:
        return {"jax_error": err}
    mj = min(n, 100_000_000 if f.f is not None else n)
    dev = jax.devices()[0]
    xj = jax.device_put(jnp.asarray(xh[:mj]), dev)
    yj = jax.device_put(jnp.asarray(yh[:mj]), dev)
    t0 = time.perf_counter()
    d, _ = fn(xj[:1024], yj[:1024])
    first = time.perf_counter() - t0
    fn(xj, yj)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        d, g = fn(xj, yj)
        g[0].block_until_ready()
        times.append(time.perf_counter() - t0)
    return {
        "jax_points_per_s": mj / float(np.median(times)),
        "jax_first_call_s": first,
        "jax_device": str(dev),
    }


def grid(sim: bool) -> list:
    import fastsdf as sdf
    from fastsdf.device import cuda
    from fastsdf.shapes.scenes import seed_world

    cu = cuda()
    f = seed_world()
    side = 50 if sim else 400
    g = sdf.GridSDF(f, bounds=[(-2.5, 2.5), (-2.5, 2.5)], samples=[side * 1j, side * 1j])
    n = 2_000 if sim else 100_000_000
    rng = np.random.default_rng(2)
    xh, yh = rng.uniform(-2.4, 2.4, (2, n))
    xd, yd = cu.to_device(xh), cu.to_device(yh)
    t = _median_time(lambda: g(xd, yd, compute_gradient=True, backend="cuda"))
    m = min(n, 20_000_000)
    tc = _median_time(lambda: g(xh[:m], yh[:m], compute_gradient=True), repeats=3)
    d_gpu = to_host(g(xd[:100000], yd[:100000], backend="cuda"))
    d_cpu = g(xh[:100000], yh[:100000])
    row = {
        "scene": f"GridSDF {side}x{side} of the notebook's world",
        "points": n,
        "cuda_points_per_s": n / t,
        "cpu_points_per_s": m / tc,
        "max_abs_diff_value": float(np.max(np.abs(d_gpu - d_cpu))),
    }
    print(json.dumps(row), flush=True)
    return [row]


def particles(sim: bool) -> list:
    from bench.cuda_particles import rows

    return rows(sim=sim)


def grains(sim: bool) -> list:
    """The dense bed at 1e6 and 1e7 discs with and without history, and 1e8 with history (the
    largest case the memory target is about; without history it needs less)."""
    from bench.cuda_granular import rows

    if sim:
        return rows(sim=True)
    return rows(sizes=(10**6, 10**7)) + rows(sizes=(10**8,), history=(True,))


def machine() -> dict:
    info = {"python": platform.python_version(), "cpu_count": os.cpu_count()}
    try:
        import numba
        import numba_cuda

        info.update(numba=numba.__version__, numba_cuda=numba_cuda.__version__)
    except ImportError:
        pass
    info["numpy"] = np.__version__
    try:
        from fastsdf.device import cuda

        cu = cuda()
        if not os.environ.get("NUMBA_ENABLE_CUDASIM"):
            d = cu.get_current_device()
            info["gpu"] = d.name.decode() if isinstance(d.name, bytes) else str(d.name)
            info["sm_count"] = d.MULTIPROCESSOR_COUNT
    except Exception as exc:
        info["gpu_error"] = repr(exc)
    try:
        import numba

        info["numba_threads"] = numba.get_num_threads()
    except ImportError:
        pass
    return info


def _table(results: dict) -> str:
    lines = [f"machine: {json.dumps(results['machine'])}", ""]
    for section, rows in results.items():
        if section == "machine":
            continue
        lines.append(f"## {section}")
        for row in rows:
            lines.append(
                "- "
                + ", ".join(
                    f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()
                )
            )
        lines.append("")
    return "\n".join(lines)


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.environ.get("OUT", "."))
    ap.add_argument("--sim", action="store_true", help="tiny sizes under the simulator")
    ap.add_argument("--only", default="expr,variants,grid,particles,grains")
    ap.add_argument(
        "--scenes", default="", help="expressions: indices of the scenes to run (default all)"
    )
    args = ap.parse_args(argv)
    if args.sim:
        os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
    sections = {
        "expr": lambda: expressions(args.sim, args.scenes),
        "variants": lambda: kernel_variants(args.sim),
        "grid": lambda: grid(args.sim),
        "particles": lambda: particles(args.sim),
        "grains": lambda: grains(args.sim),
    }
    results: dict = {"machine": machine()}
    print(json.dumps(results["machine"]), flush=True)
    for name in args.only.split(","):
        t0 = time.perf_counter()
        try:
            results[name] = sections[name]()
        except Exception:
            traceback.print_exc()
            results[name] = [{"error": traceback.format_exc(limit=3)[-800:]}]
        print(f"[{name}: {time.perf_counter() - t0:.1f} s]", flush=True)
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "bench_cuda.json"), "w") as fh:
            json.dump(results, fh, indent=1, default=str)
    table = _table(results)
    with open(os.path.join(args.out, "bench_cuda.md"), "w") as fh:
        fh.write(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
