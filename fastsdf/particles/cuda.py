"""Particles on a CUDA GPU: ``ParticleSimulation(world, ..., device='cuda')``.

One thread per particle: :meth:`CudaStep.run` launches one kernel that takes each particle
through all ``k`` steps of a call in registers (particles do not interact, so nothing couples
the threads), reading its state once and writing it once. The per-particle arithmetic is the
CPU's, written once: the kernel calls the numba ``@njit`` functions the CPU kernels call
(numba-cuda compiles them again for the device): the integration and checks
(:mod:`.kernels.step`), the collision response and the tunnelling sweep
(:mod:`.kernels.contact`), the grid's sampler (:func:`fastsdf.fields.grid.sample_stored` or
``sample_fd``), the scene's point function (``f.compiled.point_fn('vg')``) and the fused user
forces (``@njit`` functions and :class:`.FieldForce`). It takes them from a kernel module
generated as the CPU's is (the kernels' bodies after a scene block, :func:`device_module`),
whose scene block queries the world in code numba-cuda compiles.

A step is the CPU's (integrate, query the end point, sweep a fast step that is not provably
clear when ``prevent_tunnelling``, respond) without query skipping, which changes no result;
the kernel is compiled without contraction of ``a * b + c`` into FMA instructions (NVVM's
``-fma=0``), as the CPU's numba code is, so a GPU step rounds as the CPU's does.

Worlds: a dense :class:`fastsdf.GridSDF` (stored or finite-difference gradients; in mode
``'exact'`` a point outside the grid calls the scene's point function on the device), an exact
SDF, with runtime parameters too (their values are launch arguments: no recompile), and a
moving world (built with :data:`fastsdf.t`: evaluated at the end of each step with its time
derivative, the response relative to the wall, as on the CPU; without the sweep). Not on the
GPU (a clear error names them): band grids and other samplers, float32 state, Python force
generators, resting contact, the sweep in a moving world.

The state lives on the device as numba device arrays (``sim.p['x']``), which CuPy and PyTorch
take without a copy (``__cuda_array_interface__``); ``sim.host('x')`` copies to NumPy.
:meth:`CudaStep.run` does not wait for the GPU: particles frozen by a call (see
:meth:`fastsdf.particles.ParticleSimulation.run`) are counted on the device and reported by
``sim.check()``, which waits.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np

from fastsdf import device as _device
from fastsdf.particles.kernels.config import Budget, Physics, State
from fastsdf.particles.kernels.constants import FLAG_INPUT
from fastsdf.particles.scene_blocks import _is_grid, block_source, device_scene, generated_module
from fastsdf.particles.state import FieldState, Particles

__all__ = [
    "DeviceParticles",
    "CudaStep",
    "THREADS_PER_BLOCK",
    "ieee_compile",
    "kernel_signature",
]

#: Threads per block of the step kernel (under the simulator: fewer, its threads are slow).
THREADS_PER_BLOCK = 256


@contextlib.contextmanager
def ieee_compile() -> Iterator[None]:
    """Compile CUDA kernels without FMA contraction (NVVM ``-fma=0``) within the block:
    ``a * b + c`` rounds twice, as numba's CPU code does, so the device reproduces the CPU's
    bits. (numba-cuda's ``cuda.jit`` offers no option for it; explicit ``llvm.fmuladd``
    calls, as in :mod:`fastsdf.backends.kernel.vmath`, stay fused on both targets.)"""
    from numba.cuda.cudadrv import nvvm

    original = getattr(nvvm, "compile_ir", None)
    if original is None:  # another numba-cuda: its default (contraction) applies
        yield
        return

    def compile_ir(llvmir: Any, **options: Any) -> Any:
        if not options.get("fastmath"):
            options["fma"] = False
        return original(llvmir, **options)

    nvvm.compile_ir = compile_ir
    try:
        yield
    finally:
        nvvm.compile_ir = original


# ---------------------------------------------------------------------------------------------
# The state on the device.


class DeviceParticles(FieldState):
    """The particles' state on the GPU: the fields of :class:`.Particles` (``x``, ``v``:
    (n, 2); ``m``, ``r``, ``cr``, ``cf``: (n,); float64) as numba device arrays, with the
    family's mapping surface (:class:`.FieldState`).

    ``p['x']`` is the device array itself (CuPy: ``cupy.asarray(p['x'])``, PyTorch:
    ``torch.as_tensor(p['x'], device='cuda')``, both without a copy; write it in place freely
    between steps). ``p['x'] = value`` copies a device array on the device and NumPy data
    (broadcast, e.g. ``p['cr'] = 0.9``) from the host. :meth:`host` is a NumPy copy.
    """

    FIELDS = Particles.FIELDS

    def __init__(self, host: Particles) -> None:
        if host.dtype != np.dtype(np.float64):
            raise ValueError(
                f"device='cuda' steps float64 state only, got dtype={host.dtype} "
                "(pass dtype=np.float64)"
            )
        cu = _device.cuda()
        self._n = len(host)
        self._arrays = {k: cu.to_device(np.ascontiguousarray(host[k])) for k in self.FIELDS}

    def _assign_device(self, name: str, arr: Any, value: Any) -> bool:
        if not _device.is_device_array(value):
            return False
        src = _device.as_device(value, f"p[{name!r}]")
        if tuple(src.shape) != tuple(arr.shape):
            raise ValueError(
                f"p[{name!r}] has shape {arr.shape}; cannot assign a device array of "
                f"shape {src.shape}"
            )
        arr.copy_to_device(src)
        return True

    def _write(self, arr: Any, full: np.ndarray) -> None:
        arr.copy_to_device(np.ascontiguousarray(full, dtype=np.float64))

    def host(self) -> Particles:
        """A NumPy copy of the state (a :class:`.Particles`)."""
        out = Particles(self._n, np.float64)
        for name in self.FIELDS:
            out._arrays[name][...] = _device.to_host(self._arrays[name])
        return out

    def copy(self) -> DeviceParticles:
        """An independent copy, on the device."""
        out = DeviceParticles.__new__(DeviceParticles)
        out._n = self._n
        cu = _device.cuda()
        out._arrays = {}
        for name, arr in self._arrays.items():
            new = cu.device_array(arr.shape, dtype=arr.dtype)
            new.copy_to_device(arr)
            out._arrays[name] = new
        return out


# ---------------------------------------------------------------------------------------------
# The world's query on the device.


def _unsupported(what: str) -> NotImplementedError:
    return NotImplementedError(f"device='cuda' does not support {what}; use device='cpu'")


# Device kernel modules by world and forces (the entry keeps the forces alive, so their ids
# are not reused meanwhile).
_DEVICE_MODULES: dict = {}


def device_module(f: Any, forces: tuple = ()) -> tuple:
    """The kernel module of the world ``f`` and the fused user forces for the device:
    :mod:`fastsdf.particles.kernels`' bodies after the GPU's scene block
    (:func:`fastsdf.particles.scene_blocks.device_scene`: a query numba-cuda can compile),
    generated and cached like the CPU's (:func:`fastsdf.particles.world._kernel_module`).

    Returns ``(module, key, arrays)``: the module's ``_query_t(world, x, y, t) -> (d, dd/dx,
    dd/dy, dd/dt)`` takes the launch argument ``world`` (see :meth:`CudaStep.world_arg`);
    ``key`` names the compiled kernel; ``arrays``: the host arrays the query reads (copied to
    the device once). Raises :class:`NotImplementedError` naming a world the GPU step does not
    handle."""
    scene = device_scene(f, _unsupported)
    full_key = scene.key + tuple(id(fn) for fn in forces)
    entry = _DEVICE_MODULES.get(full_key)
    if entry is None:
        title = "# Scene block of the CUDA step (fastsdf.particles.cuda)."
        source, late = block_source(scene, tuple(forces), ahead=False, title=title)
        module, _ = generated_module(source, late, scene.key, "fastsdf_cuda_particles")
        entry = _DEVICE_MODULES[full_key] = (module, tuple(forces))
    return entry[0], full_key, list(scene.data)


# ---------------------------------------------------------------------------------------------
# The step kernel.

_KERNELS: dict = {}
#: ``numba.cuda``, once a kernel is built: the kernels name it as a module global (the
#: simulator swaps such globals for its own module while a kernel runs).
cuda: Any = None


def step_kernel(module: Any, trace: bool, key: tuple) -> Any:
    """The CUDA kernel of one device kernel module (:func:`device_module`: the world's query
    and the fused user forces), with the tunnelling sweep when ``trace`` (built once per
    ``key``).

    Launch arguments (:func:`kernel_signature`): the state (a :class:`.kernels.State` of device
    arrays, ``check_all`` True), ``BAD`` (int64, (1,): frozen particles are counted there),
    ``steps``, the call's :class:`.kernels.Physics` and :class:`.kernels.Budget` (its
    ``lip`` for the sweep), and the world's query data ``world`` (:meth:`CudaStep.world_arg`).

    One thread per particle: its checks (:func:`.kernels.phases.input_ok`, every field, as the
    CPU's first call checks them), then each step :func:`.kernels.phases.particle_step`, the
    CPU's step, with query skipping off (which changes no result) and the sweep as compiled
    (``trace``)."""
    global cuda
    kernel = _KERNELS.get(key)
    if kernel is not None:
        return kernel
    cuda = _device.cuda()
    input_ok = module.input_ok
    particle_step = module.particle_step
    switched = module.switched
    use_force = bool(module.USE_FORCE)
    if trace and module.MOVING:
        raise _unsupported("the tunnelling sweep in a moving world; pass prevent_tunnelling=False")
    sweeps = bool(trace)

    def step(state, BAD, steps, physics, budget, world):
        i = cuda.grid(1)
        if i >= state.X.shape[0]:
            return
        X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
        ok, m = input_ok(state, i, True)
        if not ok:
            FLAGS[i] = FLAG_INPUT
            cuda.atomic.add(BAD, 0, 1)
            return
        x = X[i, 0]
        y = X[i, 1]
        vx = V[i, 0]
        vy = V[i, 1]
        r = R[i]
        inv_m = 1.0 / m
        # what the thread knows as constants: no Python forces, resting contact or skipping
        own = switched(physics, physics.use_m or use_force, False, 0.0)
        thread = Budget(sweeps, budget.lip, 0.0, 0.0, False)
        flag = 0
        for k in range(steps):
            here = (x, y, vx, vy, r, m, inv_m)
            nx, ny, nvx, nvy, c, code, touched = particle_step(
                world, here, (CR, CF, i), 0.0, (0.0, 0.0, 0.0, 0.0), k, own, thread, steps
            )
            if code > 0:
                flag = code
                break
            x = nx
            y = ny
            vx = nvx
            vy = nvy
        X[i, 0] = x
        X[i, 1] = y
        V[i, 0] = vx
        V[i, 1] = vy
        if flag != 0:
            FLAGS[i] = flag
            cuda.atomic.add(BAD, 0, 1)

    kernel = _KERNELS[key] = cuda.jit(step)
    return kernel


def kernel_signature(world_arg: tuple) -> tuple:
    """The argument types of the step kernel for the world's launch argument ``world_arg``
    (see :func:`step_kernel`), e.g. to compile it ahead of a launch."""
    import numba

    one = np.zeros(1)
    state = State(
        np.zeros((1, 2)),
        np.zeros((1, 2)),
        one,
        one,
        one,
        one,
        np.zeros((0, 2)),
        np.zeros(1, dtype=np.int32),
        True,
    )
    physics = Physics(1.0, 0.0, 0.0, 0.0, 0.0, True, False, False, False, 0.0)
    budget = Budget(True, 1.0, 0.0, 0.0, False)
    return (
        numba.typeof(state),
        numba.int64[::1],
        numba.int64,
        numba.typeof(physics),
        numba.typeof(budget),
        numba.typeof(world_arg),
    )


class CudaStep:
    """The GPU step of one :class:`fastsdf.particles.ParticleSimulation` (``device='cuda'``):
    the world's query data on the device, the flags and frozen count, the compiled kernels."""

    def __init__(self, world: Any) -> None:
        _, _, arrays = device_module(world)  # checks the world (a clear error) at once
        cu = _device.cuda()
        self._world = world
        # the world's arrays on the device, once (a grid's nodes)
        self._device_arrays = {id(a): cu.to_device(a) for a in arrays}
        self.flags: Any = None
        self.bad = cu.to_device(np.zeros(1, dtype=np.int64))
        self._no_ext = cu.to_device(np.zeros((0, 2)))
        #: Steps run since the frozen count was last read (for the error's message).
        self.steps_unchecked = 0

    def world_arg(self, params: tuple) -> tuple:
        """The ``world`` launch argument: a grid's sampler data with its arrays on the device,
        an SDF's parameter values ``params`` (or a placeholder)."""
        f = self._world
        if _is_grid(f):
            return tuple(
                _kernel_array(self._device_arrays[id(a)]) if isinstance(a, np.ndarray) else a
                for a in f.sampler_data
            )
        return tuple(float(v) for v in params) if f.compiled.parametric else (0.0,)

    def run(
        self,
        p: DeviceParticles,
        steps: int,
        physics: Physics,
        user: tuple,
        budget: Budget,
        params: tuple,
    ) -> None:
        """Launch ``steps`` steps of every particle of ``p`` (asynchronous: no wait for the
        GPU) with ``physics`` (:class:`.kernels.Physics`), the fused user forces ``user``
        (numba dispatchers), ``budget`` (:class:`.kernels.Budget`: the tunnelling sweep
        ``trace`` with the world's Lipschitz bound ``lip``) and ``params``, the values of the
        world's parameters."""
        cu = _device.cuda()
        module, key, _ = device_module(self._world, tuple(user))
        kernel = step_kernel(module, budget.trace, key + (bool(budget.trace),))
        n = len(p)
        if self.flags is None or self.flags.shape[0] != n:
            self.flags = cu.to_device(np.zeros(n, dtype=np.int32))
        tpb = 32 if _device.simulated() else THREADS_PER_BLOCK
        blocks = (n + tpb - 1) // tpb
        a = p._arrays
        X, V, M, R, CR, CF = (_kernel_array(a[k]) for k in Particles.FIELDS)
        ext, flags = _kernel_array(self._no_ext), _kernel_array(self.flags)
        state = State(X, V, M, R, CR, CF, ext, flags, True)
        with ieee_compile(), warnings.catch_warnings():
            # (compiles on the first launch only; a small launch is not a performance problem
            # worth numba-cuda's under-utilisation warning here)
            for category in _performance_warnings():
                warnings.simplefilter("ignore", category)
            kernel[blocks, tpb](
                state, self.bad, int(steps), physics, budget, self.world_arg(params)
            )
        self.steps_unchecked += int(steps)

    def frozen(self) -> tuple[int, np.ndarray | None]:
        """Wait for the GPU; the count of particles frozen since the last call and their flags
        (host copies), and reset both."""
        count = int(_device.to_host(self.bad)[0])
        flags = None
        if count:
            flags = _device.to_host(self.flags)
            self.flags.copy_to_device(np.zeros_like(flags))
            self.bad.copy_to_device(np.zeros(1, dtype=np.int64))
        return count, flags


def _performance_warnings() -> list:
    """numba's and numba-cuda's NumbaPerformanceWarning classes (numba-cuda has its own)."""
    from numba.core.errors import NumbaPerformanceWarning

    found = [NumbaPerformanceWarning]
    try:
        from numba.cuda.core.errors import NumbaPerformanceWarning as cuda_warning
    except ImportError:
        return found
    return found + [cuda_warning]


def _kernel_array(a: Any) -> Any:
    """A device array as a kernel argument. Under numba-cuda's simulator an array inside a
    tuple argument reaches the CPU-compiled helpers as it is: pass the simulator's NumPy
    array there (a real device array is passed as it is)."""
    return getattr(a, "_ary", a) if _device.simulated() else a
