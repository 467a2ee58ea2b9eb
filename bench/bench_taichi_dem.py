"""Granular matter: the dense bed of ``bench_granular`` in Taichi, the structure of the Taichi DEM
demo (taichi-dev/taichi_dem, ``dem.py``) with the same contact law, against fastsdf, same run.

    python -m bench.bench_taichi_dem [--sizes 1e4 1e5] [--blocks 3]

The peer follows ``dem.py``: every step a cell grid is rebuilt by counting grains per cell
(atomic adds), a prefix sum and a scatter of grain ids (a counting sort), and each grain scans
the 3x3 cells around it, resolving each pair once (``j > i``) and adding the force to both grains
with atomic adds. Its contact law is the demo's normal spring-dashpot, to which the tangential
law of ``gran/hooke`` is added as fastsdf states it (viscous ``gamma_t = gamma_n / 2`` capped by
``mu |F_n|``, torques, rotation), the floor at y = 0 the same contact, x periodic, velocity
Verlet with the same predicted velocity in the dashpots. CPU backend, float64, 2 threads
(``cpu_max_num_threads``); fastsdf history-free (``gran/hooke``) with numba's threads. The two
take turns, block after block of steps.
"""

import argparse
import math
import os
import sys
import time

import numba
import numpy as np

from .bench_granular import DT, GAMMA_N, KN, MU, hex_bed, ours

SLOTS = 6  # contact springs kept per grain (pairs j > i): a dense bed of equal discs needs 3


def taichi_bed(n: int, threads: int, history: bool = False):
    import taichi as ti

    ti.init(arch=ti.cpu, default_fp=ti.f64, cpu_max_num_threads=threads, log_level=ti.WARN)
    pos, period = hex_bed(n)
    n = len(pos)
    rad = 0.5
    mass = math.pi * rad * rad
    cell = 2 * rad * 1.05
    ncx = int(period // cell)
    cw = period / ncx
    ncy = int((pos[:, 1].max() + 5) // cell) + 1
    x = ti.Vector.field(2, ti.f64, n)
    v = ti.Vector.field(2, ti.f64, n)
    p = ti.Vector.field(2, ti.f64, n)  # predicted velocity
    f = ti.Vector.field(2, ti.f64, n)
    w = ti.field(ti.f64, n)
    pw = ti.field(ti.f64, n)
    tq = ti.field(ti.f64, n)
    count = ti.field(ti.i32, ncx * ncy)
    start = ti.field(ti.i32, ncx * ncy + 1)
    fill = ti.field(ti.i32, ncx * ncy)
    ids = ti.field(ti.i32, n)
    partner = ti.field(ti.i32, (n, SLOTS))  # history: the other grain of each spring, -1: free
    spring = ti.field(ti.f64, (n, SLOTS))
    wall_spring = ti.field(ti.f64, n)
    partner.fill(-1)
    x.from_numpy(pos)
    kt = KN * 2.0 / 7.0
    gn_pair = GAMMA_N * mass / 2  # LAMMPS's gamma_n times m_eff
    gn_wall = GAMMA_N * mass
    inertia = 0.5 * mass * rad * rad

    @ti.func
    def contact(delta, nrm, vr, wr, gamma_n):
        vn = vr.dot(nrm)
        reach = abs(vn) * DT
        g = gamma_n
        if reach > 2.0 * delta:
            g *= 0.5 + delta / reach
        fn = KN * delta - g * vn
        vt = vr - vn * nrm + wr * ti.Vector([nrm[1], -nrm[0]])
        gt = 0.5 * g
        cap = abs(MU * fn)
        ft = -gt * vt
        if ft.norm_sqr() > cap * cap:
            ft = -cap * vt / vt.norm()
        return fn * nrm + ft, ft

    @ti.func
    def contact_history(delta, nrm, vr, wr, gamma_n, sp):
        """As fastsdf's ``_contact_history``: the stretch ``sp`` along t = (-n_y, n_x)."""
        vn = vr.dot(nrm)
        reach = abs(vn) * DT
        g = gamma_n
        if reach > 2.0 * delta:
            g *= 0.5 + delta / reach
        fn = KN * delta - g * vn
        t = ti.Vector([-nrm[1], nrm[0]])
        vts = vr.dot(t) - wr
        sp += vts * DT
        gt = 0.5 * g
        ft = -(kt * sp + gt * vts)
        cap = abs(MU * fn)
        if abs(ft) > cap:
            r = cap / abs(ft)
            lag = gt * vts / kt
            sp = r * (sp + lag) - lag
            ft *= r
        return fn * nrm + ft * t, ft * t, sp

    @ti.kernel
    def kick_drift(dt_kick: ti.f64, dt: ti.f64):
        for i in x:
            a = f[i] / mass
            al = tq[i] / inertia
            v[i] += a * dt_kick
            w[i] += al * dt_kick
            p[i] = v[i] + a * dt
            pw[i] = w[i] + al * dt
            x[i] += (v[i] + 0.5 * a * dt) * dt
            x[i][0] = x[i][0] - period * ti.floor(x[i][0] / period)

    @ti.kernel
    def grid():
        for c in count:
            count[c] = 0
        for i in x:
            cx = ti.min(int(x[i][0] / cw), ncx - 1)
            cy = ti.max(ti.min(int(x[i][1] / cell), ncy - 1), 0)
            ti.atomic_add(count[cy * ncx + cx], 1)
        ti.loop_config(serialize=True)
        for c in range(ncx * ncy):  # prefix sum (dem.py: per column, then rows)
            start[c + 1] = start[c] + count[c]
        for c in count:
            fill[c] = start[c]
        for i in x:
            cx = ti.min(int(x[i][0] / cw), ncx - 1)
            cy = ti.max(ti.min(int(x[i][1] / cell), ncy - 1), 0)
            k = ti.atomic_add(fill[cy * ncx + cx], 1)
            ids[k] = i

    @ti.kernel
    def forces(dt_half: ti.f64):
        for i in x:
            v[i] += f[i] / mass * dt_half
            w[i] += tq[i] / inertia * dt_half
            f[i] = ti.Vector([0.0, -mass])
            tq[i] = 0.0
        for i in x:
            cx = ti.min(int(x[i][0] / cw), ncx - 1)
            cy = ti.max(ti.min(int(x[i][1] / cell), ncy - 1), 0)
            seen = 0  # history: the slots whose pair is in contact this step (bits)
            for ox, oy in ti.static(ti.ndrange((-1, 2), (-1, 2))):
                ky = cy + oy
                if 0 <= ky < ncy:
                    kx = (cx + ox + ncx) % ncx
                    c = ky * ncx + kx
                    for k in range(start[c], start[c + 1]):
                        j = ids[k]
                        if j > i:
                            d = x[i] - x[j]
                            d[0] -= period * ti.round(d[0] / period)
                            r2 = d.norm_sqr()
                            if r2 < 4 * rad * rad:
                                dist = ti.sqrt(r2)
                                nrm = d / dist
                                fc = ti.Vector([0.0, 0.0])
                                ft = ti.Vector([0.0, 0.0])
                                if ti.static(history):
                                    slot = -1
                                    free = -1
                                    for q in range(SLOTS):
                                        if partner[i, q] == j:
                                            slot = q
                                        elif partner[i, q] < 0 and free < 0:
                                            free = q
                                    if slot < 0:
                                        slot = free
                                        partner[i, slot] = j
                                        spring[i, slot] = 0.0
                                    seen |= 1 << slot
                                    fc, ft, sp = contact_history(
                                        2 * rad - dist,
                                        nrm,
                                        p[i] - p[j],
                                        rad * (pw[i] + pw[j]),
                                        gn_pair,
                                        spring[i, slot],
                                    )
                                    spring[i, slot] = sp
                                else:
                                    fc, ft = contact(
                                        2 * rad - dist,
                                        nrm,
                                        p[i] - p[j],
                                        rad * (pw[i] + pw[j]),
                                        gn_pair,
                                    )
                                cross = nrm[0] * ft[1] - nrm[1] * ft[0]
                                f[i] += fc
                                f[j] -= fc
                                tq[i] -= rad * cross
                                tq[j] -= rad * cross
            if ti.static(history):
                for q in range(SLOTS):  # pairs that parted forget their spring
                    if (seen >> q) & 1 == 0:
                        partner[i, q] = -1
            if x[i][1] < rad:  # the floor
                nrm = ti.Vector([0.0, 1.0])
                fc = ti.Vector([0.0, 0.0])
                ft = ti.Vector([0.0, 0.0])
                if ti.static(history):
                    fc, ft, sp = contact_history(
                        rad - x[i][1], nrm, p[i], rad * pw[i], gn_wall, wall_spring[i]
                    )
                    wall_spring[i] = sp
                else:
                    fc, ft = contact(rad - x[i][1], nrm, p[i], rad * pw[i], gn_wall)
                f[i] += fc
                tq[i] -= rad * (nrm[0] * ft[1] - nrm[1] * ft[0])
            elif ti.static(history):
                wall_spring[i] = 0.0

    def step(k: int) -> None:
        for _ in range(k):
            kick_drift(0.5 * DT, DT)
            grid()
            forces(0.5 * DT)
        ti.sync()

    # first force evaluation, as fastsdf's constructor does
    p.from_numpy(np.zeros((n, 2)))
    grid()
    forces(0.0)
    kick_drift(0.0, 0.0)

    def mean_height() -> float:
        return float(x.to_numpy()[:, 1].mean())

    return step, n, mean_height


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e4, 1e5])
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--history", action="store_true", help="tangential springs on both sides")
    a = ap.parse_args()
    threads = numba.get_num_threads()
    load0 = os.getloadavg()[0]
    for n in (int(s) for s in a.sizes):
        step, nt, height = taichi_bed(n, threads, a.history)
        sim = ours(n, a.history)
        steps = max(20, int(1e6 // n))
        step(steps)
        sim.advance(steps)
        rt, ro = [], []
        for _ in range(a.blocks):
            t0 = time.perf_counter()
            step(steps)
            rt.append(nt * steps / (time.perf_counter() - t0))
            t0 = time.perf_counter()
            sim.advance(steps)
            ro.append(nt * steps / (time.perf_counter() - t0))
        print(
            f"{nt:,} discs, {threads} threads, {'history' if a.history else 'history-free'}: "
            f"fastsdf {np.median(ro) / 1e6:.2f} M "
            f"({max(ro) / 1e6:.2f}), Taichi {np.median(rt) / 1e6:.2f} M ({max(rt) / 1e6:.2f}) "
            f"particle-steps/s; ratio {np.median(ro) / np.median(rt):.2f}x; mean height after "
            f"{sim.time / DT:.0f} steps: fastsdf {sim.grains.y.mean():.6f}, Taichi {height():.6f}",
            flush=True,
        )
    print(f"load {load0:.1f} -> {os.getloadavg()[0]:.1f}", file=sys.stderr)


if __name__ == "__main__":
    main()
