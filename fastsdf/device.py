"""The CUDA target's entry: numba-cuda loaded on demand, and arrays moved between frameworks.

``import fastsdf`` never imports numba-cuda: :func:`cuda` does, the first time a CUDA path is
asked for, and raises a clear :class:`RuntimeError` naming the ``cuda`` extra where numba-cuda
is missing or no GPU is visible. ``NUMBA_ENABLE_CUDASIM=1`` (set before the first import of
``numba.cuda``) runs every CUDA kernel on the CPU under numba-cuda's simulator: the tests use it.

Device arrays cross frameworks without copies through ``__cuda_array_interface__`` (CuPy,
PyTorch, numba's own) or DLPack (JAX): :func:`as_device` takes any of them (and NumPy arrays,
copied to the device), :func:`like` hands a result back as the caller's kind of array.
"""

from __future__ import annotations

import os
from types import ModuleType
from typing import Any

import numpy as np

__all__ = ["cuda", "available", "simulated", "is_device_array", "as_device", "like", "to_host"]

_INSTALL = "pip install 'fastsdf[cuda]' (numba-cuda)"


def simulated() -> bool:
    """Whether numba-cuda runs its kernels on the CPU (``NUMBA_ENABLE_CUDASIM=1``)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0").strip() not in ("", "0")


def _patch_numpy() -> None:
    # numba-cuda 0.30 registers an implementation of np.row_stack, which numpy 2.5 removed
    # (an alias of np.vstack since numpy 1.x): the first kernel compile would fail on import.
    if not hasattr(np, "row_stack"):
        np.row_stack = np.vstack


def cuda() -> ModuleType:
    """``numba.cuda``, checked: raises :class:`RuntimeError` naming the ``cuda`` extra where
    numba-cuda is not installed, or where no CUDA GPU (nor the simulator) is available."""
    _patch_numpy()
    try:
        import numba_cuda  # noqa: F401 - the maintained CUDA target, not numba's deprecated one
        from numba import cuda as numba_cuda_module
    except ImportError as exc:
        raise RuntimeError(
            f"the CUDA target needs numba-cuda, which is not installed: {_INSTALL}"
        ) from exc
    if not simulated() and not numba_cuda_module.is_available():
        raise RuntimeError(
            "the CUDA target found no usable CUDA GPU (numba.cuda.is_available() is False); "
            "NUMBA_ENABLE_CUDASIM=1 runs CUDA kernels on the CPU under numba-cuda's simulator"
        )
    return numba_cuda_module


def available() -> bool:
    """Whether :func:`cuda` would succeed (numba-cuda installed, a GPU or the simulator)."""
    try:
        cuda()
    except RuntimeError:
        return False
    return True


def is_device_array(a: Any) -> bool:
    """Whether ``a`` lives on a CUDA device (``__cuda_array_interface__`` or a DLPack device
    of type CUDA)."""
    if hasattr(a, "__cuda_array_interface__") or hasattr(a, "copy_to_host"):
        return True  # (numba's device arrays, and the simulator's, have copy_to_host)
    dev = getattr(a, "__dlpack_device__", None)
    if dev is not None and not isinstance(a, np.ndarray):
        try:
            return int(dev()[0]) == 2  # kDLCUDA
        except Exception:  # a foreign object: not ours to judge further
            return False
    return False


def _kind(a: Any) -> str:
    mod = type(a).__module__.split(".")[0]
    if mod in ("cupy", "torch", "jax", "jaxlib"):
        return "jax" if mod == "jaxlib" else mod
    if isinstance(a, np.ndarray) or not is_device_array(a):
        return "numpy"
    return "numba"


def as_device(a: Any, name: str = "array", dtype: Any = np.float64) -> Any:
    """``a`` as a numba device array of ``dtype`` without a copy where it already is one on
    the device (CuPy, PyTorch, numba, JAX); NumPy data (and anything array-like) is copied to
    the device. A device array of another dtype is a :class:`TypeError` naming ``name``."""
    cu = cuda()
    if is_device_array(a):
        if not hasattr(a, "__cuda_array_interface__") and not hasattr(a, "copy_to_host"):
            # DLPack only (JAX): CuPy or PyTorch take it without a copy when present
            a = _from_dlpack(a, name)
        d = a if hasattr(a, "copy_to_host") else cu.as_cuda_array(a)
        if d.dtype != np.dtype(dtype):
            raise TypeError(f"{name} must hold {np.dtype(dtype)} on the device, got {d.dtype}")
        return d
    host = np.asarray(a)
    if host.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be real numbers, got dtype {host.dtype}")
    return cu.to_device(np.ascontiguousarray(host, dtype=dtype))


def _from_dlpack(a: Any, name: str) -> Any:
    for modname in ("cupy", "torch"):
        try:
            mod = __import__(modname)
        except ImportError:
            continue
        return mod.from_dlpack(a)
    raise TypeError(
        f"{name} is a DLPack device array ({type(a).__name__}); taking it without a copy "
        "needs CuPy or PyTorch installed (numba-cuda reads __cuda_array_interface__ only)"
    )


def like(result: Any, template: Any) -> Any:
    """The device array ``result`` as the kind of array ``template`` is: CuPy, PyTorch and
    JAX arrays without a copy, NumPy copied to the host, anything else a numba device array."""
    kind = _kind(template)
    if kind == "numpy":
        return to_host(result)
    if kind == "cupy":
        import cupy

        return cupy.asarray(result)
    if kind == "torch":
        import torch

        return torch.as_tensor(result, device="cuda")
    if kind == "jax":
        import jax.dlpack

        return jax.dlpack.from_dlpack(_from_dlpack_source(result))
    return result


def _from_dlpack_source(result: Any) -> Any:
    # numba's device arrays speak __cuda_array_interface__ only; JAX reads DLPack.
    for modname in ("cupy", "torch"):
        try:
            mod = __import__(modname)
        except ImportError:
            continue
        return mod.asarray(result) if modname == "cupy" else mod.as_tensor(result, device="cuda")
    raise TypeError("handing a result to JAX without a copy needs CuPy or PyTorch installed")


def to_host(a: Any) -> np.ndarray:
    """A NumPy copy of a device array (of any kind), or ``a`` itself as a NumPy array."""
    if hasattr(a, "copy_to_host"):
        return np.asarray(a.copy_to_host())
    if is_device_array(a):
        return np.asarray(cuda().as_cuda_array(a).copy_to_host())
    return np.asarray(a)
