"""Instruction mix of the compiled particle step of a grid world.

    python -m bench.step_asm

Compiles the kernels afresh in a temporary cache directory (numba cannot show the assembly of
code loaded from its cache) and counts:

* in the particle-by-particle step (``_block`` and the functions it calls out of line: the
  sweep ``swept``, the march): the instructions, branches, calls, scalar (``sd``) and packed
  (``pd``) double arithmetic, and whether any vector register or gather is used;
* in the block kernel's passes (``_simd_*`` of the ``simd`` variant of ``step_ser``, see
  :mod:`fastsdf.particles.kernels`): each
  pass's innermost loop, its instructions per particle (a loop iteration handles 4 particles
  where it is vectorized), its ymm (256-bit) instructions and square roots/divisions, and the
  masked stores (``vmaskmovpd``, microcoded and slow on AMD Zen 2) of the whole function.

The limit analysis in ``bench/results/particles.md`` uses these counts.
"""

import collections
import os
import re
import tempfile


def _per_iteration(body: list) -> int:
    """Particles per loop iteration, from the loop counter's step (bytes of a float64 row, or
    an index)."""
    for x in body:
        m = re.match(r"^(?:add|sub)q\s+\$(-?\d+), %r", x)
        if m:
            k = abs(int(m.group(1)))
            return k // 8 if k >= 32 else k
    return 1


def _hot_loops(asm: str) -> list:
    """(instructions, ymm instructions, square roots and divisions, particles per iteration)
    of each backward-jumping loop of the first function in ``asm``, longest first."""
    lines = asm.split(".Lfunc_end0")[0].splitlines()
    labels = {m.group(1): i for i, l in enumerate(lines) if (m := re.match(r"^(\.LBB\S+):", l))}
    out = []
    for i, line in enumerate(lines):
        m = re.match(r"^\s+j\w+\s+(\.LBB\S+)", line)
        if m and labels.get(m.group(1), i) < i:
            body = [
                x.strip()
                for x in lines[labels[m.group(1)] : i + 1]
                if x.startswith("\t") and not x.startswith("\t.")
            ]
            out.append(
                (
                    len(body),
                    sum("ymm" in x for x in body),
                    sum(x.startswith(("vsqrt", "vdiv")) for x in body),
                    _per_iteration(body),
                )
            )
    return sorted(out, reverse=True)


def main() -> None:
    os.environ["FASTSDF_CACHE_DIR"] = tempfile.mkdtemp(prefix="fastsdf_asm_")
    import fastsdf as sdf
    import fastsdf.particles as phys
    from fastsdf.shapes.scenes import seed_world

    g = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    sim = phys.ParticleSimulation(g, n=100, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.engine.simd = False
    sim.run(1)  # serial path: n < PARALLEL_MIN_PARTICLES, the general variant
    kernel = sim.engine.kernel()[0].step_ser
    asm = kernel.inspect_asm(kernel.signatures[0])
    funcs, cur = {}, None
    for line in asm.splitlines():
        m = re.match(r"^([A-Za-z_$][^\s:]*):", line)
        if m:
            cur = m.group(1)
            funcs[cur] = []
        elif cur and line.startswith("\t") and not line.startswith("\t."):
            funcs[cur].append(line.split()[0])
    print("particle-by-particle step (step_ser, the general variant)")
    print(
        f"{'function':12s} {'instr':>6s} {'branches':>8s} {'calls':>6s} {'mul/add sd':>10s} "
        f"{'div sd':>6s} {'sqrt sd':>7s} {'pd ops':>6s} {'gathers':>7s}"
    )
    for name, ops in funcs.items():
        short = next((k for k in ("_block_of", "_block", "swept", "_march") if k in name), None)
        if short is None:
            continue
        c = collections.Counter(ops)
        text = " ".join(ops)
        print(
            f"{short:12s} {len(ops):6d} {sum(v for k, v in c.items() if k.startswith('j')):8d} "
            f"{c['call'] + c['callq']:6d} "
            f"{sum(c[k] for k in ('vmulsd', 'vaddsd', 'vsubsd')):10d} {c['vdivsd']:6d} "
            f"{c['vsqrtsd']:7d} {sum(v for k, v in c.items() if k.endswith('pd')):6d} "
            f"{text.count('gather'):7d}"
        )

    # The block kernel, in the peers' configuration and with the defaults.
    for kw in ({"prevent_tunnelling": False}, {}):
        s = phys.ParticleSimulation(g, n=100, seed=0, **kw)
        s.force_generators.append(phys.Gravity())
        s.engine.skip = bool(kw == {})
        s.run(1)
    mod = sim.engine.kernel()[0]
    print("\nblock kernel (the simd variant): innermost loop of each pass")
    print(
        f"{'pass':26s} {'instr/particle':>14s} {'ymm':>5s} {'sqrt+div':>8s} {'masked st':>9s}"
        "   (ymm, sqrt+div: per loop iteration)"
    )
    for name in (
        "_simd_move_plain",
        "_simd_move_budget",
        "_simd_gather_all",
        "_simd_gather_some",
        "_simd_respond_all_plain",
        "_simd_respond_none_plain",
        "_simd_respond_all",
        "_simd_respond_none",
        "_simd_commit",
    ):
        d = getattr(mod, name)
        if not d.signatures:
            continue
        a = d.inspect_asm(d.signatures[0])
        loops = _hot_loops(a)
        if not loops:
            continue
        n, ymm, sd, k = loops[0]
        per = n / k
        print(f"{name:26s} {per:14.1f} {ymm:5d} {sd:8d} {a.count('vmaskmov'):9d}")


if __name__ == "__main__":
    main()
