"""Shared fixtures and reference helpers for the fastsdf tests."""

import importlib.util
import os

import numpy as np
import pytest

# The tests share the installation's kernel cache (its files are named by the hash of their
# source, so a stale entry cannot be hit); tests of a fresh installation use their own folders.
os.environ.setdefault("MPLBACKEND", "Agg")
# The CUDA target's tests run under numba-cuda's simulator (kernels executed on the CPU), read
# when numba.cuda is first imported; NUMBA_ENABLE_CUDASIM=0 runs them on a GPU instead.
os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")

#: Whether the CUDA target can be tested here (numba-cuda is the `cuda` extra; without it the
#: CUDA paths of the shared suites are left out, and the rest must pass).
HAS_NUMBA_CUDA = importlib.util.find_spec("numba_cuda") is not None


@pytest.fixture(autouse=True)
def _kernel_backend(request, monkeypatch):
    """Tests call the compiled kernel unless they name a backend or take the marker
    ``default_backend``: under the shipped default (``'auto'``) which evaluator answers a call
    depends on a background compilation's progress (the bits do not), and every new scene
    would compile in a background thread beside the test. ``FASTSDF_TEST_DEFAULT_BACKEND=1``
    runs every test with the shipped default."""
    if "default_backend" in request.keywords or os.environ.get("FASTSDF_TEST_DEFAULT_BACKEND"):
        return
    from fastsdf.function import Function

    monkeypatch.setattr(Function, "backend", "kernel")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def evaluate(comp, x, y, compute_gradient=False, prune=None):
    """A :class:`fastsdf.function.CompiledSDF`'s kernel at points (a request made as
    ``Function.__call__`` makes it): the value, or ``(value, gradient)``."""
    from fastsdf.backends.request import make_request

    req = make_request(x, y, "vg" if compute_gradient else "v", prune=prune)
    return req.answer(comp.evaluate(req))


def central_gradient(f, x, y, h=1e-6):
    """Central finite differences of the value of ``f`` at points (x, y): (n, 2)."""
    gx = (f(x + h, y) - f(x - h, y)) / (2 * h)
    gy = (f(x, y + h) - f(x, y - h)) / (2 * h)
    return np.stack([gx, gy], axis=-1)


def value_of(f):
    """The value of ``f``'s value-and-gradient call (for finite differences of a scene whose
    test compiled that kernel: a value-only call would compile a second kernel)."""
    return lambda x, y: f(x, y, compute_gradient=True)[0]


def brute_distance(points, boundary):
    """Unsigned distance from each point to the nearest of the densely sampled ``boundary``."""
    out = np.empty(len(points))
    for start in range(0, len(points), 256):
        p = points[start : start + 256, None, :]
        out[start : start + 256] = np.sqrt(((p - boundary[None]) ** 2).sum(-1)).min(axis=1)
    return out


def rotate(points, angle):
    """Rotate row-vector points counter-clockwise by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return points @ np.array([[c, s], [-s, c]])
