"""The granular engine on a CUDA GPU: ``GranularSimulation(..., device='cuda')``.

The same physics as the CPU engine (:mod:`fastsdf.granular.simulation`), written once: the
CUDA kernels here call the plain ``@njit`` functions of :mod:`fastsdf.granular.kernels`
(:func:`~fastsdf.granular.kernels.pair_force`, :func:`~fastsdf.granular.kernels.wall_force`,
:func:`~fastsdf.granular.kernels.half_kick`, :func:`~fastsdf.granular.kernels.kick_grain`),
which numba-cuda compiles again for the device, and the world's own per-point function (a
GridSDF's bilinear ``sampler`` or a static scene's ``point_vg``).

Layout: one thread per grain; the state is one (12, n) float64 array, a row per field
(structure of arrays: neighbouring threads read neighbouring addresses); the Verlet list is an
(S, n) uint32 array, slot-major (``nbr[k, i]``: the ``k``-th neighbour of grain ``i``, so a warp
reading its slot ``k`` reads consecutive words), each entry the neighbour's index and its
periodic image as on the CPU (:mod:`fastsdf.granular.cells`), unused slots
:data:`EMPTY`. The list is full (each pair at both grains): each grain gathers its own force
and writes only its own state, with no atomics; both sides of a pair compute the same bits
(see :func:`~fastsdf.granular.kernels.pair_force`). ``S`` (``max_neighbours``) is fixed; a
grain with more neighbours is reported by the rebuild (a RuntimeError naming the count found).

A substep is two kernels, as on the CPU: the elementwise kick and drift, which also raises a
device flag when a grain has moved farther than half the skin since the list was built (the
CPU's test of the largest displacement, asked as "did any grain pass": a store any thread may
make replaces the reduction), and
the force pass (half kick, gravity, pairs, the world). The host launches a batch of substeps
(:data:`CHECK_EVERY`) without waiting, then reads the flag once: every kernel after the
substep that raised it returns at once, so the host rebuilds, completes that substep's force
pass and goes on from there: the list is rebuilt at the same substeps as on the CPU.

Rebuild: the cell list by a counting sort on the device (cell counts by atomic adds, an
exclusive prefix sum over the cells, a scatter, then each cell's few grains put in index
order, so the order is deterministic and the same stable order as the CPU's sort; a
comparison sort would cost several passes over all grains for what a cell of one or two
grains settles in place); the grains reordered by cell; the list built; with history the
springs carried from the old list by matching neighbour ids (as
:func:`fastsdf.granular.cells.carry_springs`).

Memory per grain on the device (float64 state): the state 96 bytes, the grain's given index
4, float32 reference positions 8, the list ``4 S``, the cell counts about 2.5 in a dense
packing (at most ``2 n + 64`` cells), 1 for the near-the-world flag; without history an 8-byte
scratch row, so ``4 S + 120`` (148 bytes for a dense bed of equal discs, ``S = 7``); with
history one spring per slot and the list before the rebuild (``24 S``, the scratch lives in
the new list's springs), 8 bytes for the spring against the world: ``24 S + 120`` (288 bytes
at ``S = 7``); rolling resistance adds a torque per slot in both lists and one against the
world, ``16 S + 8`` (408 bytes at ``S = 7``). See
:meth:`CudaGranularSimulation.memory_per_grain`.
"""

from __future__ import annotations

import math
import time as _time
from typing import Any, NamedTuple

import numpy as np
from numba import float64, njit

from fastsdf.device import cuda, simulated
from fastsdf.fields.grid import GridSDF
from fastsdf.granular.cells import INDEX_MASK, make_grid
from fastsdf.granular.kernels import (
    Grain,
    Grains,
    Pair,
    WallPair,
    grain_mass,
    half_kick,
    image_shift,
    kick_grain,
    kinetic_energy,
    law_terms,
    pair_force,
    wall_force,
)
from fastsdf.granular.simulation import GranularSimulation
from fastsdf.notice import compiling

__all__ = ["CHECK_EVERY", "EMPTY", "CudaGranularSimulation", "default_max_neighbours"]

#: ``numba.cuda``, loaded by the first GPU engine (:func:`_load`): importing this module needs no
#: numba-cuda, so the package registers the class without it. (A module global: numba-cuda's
#: simulator swaps it inside kernels.)
cu: Any = None


def _load() -> Any:
    global cu
    if cu is None:
        cu = cuda()
    return cu


class _Kernel:
    """A CUDA kernel compiled when first launched (``kernel[grid, block](...)``)."""

    def __init__(self, fn: Any) -> None:
        self._fn = fn
        self._kernel: Any = None

    def __getitem__(self, config: Any) -> Any:
        if self._kernel is None:
            self._kernel = _load().jit(self._fn)
        return self._kernel[config]


#: An unused slot of the neighbour list.
EMPTY = 0xFFFFFFFF
#: Substeps launched between two reads of the rebuild flag (the host's only waits).
CHECK_EVERY = 32
#: Threads per block (the simulator runs each as a Python thread: fewer there).
BLOCK = 64 if simulated() else 256
#: Rows of the state array.
X, Y, VX, VY, W, R, FX, FY, TQ, PX, PY, PW = range(12)
#: Cells scanned per thread in the prefix sum.
_RUN = 64


def default_max_neighbours(r_min: float, r_max: float, skin: float) -> int:
    """Slots per grain of the neighbour list: how many grains of radius ``r_min``, overlapping
    each other by at most 1%, fit around one of ``r_max`` with their centres within ``r_max +
    r_min + skin`` (on that circle, ``pi / asin(0.99 r_min / (r_max + r_min + skin))``), times
    the rings of them a skin that wide holds (one below ``sqrt(3) r_min``): 7 for equal discs
    and a skin of 0.2 diameters."""
    reach = r_max + r_min + skin
    ring = int(math.pi / math.asin(min(0.99 * r_min / reach, 1.0)))
    return max(1, ring * (1 + int(skin / (math.sqrt(3.0) * r_min))))


def _empty(shape: Any, dtype: Any = np.float64) -> Any:
    """An uninitialised device array; under the simulator filled with poison (NaN, or a
    large integer) so that a kernel reading memory nothing wrote shows in the tests as
    it would on a GPU."""
    a = cu.device_array(shape, dtype)
    if simulated():
        host = a.copy_to_host()
        poison = np.nan if np.dtype(dtype).kind == "f" else np.int64(0x5A5A5A5A).astype(dtype)
        host[...] = poison
        a.copy_to_device(host)
    return a


def _grid(n: int) -> tuple:
    """``(blocks, threads)`` of a launch over ``n`` items: :data:`BLOCK` threads a block on
    the GPU; under the simulator no more threads than the next power of two of ``n``."""
    threads = BLOCK if not simulated() else min(BLOCK, 1 << max(n - 1, 0).bit_length())
    return max(1, (n + threads - 1) // threads), threads


# -- the world at one point -----------------------------------------------------------------


@njit(cache=True)
def _no_world(data: Any, x: float, y: float) -> tuple:
    return math.inf, 0.0, 0.0


def _scene_point(scene: Any, what: str) -> tuple:
    """A static scene's value-and-gradient device function and its tables on the device (the
    function layer's ``scene.compiled.cuda``: the CPU's point function emitted for the GPU,
    ``module.point_vg``, its tables as arguments, ``table_args()``)."""
    if getattr(scene, "param_names", ()) or getattr(scene, "time_dependent", False):
        raise ValueError(
            f"the CUDA engine takes a static world (a GridSDF, or a scene without parameters "
            f"or time), got {what}={scene!r}: sample it into a GridSDF, or use device='cpu'"
        )
    compiled = getattr(scene, "compiled", None)
    if compiled is None:
        raise TypeError(
            f"the CUDA engine takes a fastsdf Function or GridSDF as its world, got "
            f"{what}={scene!r}"
        )
    kernels = compiled.cuda
    return kernels.module.point_vg, tuple(kernels.table_args())


_AT: dict = {}


def _grid_at(sampler: Any, exact: Any) -> Any:
    """The device function of a GridSDF with ``sampler``, answering outside its bounds with
    the exact scene's point function ``exact`` (or None): one per pair (compiled once)."""
    key = ("grid", sampler, exact)
    if key in _AT:
        return _AT[key]
    if exact is not None:

        @cu.jit(device=True)
        def grid_or_exact(data: Any, x: float, y: float) -> tuple:
            d, gx, gy, inside = sampler(data[0], x, y)
            if not inside and math.isfinite(x) and math.isfinite(y):
                return exact(x, y, *data[1])
            return d, gx, gy

        _AT[key] = grid_or_exact
    else:

        @njit
        def grid(data: Any, x: float, y: float) -> tuple:
            d, gx, gy, _ = sampler(data, x, y)
            return d, gx, gy

        _AT[key] = grid
    return _AT[key]


def _scene_at(point: Any) -> Any:
    """The device function of a scene whose point function is ``point`` (tables as data)."""
    key = ("scene", point)
    if key not in _AT:

        @cu.jit(device=True)
        def scene(data: Any, x: float, y: float) -> tuple:
            return point(x, y, *data)

        _AT[key] = scene
    return _AT[key]


def _world_point(world: Any) -> tuple:
    """``(at, data)``: a device function ``at(data, x, y) -> (d, dd/dx, dd/dy)`` the kernels
    call, and its data (device arrays): a GridSDF's own ``@njit`` sampler on its nodes (with
    its exact scene outside its bounds in ``mode='exact'``), or a scene's point function. The
    functions are kept per scene code, so the kernels that call them compile once."""
    if world is None:
        return _no_world, (0.0,)
    if isinstance(world, GridSDF):
        nodes = world.device_sampler_data()
        if world.mode == "exact" and world.exact is not None:
            exact, tables = _scene_point(world.exact, "world.exact")
            return _grid_at(world.sampler, exact), (nodes, tables)
        return _grid_at(world.sampler, None), nodes
    point, tables = _scene_point(world, "world")
    return _scene_at(point), tables


# -- kernels that do not depend on the contact law ------------------------------------------


@_Kernel
def _fill_i32(a, value):
    i = cu.grid(1)
    if i < a.shape[0]:
        a[i] = value


@_Kernel
def _fill_u32(a, value):
    i = cu.grid(1)
    if i < a.shape[0]:
        a[i] = value


@_Kernel
def _bounds(st, out):
    """Min and max of x and y over the grains, ``out = (xlo, -xhi, ylo, -yhi, bad)`` (out
    starts at ``(inf, inf, inf, inf, 0)``; ``bad`` is 1 when a coordinate is not finite): each
    thread reduces a strided share, each block its threads in shared memory,
    then one atomic min per block and value (atomics per grain would all queue on four
    addresses)."""
    sh = cu.shared.array((4, BLOCK), float64)
    t = cu.threadIdx.x
    n = st.shape[1]
    a = math.inf
    b = math.inf
    c = math.inf
    e = math.inf
    i = cu.grid(1)
    while i < n:
        if not (math.isfinite(st[X, i]) and math.isfinite(st[Y, i])):
            out[4] = 1.0
        a = min(a, st[X, i])
        b = min(b, -st[X, i])
        c = min(c, st[Y, i])
        e = min(e, -st[Y, i])
        i += cu.gridsize(1)
    sh[0, t] = a
    sh[1, t] = b
    sh[2, t] = c
    sh[3, t] = e
    cu.syncthreads()
    step = cu.blockDim.x // 2
    while step > 0:
        if t < step:
            for k in range(4):
                sh[k, t] = min(sh[k, t], sh[k, t + step])
        cu.syncthreads()
        step //= 2
    if t == 0:
        for k in range(4):
            cu.atomic.min(out, k, sh[k, 0])


@_Kernel
def _keys(st, grid, keys, rank, counts):
    """Each grain's cell in ``grid`` (a :class:`~fastsdf.granular.cells.CellGrid`; x wrapped
    into the period first, as on the CPU) and its rank among its cell's grains as the atomic
    count hands it out."""
    i = cu.grid(1)
    if i < st.shape[1]:
        xi = st[X, i]
        if grid.period > 0.0:
            xi = grid.x0 + (xi - grid.x0) % grid.period
            st[X, i] = xi
        cx = min(max(int((xi - grid.x0) * grid.inv_w), 0), grid.ncx - 1)
        cy = min(max(int((st[Y, i] - grid.y0) * grid.inv_h), 0), grid.ncy - 1)
        k = cy * grid.ncx + cx
        keys[i] = k
        rank[i] = cu.atomic.add(counts, k, 1)


@_Kernel
def _scan_runs(a, m, sums, run):
    """Exclusive prefix sum within each run of ``run`` entries of ``a[:m]``; run totals into
    ``sums``."""
    t = cu.grid(1)
    lo = t * run
    if lo < m:
        hi = min(lo + run, m)
        acc = 0
        for c in range(lo, hi):
            v = a[c]
            a[c] = acc
            acc += v
        sums[t] = acc


@_Kernel
def _add_offsets(a, m, sums, run):
    c = cu.grid(1)
    if c < m:
        a[c] += sums[c // run]


@_Kernel
def _scatter(keys, rank, cell_start, perm):
    i = cu.grid(1)
    if i < keys.shape[0]:
        perm[cell_start[keys[i]] + rank[i]] = i


@_Kernel
def _order_cells(cell_start, ncells, perm):
    """Put each cell's grains in index order (an insertion sort of a handful): the stable
    order of the CPU's counting sort, whatever order the atomics handed out."""
    c = cu.grid(1)
    if c < ncells:
        lo = cell_start[c]
        hi = cell_start[c + 1]
        for a in range(lo + 1, hi):
            v = perm[a]
            b = a - 1
            while b >= lo and perm[b] > v:
                perm[b + 1] = perm[b]
                b -= 1
            perm[b + 1] = v


@_Kernel
def _gather_row(src, row, perm, out):
    i = cu.grid(1)
    if i < perm.shape[0]:
        out[i] = src[row, perm[i]]


@_Kernel
def _put_row(dst, row, src):
    i = cu.grid(1)
    if i < src.shape[0]:
        dst[row, i] = src[i]


@_Kernel
def _gather_i32(src, perm, out):
    i = cu.grid(1)
    if i < perm.shape[0]:
        out[i] = src[perm[i]]


@_Kernel
def _copy_i32(src, dst):
    i = cu.grid(1)
    if i < src.shape[0]:
        dst[i] = src[i]


@_Kernel
def _build(st, cell_start, grid, skin, nbr, flag):
    """Grain ``i``'s neighbours closer than ``R_i + R_j + skin`` in the 3 x 3 cells of ``grid``
    around its own, in cell order then index order, into its slots; a grain with more than the
    slots records its count in ``flag[1]`` (atomic max)."""
    i = cu.grid(1)
    n = st.shape[1]
    if i >= n:
        return
    x0, y0, inv_w, inv_h, ncx, ncy, period = grid
    slots = nbr.shape[0]
    xi = st[X, i]
    yi = st[Y, i]
    ri = st[R, i] + skin
    cx = min(max(int((xi - x0) * inv_w), 0), ncx - 1)
    cy = min(max(int((yi - y0) * inv_h), 0), ncy - 1)
    half = 0.5 * period
    count = 0
    for oy in range(-1, 2):
        ky = cy + oy
        if ky < 0 or ky >= ncy:
            continue
        for ox in range(-1, 2):
            kx = cx + ox
            if period > 0.0:
                kx = (kx + ncx) % ncx
            elif kx < 0 or kx >= ncx:
                continue
            cell = ky * ncx + kx
            for j in range(cell_start[cell], cell_start[cell + 1]):
                if j == i:
                    continue
                dx = xi - st[X, j]
                image = 0
                if period > 0.0:  # the nearest image (np.rint(dx / period) on the CPU)
                    if dx > half:
                        dx -= period
                        image = 1
                    elif dx < -half:
                        dx += period
                        image = 2
                dy = yi - st[Y, j]
                cut = ri + st[R, j]
                if dx * dx + dy * dy < cut * cut:
                    if count < slots:
                        nbr[count, i] = j | (image << 30)
                    count += 1
    for k in range(count, slots):
        nbr[k, i] = EMPTY
    if count > slots:
        cu.atomic.max(flag, 1, count)


@_Kernel
def _carry(perm, old_nbr, old_mem, nbr, mem):
    """Each new entry takes the memory of the same pair in the old list (new slot ``p`` was
    old slot ``perm[p]``): a search of the grain's old row; 0 for a pair not found (new)."""
    p = cu.grid(1)
    if p >= perm.shape[0]:
        return
    slots = nbr.shape[0]
    cols = mem.shape[0]
    op = perm[p]
    for k in range(slots):
        e = nbr[k, p]
        if e == EMPTY:
            break
        oq = perm[e & INDEX_MASK]
        at = -1
        for k2 in range(slots):
            e2 = old_nbr[k2, op]
            if e2 == EMPTY:
                break
            if (e2 & INDEX_MASK) == oq:
                at = k2
                break
        for c in range(cols):
            mem[c, k, p] = old_mem[c, at, op] if at >= 0 else 0.0


@_Kernel
def _set_refs(st, xref, yref):
    i = cu.grid(1)
    if i < st.shape[1]:
        xref[i] = np.float32(st[X, i])
        yref[i] = np.float32(st[Y, i])


@_Kernel
def _drift(s, flag, st, xref, yref, dt_kick, dt, density, lim):
    """The elementwise pass of substep ``s`` (see :func:`fastsdf.granular.kernels.kick_drift`);
    raises ``flag[0] = s`` when a grain has moved farther than ``sqrt(lim)`` since the list was
    built. Does nothing once an earlier substep raised it."""
    i = cu.grid(1)
    if i >= st.shape[1]:
        return
    f = flag[0]
    if f != 0 and f != s:
        return
    grain = Grain(st[X, i], st[Y, i], st[VX, i], st[VY, i], st[W, i], st[R, i], st[FX, i],
                  st[FY, i], st[TQ, i])  # fmt: skip
    x, y, vx, vy, w, px, py, pw = kick_grain(grain, dt_kick, dt, density)
    st[X, i] = x
    st[Y, i] = y
    st[VX, i] = vx
    st[VY, i] = vy
    st[W, i] = w
    st[PX, i] = px
    st[PY, i] = py
    st[PW, i] = pw
    ex = x - xref[i]
    ey = y - yref[i]
    if not ex * ex + ey * ey <= lim:
        flag[0] = s


# -- kernels of one world and one contact model ---------------------------------------------


class DeviceWorld(NamedTuple):
    """The world as the kernels take it on the device: which grains the force pass asks it
    about (``near``, int8 per grain, set at each rebuild), the grains' springs against it
    (``springs``, a row per kind as on the CPU), the data of its device function (``data``,
    see :func:`_world_point`) and the total force it exerts on the grains (``force``, 2
    float64, summed by atomics)."""

    near: Any
    springs: Any
    data: Any
    force: Any


class Model(NamedTuple):
    """The contact model's variant, constants of the compiled force pass (as ``memory is
    None`` is on the CPU): springs between grains (``history``) and their rolling torque
    (``roll``), and the same against the world."""

    history: bool
    roll: bool
    wall_history: bool
    wall_roll: bool


_KERNELS: dict = {}


def _kernels(at: Any, model: Model) -> tuple:
    """``(drift, forces, mark_near, energy)``: the kernels that call the world ``at`` and the
    contact ``model``'s variant (each compiled once per combination)."""
    key = (at, model)
    if key not in _KERNELS:
        _KERNELS[key] = (_drift, _forces_kernel(at, model), *_world_kernels(at))
    return _KERNELS[key]


_NEIGHBOUR: list = []


def _neighbour() -> Any:
    """The device function ``(st, nbr, k, i, xi, yi, period) -> (j, dx, dy)``: grain ``i``'s
    ``k``-th listed neighbour ``j`` and the offset ``(x_i, y_i) - (x_j, y_j)`` (the periodic
    image applied); ``j = -1`` past the last."""
    if not _NEIGHBOUR:

        @cu.jit(device=True)
        def neighbour(st, nbr, k, i, xi, yi, period):
            e = nbr[k, i]
            if e == EMPTY:
                return -1, 0.0, 0.0
            j = e & INDEX_MASK
            return j, xi - st[X, j] - image_shift(e, period), yi - st[Y, j]

        _NEIGHBOUR.append(neighbour)
    return _NEIGHBOUR[0]


class Centre(NamedTuple):
    """Grain ``i`` as its contacts see it, read once by the force pass: centre ``(x, y)``,
    radius ``r``, predicted velocity ``(vx, vy)`` and angular velocity ``w``."""

    x: float
    y: float
    r: float
    vx: float
    vy: float
    w: float


def _pair_sum(history: bool, roll: bool) -> Any:
    """The device function ``(st, nbr, mem, i, me, law, period) -> (fx, fy, torque)``: grain
    ``i`` (``me``, a :class:`Centre`) against its listed neighbours under ``law`` (a
    :class:`~fastsdf.granular.kernels.Law`), its springs in ``mem`` updated."""

    neighbour = _neighbour()

    @cu.jit(device=True)
    def pair_sum(st, nbr, mem, i, me, law, period):
        ri = me.r
        mi = grain_mass(ri, law.density)
        gamma_equal = law.damp * math.sqrt(0.5 * mi)
        fx = 0.0
        fy = 0.0
        tq = 0.0
        for k in range(nbr.shape[0]):
            j, dx, dy = neighbour(st, nbr, k, i, me.x, me.y, period)
            if j < 0:
                break
            pair = Pair(dx, dy, ri, st[R, j], me.vx - st[PX, j], me.vy - st[PY, j], me.w,
                        st[PW, j], i < j)  # fmt: skip
            s = 0.0
            mr = 0.0
            if history:
                s = mem[0, k, i]
                if roll:
                    mr = mem[1, k, i]
            touch, cfx, cfy, cross, s, mr = pair_force(
                pair, mi, gamma_equal, law, s, mr, history, roll
            )
            if history:
                mem[0, k, i] = s
                if roll:
                    mem[1, k, i] = mr
            if touch:
                fx += cfx
                fy += cfy
                tq += mr - ri * cross
        return fx, fy, tq

    return pair_sum


def _wall_touch(at: Any, history: bool, roll: bool) -> Any:
    """The device function ``(world, i, me, law) -> (touch, fx, fy, torque)``: grain ``i``'s
    (``me``, a :class:`Centre`) contact with the world (a :class:`DeviceWorld` whose device
    function is ``at``), its springs against it updated and its force added to
    ``world.force``."""

    @cu.jit(device=True)
    def wall_touch(world, i, me, law):
        d, gx, gy = at(world.data, me.x, me.y)
        wall = WallPair(d, gx, gy, 0.0, me.r, me.vx, me.vy, me.w)
        springs = world.springs
        s = 0.0
        mr = 0.0
        if history:
            s = springs[0, i]
            if roll:
                mr = springs[1, i]
        touch, cfx, cfy, tq, s, mr = wall_force(wall, law, s, mr, history, roll)
        if history:
            springs[0, i] = s
            if roll:
                springs[1, i] = mr
        if touch:
            cu.atomic.add(world.force, 0, cfx)
            cu.atomic.add(world.force, 1, cfy)
        return touch, cfx, cfy, tq

    return wall_touch


def _forces_kernel(at: Any, model: Model) -> Any:
    """The force pass of the world ``at`` and the contact ``model``."""
    pair_sum = _pair_sum(model.history, model.roll)
    wall_touch = _wall_touch(at, model.wall_history, model.wall_roll)

    @cu.jit
    def forces(flag, st, nbr, mem, world, law, wall, bulk):
        """The force pass (see :func:`fastsdf.granular.kernels.pair_forces` and
        :func:`~fastsdf.granular.kernels.wall_forces`): half kick, gravity, each listed pair
        (gathered by this grain alone), the world for grains near it. ``law`` and ``wall``:
        the :class:`~fastsdf.granular.kernels.Law` of the pairs and of the world, ``bulk`` a
        :class:`~fastsdf.granular.kernels.Bulk`. Does nothing when ``flag[0]`` is raised."""
        i = cu.grid(1)
        if i >= st.shape[1] or flag[0] != 0:
            return
        ri = st[R, i]
        mi = grain_mass(ri, law.density)
        vx, vy, w = half_kick(st[VX, i], st[VY, i], st[W, i], ri, st[FX, i], st[FY, i],
                              st[TQ, i], 0.5 * law.dt, law.density)  # fmt: skip
        st[VX, i] = vx
        st[VY, i] = vy
        st[W, i] = w
        me = Centre(st[X, i], st[Y, i], ri, st[PX, i], st[PY, i], st[PW, i])
        fx, fy, tq = pair_sum(st, nbr, mem, i, me, law, bulk.period)
        fx += mi * bulk.gravity_x
        fy += mi * bulk.gravity_y
        if world.near[i] != 0:
            touch, cfx, cfy, wtq = wall_touch(world, i, me, wall)
            if touch:
                fx += cfx
                fy += cfy
                tq += wtq
        st[FX, i] = fx
        st[FY, i] = fy
        st[TQ, i] = tq

    return forces


_WORLD_KERNELS: dict = {}


def _world_kernels(at: Any) -> tuple:
    """``(mark_near, energy)`` of the world ``at`` (compiled once per world function)."""
    if at in _WORLD_KERNELS:
        return _WORLD_KERNELS[at]
    neighbour = _neighbour()

    @cu.jit
    def mark_near(st, world, skin):
        """Which grains the force pass asks the world about until the next rebuild (as the
        CPU's ``d - R < skin``, NaN included); the others forget their springs."""
        i = cu.grid(1)
        if i >= st.shape[1]:
            return
        d, _, _ = at(world.data, st[X, i], st[Y, i])
        if d - st[R, i] >= skin:
            world.near[i] = 0
            for c in range(world.springs.shape[0]):
                world.springs[c, i] = 0.0
        else:
            world.near[i] = 1

    @cu.jit
    def energy(st, nbr, world, kn, wall_kn, period, out):
        """Per grain: elastic energy of its pairs with a higher index and their count, and of
        its contact with the world and whether it touches (rows 0 to 3 of ``out``)."""
        i = cu.grid(1)
        if i >= st.shape[1]:
            return
        e = 0.0
        c = 0.0
        for k in range(nbr.shape[0]):
            j, dx, dy = neighbour(st, nbr, k, i, st[X, i], st[Y, i], period)
            if j < 0:
                break
            if j <= i:
                continue
            delta = st[R, i] + st[R, j] - math.sqrt(dx * dx + dy * dy)
            if delta > 0.0:
                e += 0.5 * kn * delta * delta
                c += 1.0
        out[0, i] = e
        out[1, i] = c
        out[2, i] = 0.0
        out[3, i] = 0.0
        if world.near[i] != 0:
            d, _, _ = at(world.data, st[X, i], st[Y, i])
            delta = st[R, i] - d
            if delta > 0.0:
                out[2, i] = 0.5 * wall_kn * delta * delta
                out[3, i] = 1.0

    _WORLD_KERNELS[at] = (mark_near, energy)
    return _WORLD_KERNELS[at]


class CudaGranularSimulation(GranularSimulation, device="cuda"):
    """:class:`~fastsdf.granular.GranularSimulation` stepped on a CUDA GPU, built by
    ``GranularSimulation(..., device='cuda')``: the same parameters (``radius``, ``contacts``,
    ``wall_contacts``, ``density``, ``timestep``, ``substeps_per_contact``, ``substep``,
    ``skin``, ``periodic_x``, ``chunks``: see there), physics and accessors
    (``positions``, ``velocities``, ... are host copies, in the grains' given order); the state
    lives on the device (see the module docs). ``max_neighbours``: slots of the neighbour list
    per grain (``None``: :func:`default_max_neighbours`). The world must be static (a GridSDF,
    or a scene without parameters or time); forces beyond gravity (``external``) are not
    taken. ``grains`` is a host copy of the device state, refreshed when read after a step."""

    _stale: bool
    _dev: dict
    _host: Grains
    _host_ids: np.ndarray
    #: (the CPU's threads do not step these grains)
    tune_threads = False

    def __init__(
        self, *args: Any, max_neighbours: int | None = None, device: str = "cuda", **kwargs: Any
    ) -> None:
        _load()  # numba-cuda, or a clear error naming the extra
        self._max_neighbours_given = max_neighbours
        super().__init__(*args, **kwargs)

    # -- the host copies the base class reads -------------------------------------------------
    @property
    def grains(self) -> Grains:
        """The state as host arrays (a copy of the device's, refreshed after each step)."""
        if self._stale:
            st = self._dev["st"].copy_to_host()
            self._host = Grains(*(np.ascontiguousarray(st[k]) for k in range(12)))
            self._host_ids = self._dev["ids"].copy_to_host().astype(np.int64)
            self._stale = False
        return self._host

    @grains.setter
    def grains(self, value: Grains) -> None:
        self._host = value
        self._stale = False

    @property
    def ids(self) -> np.ndarray:
        """``ids[slot]``: the given index of the grain stored in ``slot`` (host copy)."""
        self.grains  # noqa: B018 - refreshes the host copies
        return self._host_ids

    @ids.setter
    def ids(self, value: np.ndarray) -> None:
        self._host_ids = value

    @property
    def external(self) -> Any:
        """Forces beyond gravity: not taken by the CUDA engine (always None)."""
        return None

    @external.setter
    def external(self, value: Any) -> None:
        if value is not None:
            raise TypeError(
                "the CUDA engine takes gravity only: Drag, FieldForce and @njit forces run on "
                "device='cpu'"
            )

    # -- device state ---------------------------------------------------------------------------
    def _start_engine(self) -> None:
        """The device arrays (see the module docs), the first list and forces."""
        self._stale = False
        g = self._host
        n = g.x.shape[0]
        if n >= INDEX_MASK:
            raise ValueError(f"the CUDA engine takes fewer than {INDEX_MASK} grains, got {n}")
        r = g.radius
        given = self._max_neighbours_given
        if given is None:
            slots = default_max_neighbours(float(r.min()), float(r.max()), self.skin)
        elif isinstance(given, bool) or not isinstance(given, (int, np.integer)) or given < 1:
            raise ValueError(f"max_neighbours must be an int >= 1, got max_neighbours={given!r}")
        else:
            slots = int(given)
        self.max_neighbours = slots
        self._bind_world()
        wall_cols = (2 if self.wall_contact.rolling_friction > 0 else 1) * int(
            self.wall_contact.history
        )
        cols = self._memory_cols if self._history else 0
        d: dict = {
            "st": _empty((12, n)),  # filled by _restart
            "ids": _empty(n, np.int32),
            "xref": _empty(n, np.float32),
            "yref": _empty(n, np.float32),
            "nbr": _empty((slots, n), np.uint32),
            "near": _empty(n, np.int8),
            "wmem": cu.to_device(np.zeros((wall_cols, n))),
            "counts": _empty(0, np.int32),
            "flag": cu.to_device(np.zeros(3, np.int32)),
            "wsum": cu.to_device(np.zeros(2)),
        }
        if self._history:
            # an empty list before the first: no spring to carry (the springs' memory is
            # written by the carry before it is read)
            d["mem"] = _empty((cols, slots, n))
            d["old_mem"] = _empty((cols, slots, n))
            d["old_nbr"] = _empty((slots, n), np.uint32)
            for name in ("nbr", "old_nbr"):  # (the first rebuild swaps them)
                _fill_u32[_grid(slots * n)](d[name].reshape(slots * n), EMPTY)
        else:
            d["scratch"] = _empty(n)
            d["mem"] = _empty((1, 1, 1))  # typed like the springs, never read
        self._dev = d
        self._scan_sums: dict = {}
        with compiling("the granular CUDA kernels"):
            self._restart()

    def _bind_world(self) -> None:
        """The world's device function and data, and the kernels that call it."""
        if self.moving:
            raise ValueError(
                "the CUDA engine takes a static world; a moving one (built with fastsdf.t) "
                "runs on device='cpu'"
            )
        self._at, self._wdata = _world_point(self.world)
        wall = self.wall_contact
        model = Model(
            self._history,
            self._history and self._memory_cols == 2,
            wall.history,
            wall.history and wall.rolling_friction > 0,
        )
        self._kern = _kernels(self._at, model)
        self._world_bound = self.world

    def _world(self) -> DeviceWorld:
        """The world as the kernels take it (its arrays on the device)."""
        d = self._dev
        return DeviceWorld(d["near"], d["wmem"], self._wdata, d["wsum"])

    def _restart(self) -> None:
        """Continue from the host state (after :meth:`set_state`, a new world or gravity):
        upload it, rebuild the list, predict with the current velocities and evaluate the
        forces."""
        g = self.grains
        d = self._dev
        if self.world is not self._world_bound:
            self._bind_world()
        st = np.stack([np.asarray(a, dtype=np.float64) for a in g])
        st[PX], st[PY], st[PW] = st[VX], st[VY], st[W]
        d["st"].copy_to_device(st)
        d["ids"].copy_to_device(np.asarray(self._host_ids, dtype=np.int32))
        self._stale = False
        self._rebuild()
        d["wsum"].copy_to_device(np.zeros(2))
        self._force_pass(0.0)
        self.wall_force = d["wsum"].copy_to_host()
        self._stale = True

    def _sort_scratch(self) -> Any:
        """An n-long float64 device row free during a rebuild's sort and reorder (with
        history: a row of the springs of the new list, written last)."""
        d = self._dev
        if self._history:
            return d["old_mem"][0, 0]  # becomes the new list's springs
        return d["scratch"]

    def _scan(self, a: Any, m: int, level: int = 0) -> None:
        """Exclusive prefix sum of ``a[:m]`` in place, on the device (runs of :data:`_RUN`
        per thread, their totals summed the same way, recursively; one array of totals per
        level, kept and grown as needed)."""
        runs = (m + _RUN - 1) // _RUN
        sums = self._scan_sums.get(level)
        if sums is None or sums.shape[0] < runs:
            sums = self._scan_sums[level] = _empty(max(runs + runs // 4, 1), np.int32)
        _scan_runs[_grid(runs)](a, m, sums, _RUN)
        if runs > 1:
            self._scan(sums, runs, level + 1)
            _add_offsets[_grid(m)](a, m, sums, _RUN)

    def _box(self) -> tuple:
        """``(xlo, xhi, ylo, yhi)`` of the grains (a device reduction); a FloatingPointError,
        as on the CPU, when a coordinate is not finite."""
        st = self._dev["st"]
        blocks, threads = _grid(st.shape[1])
        box = cu.to_device(np.array([np.inf, np.inf, np.inf, np.inf, 0.0]))
        _bounds[min(blocks, 1024), threads](st, box)
        xlo, mxhi, ylo, myhi, bad = box.copy_to_host()
        if bad:
            raise FloatingPointError(
                "grain positions are not finite (the simulation blew up: "
                "is the substep short enough for the stiffness?)"
            )
        return float(xlo), float(-mxhi), float(ylo), float(-myhi)

    def _rebuild(self) -> None:
        t0 = _time.perf_counter()
        d = self._dev
        st = d["st"]
        n = st.shape[1]
        launch = _grid(n)
        xlo, xhi, ylo, yhi = self._box()
        lo_hi = (np.array([xlo, xhi]), np.array([ylo, yhi]))
        grid = make_grid(
            *lo_hi, self._cutoff, self.bulk.period_x0, self.bulk.period, max_cells=2 * n + 64
        )
        ncells = grid.ncx * grid.ncy
        if d["counts"].shape[0] < ncells + 1:
            d["counts"] = _empty(ncells + ncells // 4 + 1, np.int32)
        counts = d["counts"]
        _fill_i32[_grid(ncells + 1)](counts[: ncells + 1], 0)
        scratch = self._sort_scratch()
        halves = scratch.view(np.int32)
        keys, rank = halves[:n], halves[n:]
        _keys[launch](st, grid, keys, rank, counts)
        self._scan(counts, ncells + 1)
        perm = d["xref"].view(np.int32)  # the references are written last
        _scatter[launch](keys, rank, counts, perm)
        _order_cells[_grid(ncells)](counts, ncells, perm)
        for row in range(12):
            _gather_row[launch](st, row, perm, scratch)
            _put_row[launch](st, row, scratch)
        wmem = d["wmem"]
        for row in range(wmem.shape[0]):
            _gather_row[launch](wmem, row, perm, scratch)
            _put_row[launch](wmem, row, scratch)
        ids_scratch = d["yref"].view(np.int32)
        _gather_i32[launch](d["ids"], perm, ids_scratch)
        _copy_i32[launch](ids_scratch, d["ids"])
        if self._history:  # the current list becomes the old one
            d["old_nbr"], d["nbr"] = d["nbr"], d["old_nbr"]
            d["old_mem"], d["mem"] = d["mem"], d["old_mem"]
        flag = d["flag"]
        flag.copy_to_device(np.zeros(3, np.int32))
        _build[launch](st, counts, grid, self.skin, d["nbr"], flag)
        found = int(flag.copy_to_host()[1])
        if found > self.max_neighbours:
            raise RuntimeError(
                f"a grain has {found} neighbours within R_i + R_j + skin, more than the "
                f"list's max_neighbours={self.max_neighbours} slots: pass "
                f"max_neighbours={found + 1} (or more) to GranularSimulation(..., "
                "device='cuda')"
            )
        if self._history:
            _carry[launch](perm, d["old_nbr"], d["old_mem"], d["nbr"], d["mem"])
        _set_refs[launch](st, d["xref"], d["yref"])
        # float32 references round by up to 2**-24 of the largest coordinate, per axis (x as
        # wrapped into the period)
        box = self._box() if grid.period > 0 else (xlo, xhi, ylo, yhi)
        self._ref_margin = 2.5e-7 * max(abs(v) for v in box)
        _, _, mark_near, _ = self._kern
        mark_near[launch](st, self._world(), self.skin)
        self.grid = grid
        self.rebuilds += 1
        self._stale = True
        self.timings["rebuild"] += _time.perf_counter() - t0

    def _laws(self, dt: float) -> tuple:
        """The :class:`~fastsdf.granular.kernels.Law` of the pairs and of the world for a
        substep ``dt``."""
        density = self.bulk.density
        return law_terms(self.contact, density, dt), law_terms(self.wall_contact, density, dt)

    def _force_pass(self, dt: float) -> None:
        d = self._dev
        law, wall = self._laws(dt)
        _, forces, _, _ = self._kern
        forces[_grid(d["st"].shape[1])](
            d["flag"], d["st"], d["nbr"], d["mem"], self._world(), law, wall, self.bulk
        )

    def _advance(self, substeps: int) -> None:
        d = self._dev
        st, flag = d["st"], d["flag"]
        launch = _grid(st.shape[1])
        drift, forces, _, _ = self._kern
        drift, forces = drift[launch], forces[launch]  # configured once per call
        dt = self.substep
        law, wall = self._laws(dt)
        world = self._world()
        density = self.density
        zeros = np.zeros(3, np.int32)
        d["wsum"].copy_to_device(np.zeros(2))
        done = 0
        t0 = _time.perf_counter()
        while done < substeps:
            lim = max(0.5 * self.skin - self._ref_margin, 0.0) ** 2
            batch = min(CHECK_EVERY, substeps - done)
            flag.copy_to_device(zeros)
            for b in range(1, batch + 1):
                kick = 0.0 if done + b == 1 else 0.5 * dt
                drift(b, flag, st, d["xref"], d["yref"], kick, dt, density, lim)
                forces(flag, st, d["nbr"], d["mem"], world, law, wall, self.bulk)
            raised = int(flag.copy_to_host()[0])
            if raised == 0:
                done += batch
                continue
            # substep `raised` drifted past half the skin: rebuild, then its force pass
            self._rebuild()
            flag.copy_to_device(zeros)
            self._force_pass(dt)
            done += raised
        if substeps:
            drift(1, flag, st, d["xref"], d["yref"], 0.5 * dt, 0.0, density, np.inf)
            self.wall_force = d["wsum"].copy_to_host() / substeps
        cu.synchronize()
        for _ in range(substeps):  # summed as the CPU engine sums it
            self.time += dt
        self.timings["integrate"] += _time.perf_counter() - t0
        self._stale = True

    # -- observables --------------------------------------------------------------------------
    def energy(self) -> dict:
        """As :meth:`GranularSimulation.energy`, the contacts' energy computed on the device."""
        rows = self._contact_rows()
        kinetic, rotational, potential = kinetic_energy(self.grains, self.bulk)
        ee, _, ew, _ = (float(rows[k].sum()) for k in range(4))
        tangential, rolling = self._spring_energy() if self._history else (0.0, 0.0)
        parts = {
            "kinetic": float(kinetic),
            "rotational": float(rotational),
            "potential": float(potential),
            "normal_springs": ee + ew,
            "tangential_springs": tangential,
            "rolling_springs": rolling,
        }
        parts["total"] = sum(parts.values())
        return parts

    def contact_counts(self) -> tuple[int, int]:
        """As :meth:`GranularSimulation.contact_counts`, counted on the device."""
        rows = self._contact_rows()
        return int(round(float(rows[1].sum()))), int(round(float(rows[3].sum())))

    def _contact_rows(self) -> np.ndarray:
        """Per grain, from the device: the normal springs' energy of its pairs with a higher
        index and their count, and of its wall contact and whether it touches (4 rows)."""
        d = self._dev
        n = d["st"].shape[1]
        out = _empty((4, n))
        self._kern[3][_grid(n)](
            d["st"],
            d["nbr"],
            self._world(),
            float(self.contact.stiffness),  # type: ignore[arg-type]
            float(self.wall_contact.stiffness),  # type: ignore[arg-type]
            self.bulk.period,
            out,
        )
        return out.copy_to_host()

    def _spring_energy(self) -> tuple[float, float]:
        """``(tangential, rolling)`` energy held in the springs (on the host: the same terms
        as :func:`fastsdf.granular.kernels.pair_energy` and ``wall_energy``)."""
        i, j, slot = self._host_list()
        keep = i < j  # each pair listed at both grains: counted once
        i, j, slot = i[keep], j[keep], slot[keep]
        r = self.grains.radius
        pair_springs = [m[slot, i] for m in self._dev["mem"].copy_to_host()]
        tangential, rolling = _springs_energy(
            self.contact, pair_springs, r[i] * r[j] / (r[i] + r[j])
        )
        wmem = self._dev["wmem"]
        if wmem.shape[0]:  # (storage order, as the grains' host arrays)
            wt, wr = _springs_energy(self.wall_contact, list(wmem.copy_to_host()), r)
            tangential, rolling = tangential + wt, rolling + wr
        return tangential, rolling

    def _host_list(self) -> tuple:
        """``(i, j, slot)`` of every listed pair (both sides), in storage slots."""
        nbr = self._dev["nbr"].copy_to_host()
        slot, i = np.nonzero(nbr != EMPTY)
        j = (nbr[slot, i] & INDEX_MASK).astype(np.int64)
        return i.astype(np.int64), j, slot

    def neighbour_pairs(self) -> np.ndarray:
        """The pairs ``(i, j)``, ``i < j``, of the current Verlet list, in the grains' given
        numbering, as an (m, 2) int64 array sorted by rows."""
        i, j, _ = self._host_list()
        ids = self.ids
        a, b = ids[i], ids[j]
        pairs = np.unique(np.stack([np.minimum(a, b), np.maximum(a, b)], 1), axis=0)
        return pairs.reshape(-1, 2)

    def tangential_springs(self) -> tuple:
        """As :meth:`GranularSimulation.tangential_springs` (each pair once)."""
        if not self._history:
            raise ValueError("tangential_springs needs contacts=ContactLaw(..., history=True)")
        i, j, slot = self._host_list()
        s = self._dev["mem"][0].copy_to_host()[slot, i]
        ids = self.ids
        a, b = ids[i], ids[j]
        pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], 1)
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        pairs, s = pairs[order], s[order]
        first = np.ones(len(pairs), np.bool_)
        first[1:] = np.any(pairs[1:] != pairs[:-1], axis=1)
        wall = np.zeros(ids.shape[0])
        wmem = self._dev["wmem"]
        if wmem.shape[0]:
            wall[ids] = wmem[0].copy_to_host()
        return pairs[first], s[first], wall

    def memory_per_grain(self) -> float:
        """Bytes held on the device per grain: state, list (and springs), cells, references
        (see the module docs)."""
        d = self._dev
        total = sum(a.size * a.dtype.itemsize for a in d.values())
        total += sum(a.size * a.dtype.itemsize for a in self._scan_sums.values())
        return total / d["st"].shape[1]

    def __getstate__(self) -> dict:
        self.grains  # noqa: B018 - the host copies, current
        state = self.__dict__.copy()
        state["_dev"] = {k: v.copy_to_host() for k, v in self._dev.items()}
        for k in ("_kern", "_at", "_wdata", "_scan_sums", "_world_bound"):
            state.pop(k, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._bind_world()
        self._dev = {k: cu.to_device(v) for k, v in self._dev.items()}
        self._scan_sums = {}
        self._stale = True

    def __repr__(self) -> str:
        return (
            super().__repr__().replace("GranularSimulation(", "GranularSimulation(device='cuda', ")
        )


def _springs_energy(law: Any, springs: list, r_eff: np.ndarray) -> tuple[float, float]:
    """``(k_t s**2 / 2, M**2 / (2 k_r))`` summed over springs (``springs[0]``: tangential
    stretches; ``springs[1]``, with rolling resistance: torques) of contacts of effective
    radii ``r_eff``: the terms of :func:`fastsdf.granular.kernels.pair_energy`."""
    kn = float(law.stiffness)
    tangential = 0.5 * law.tangential_stiffness * kn * float(np.sum(springs[0] ** 2))
    mu_r = law.rolling_friction
    if mu_r > 0.0 and len(springs) > 1:
        k_r = 2.25 * kn * mu_r * mu_r * r_eff * r_eff
        return tangential, float(np.sum(0.5 * springs[1] ** 2 / k_r))
    return tangential, 0.0
