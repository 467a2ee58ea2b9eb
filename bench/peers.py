"""Peer implementations for side-by-side comparisons (optional: each is skipped with a note
when its package is not installed)."""

import time

from fastsdf.expr.graph import topological_order


def jax_value_and_grad(expr, symbol_names=("x", "y")):
    """``jit(vmap(value_and_grad(f)))`` of the expression, as a JAX user would write the SDF;
    returns ``(fn, import_error)`` where fn maps (xs, ys) -> (d, (gx, gy))."""
    try:
        import jax
        import jax.numpy as jnp
    except ImportError as exc:  # optional peer
        return None, str(exc)
    jax.config.update("jax_enable_x64", True)
    order = topological_order(expr)

    def f(x, y):
        env = {symbol_names[0]: x, symbol_names[1]: y}
        val = {}
        for node in order:
            a = [val[id(c)] for c in node.args]
            op = node.op
            if op == "const":
                v = jnp.float64(node.attr)
            elif op == "sym":
                v = env[node.attr]
            elif op == "add":
                v = a[0] + a[1]
            elif op == "sub":
                v = a[0] - a[1]
            elif op == "mul":
                v = a[0] * a[1]
            elif op == "div":
                v = a[0] / a[1]
            elif op == "neg":
                v = -a[0]
            elif op == "powc":
                v = a[0] ** node.attr
            elif op == "pow":
                v = a[0] ** a[1]
            elif op in ("sqrt", "exp", "log", "sin", "cos", "abs"):
                v = getattr(jnp, op)(a[0])
            elif op == "min":
                v = jnp.minimum(a[0], a[1])
            elif op == "max":
                v = jnp.maximum(a[0], a[1])
            elif op == "length":
                # the double-where idiom: sqrt's gradient at 0 is inf, and a NaN gradient
                # passes through a where that discards its branch
                s2 = a[0] * a[0] + a[1] * a[1]
                v = jnp.where(s2 > 0, jnp.sqrt(jnp.where(s2 > 0, s2, 1.0)), 0.0)
            elif op == "smin":
                v = -jnp.logaddexp(-node.attr * a[0], -node.attr * a[1]) / node.attr
            elif op == "smax":
                v = jnp.logaddexp(node.attr * a[0], node.attr * a[1]) / node.attr
            elif op == "select":  # the graph's select: a[1] where a[0] > 0, else a[2]
                v = jnp.where(a[0] > 0, a[1], a[2])
            elif op == "floor":
                v = jnp.floor(a[0])
            else:
                raise NotImplementedError(op)
            val[id(node)] = v
        return val[id(expr)]

    fn = jax.jit(jax.vmap(jax.value_and_grad(f, argnums=(0, 1))))

    def call(xs, ys):
        d, g = fn(xs, ys)
        d.block_until_ready()
        return d, g

    return call, None


def time_first_call(fn, *args):
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


# ---------------------------------------------------------------------------------------------
# Particle peers: one fused kernel per step, as an expert user of each package would write it,
# on fastsdf's own state arrays and grid storage (GridSDF with gradient='stored', float64):
# semi-implicit Euler under gravity, a bilinear value-and-gradient lookup (points outside the
# grid clamped onto it), and the same collision response as fastsdf (House and Keyser, velocity
# only while approaching). No tunnelling check and no query skipping: the work fastsdf does
# with ``prevent_tunnelling=False`` and skipping off.


def taichi_particles(grid, threads, offline_cache=True):
    """A Taichi (CPU, float64) fused particle step on ``grid``'s storage; returns
    ``(step, error)`` with ``step(p, steps, dt, ay)`` advancing the Particles ``p`` in place."""
    try:
        import taichi as ti
    except ImportError as exc:  # optional peer
        return None, str(exc)
    ti.init(
        arch=ti.cpu,
        default_fp=ti.f64,
        cpu_max_num_threads=threads,
        log_level=ti.WARN,
        offline_cache=offline_cache,
    )
    q, x0, x1, y0, y1, ihx, ihy, nx, ny = grid.sampler_data
    nx, ny = int(nx), int(ny)

    @ti.func
    def lerp2(tx, ty, a, b, c, e):
        lo = a + ty * (b - a)
        hi = c + ty * (e - c)
        return lo + tx * (hi - lo)

    @ti.kernel
    def step(
        X: ti.types.ndarray(dtype=ti.f64, ndim=2),
        V: ti.types.ndarray(dtype=ti.f64, ndim=2),
        R: ti.types.ndarray(dtype=ti.f64, ndim=1),
        CR: ti.types.ndarray(dtype=ti.f64, ndim=1),
        CF: ti.types.ndarray(dtype=ti.f64, ndim=1),
        Q: ti.types.ndarray(dtype=ti.f64, ndim=1),
        dt: ti.f64,
        ay: ti.f64,
    ):
        for i in range(X.shape[0]):
            vx = V[i, 0]
            vy = V[i, 1] + ay * dt
            x = X[i, 0] + vx * dt
            y = X[i, 1] + vy * dt
            u = (ti.min(ti.max(x, x0), x1) - x0) * ihx
            w = (ti.min(ti.max(y, y0), y1) - y0) * ihy
            ii = ti.min(ti.cast(u, ti.i32), nx - 2)
            jj = ti.min(ti.cast(w, ti.i32), ny - 2)
            tx = u - ii
            ty = w - jj
            a = 3 * (ii * ny + jj)
            c = a + 3 * ny
            d = lerp2(tx, ty, Q[a], Q[a + 3], Q[c], Q[c + 3])
            gx = lerp2(tx, ty, Q[a + 1], Q[a + 4], Q[c + 1], Q[c + 4])
            gy = lerp2(tx, ty, Q[a + 2], Q[a + 5], Q[c + 2], Q[c + 5])
            s = d - R[i]
            if s <= 0.0:
                gl = ti.sqrt(gx * gx + gy * gy)
                if gl > 0.0:
                    nxx = gx / gl
                    nyy = gy / gl
                    cr = CR[i]
                    k = (1.0 + cr) * s
                    x -= k * nxx
                    y -= k * nyy
                    vn = vx * nxx + vy * nyy
                    if vn < 0.0:
                        f = 1.0 - CF[i]
                        vx = f * (vx - vn * nxx) - cr * vn * nxx
                        vy = f * (vy - vn * nyy) - cr * vn * nyy
            X[i, 0] = x
            X[i, 1] = y
            V[i, 0] = vx
            V[i, 1] = vy

    def run(p, steps, dt, ay):
        for _ in range(steps):
            step(p["x"], p["v"], p["r"], p["cr"], p["cf"], q, dt, ay)
        ti.sync()

    return run, None


def warp_particles(grid):
    """A Warp (CPU, float64) fused particle step on ``grid``'s storage; returns
    ``(step, error)`` like :func:`taichi_particles`. Warp's CPU kernels run on one thread."""
    try:
        import numpy as np
        import warp as wp
    except ImportError as exc:  # optional peer
        return None, str(exc)
    wp.config.quiet = True
    wp.init()
    q, x0, x1, y0, y1, ihx, ihy, nx, ny = grid.sampler_data
    f64 = wp.float64
    consts = [f64(float(v)) for v in (x0, x1, y0, y1, ihx, ihy)]

    @wp.func
    def lerp2(tx: f64, ty: f64, a: f64, b: f64, c: f64, e: f64):
        lo = a + ty * (b - a)
        hi = c + ty * (e - c)
        return lo + tx * (hi - lo)

    @wp.kernel
    def step(
        X: wp.array2d(dtype=f64),
        V: wp.array2d(dtype=f64),
        R: wp.array(dtype=f64),
        CR: wp.array(dtype=f64),
        CF: wp.array(dtype=f64),
        Q: wp.array(dtype=f64),
        dt: f64,
        ay: f64,
        x0: f64,
        x1: f64,
        y0: f64,
        y1: f64,
        ihx: f64,
        ihy: f64,
        nx: int,
        ny: int,
    ):
        i = wp.tid()
        zero = f64(0.0)
        one = f64(1.0)
        vx = V[i, 0]
        vy = V[i, 1] + ay * dt
        x = X[i, 0] + vx * dt
        y = X[i, 1] + vy * dt
        u = (wp.min(wp.max(x, x0), x1) - x0) * ihx
        w = (wp.min(wp.max(y, y0), y1) - y0) * ihy
        ii = wp.min(int(u), nx - 2)
        jj = wp.min(int(w), ny - 2)
        tx = u - f64(ii)
        ty = w - f64(jj)
        a = 3 * (ii * ny + jj)
        c = a + 3 * ny
        d = lerp2(tx, ty, Q[a], Q[a + 3], Q[c], Q[c + 3])
        gx = lerp2(tx, ty, Q[a + 1], Q[a + 4], Q[c + 1], Q[c + 4])
        gy = lerp2(tx, ty, Q[a + 2], Q[a + 5], Q[c + 2], Q[c + 5])
        s = d - R[i]
        if s <= zero:
            gl = wp.sqrt(gx * gx + gy * gy)
            if gl > zero:
                nxx = gx / gl
                nyy = gy / gl
                cr = CR[i]
                k = (one + cr) * s
                x = x - k * nxx
                y = y - k * nyy
                vn = vx * nxx + vy * nyy
                if vn < zero:
                    f = one - CF[i]
                    vx = f * (vx - vn * nxx) - cr * vn * nxx
                    vy = f * (vy - vn * nyy) - cr * vn * nyy
        X[i, 0] = x
        X[i, 1] = y
        V[i, 0] = vx
        V[i, 1] = vy

    qa = wp.array(np.asarray(q), dtype=f64, device="cpu", copy=False)

    def run(p, steps, dt, ay):
        arrs = [
            wp.array(p[k], dtype=f64, device="cpu", copy=False) for k in ("x", "v", "r", "cr", "cf")
        ]
        for _ in range(steps):
            wp.launch(
                step,
                dim=len(p),
                inputs=arrs + [qa, f64(dt), f64(ay)] + consts + [int(nx), int(ny)],
                device="cpu",
            )
        wp.synchronize()

    return run, None
