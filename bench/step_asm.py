"""Instruction mix of the compiled particle step (the generated ``_block`` of a grid world).

    python -m bench.step_asm

Compiles the kernel afresh in a temporary cache directory (numba cannot show the assembly of
code loaded from its cache) and counts, in ``_block`` and the functions it calls out of line,
the instructions, branches, calls, scalar (``sd``) and packed (``pd``) double arithmetic, and
whether any vector register or gather is used. The limit analysis in
``bench/results/particles.md`` uses these counts.
"""

import collections
import os
import re
import tempfile


def main() -> None:
    os.environ["FASTSDF_CACHE_DIR"] = tempfile.mkdtemp(prefix="fastsdf_asm_")
    import fastsdf as sdf
    import fastsdf.particles as phys
    from fastsdf.scenes import seed_world

    g = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    sim = phys.ParticleSimulation(g, n=100, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.run(1)                                  # serial path: n < PARALLEL_MIN_PARTICLES
    kernel = sim._module.run_ser
    asm = kernel.inspect_asm(kernel.signatures[0])
    funcs, cur = {}, None
    for line in asm.splitlines():
        m = re.match(r"^([A-Za-z_$][^\s:]*):", line)
        if m:
            cur = m.group(1)
            funcs[cur] = []
        elif cur and line.startswith("\t") and not line.startswith("\t."):
            funcs[cur].append(line.split()[0])
    print(f"{'function':12s} {'instr':>6s} {'branches':>8s} {'calls':>6s} {'mul/add sd':>10s} "
          f"{'div sd':>6s} {'sqrt sd':>7s} {'pd ops':>6s} {'gathers':>7s}")
    for name, ops in funcs.items():
        short = next((k for k in ("_block", "_sweep", "_march") if k in name), None)
        if short is None:
            continue
        c = collections.Counter(ops)
        text = " ".join(ops)
        print(f"{short:12s} {len(ops):6d} {sum(v for k, v in c.items() if k.startswith('j')):8d} "
              f"{c['call'] + c['callq']:6d} "
              f"{sum(c[k] for k in ('vmulsd', 'vaddsd', 'vsubsd')):10d} {c['vdivsd']:6d} "
              f"{c['vsqrtsd']:7d} {sum(v for k, v in c.items() if k.endswith('pd')):6d} "
              f"{text.count('gather'):7d}")


if __name__ == "__main__":
    main()
