"""Peer implementations for side-by-side comparisons (optional: each is skipped with a note
when its package is not installed)."""

from __future__ import annotations

import time

from fastsdf.graph import topological_order


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
                v = jnp.sqrt(a[0] * a[0] + a[1] * a[1])
            elif op == "smin":
                v = -jnp.logaddexp(-node.attr * a[0], -node.attr * a[1]) / node.attr
            elif op == "smax":
                v = jnp.logaddexp(node.attr * a[0], node.attr * a[1]) / node.attr
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
