"""Hard cases: damaged kernel caches, gradients exactly on boundaries and spines, subnormal and
extreme coordinates, degenerate parameters."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# ---------------------------------------------------------------------------------------------
# The kernel cache: any damaged file is detected, repaired once, and never crashes a process.

_CACHE_SCRIPT = textwrap.dedent("""
    import sys, warnings
    import numpy as np
    warnings.simplefilter("always")
    import fastsdf as sdf
    f = sdf.Circle([0.1, 0.0], 0.5) | sdf.Box([0.0, 0.0], [1.0, 1.0])
    d, g = f(np.array([0.3]), np.array([0.2]), compute_gradient=True)
    k = f.compiled.module.batch_vg_ser
    print("RESULT", repr(float(d[0])), repr(float(g[0, 0])), repr(float(g[0, 1])),
          sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()))
""")


def _run_cache_script(cache, background=False):
    env = dict(os.environ, FASTSDF_CACHE_DIR=str(cache), PYTHONPATH=ROOT,
               PYTHONWARNINGS="always")
    args = [sys.executable, "-c", _CACHE_SCRIPT]
    if background:
        return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)


def _parse(proc):
    out, err = proc.stdout, proc.stderr
    assert proc.returncode == 0, err[-3000:]
    line = [s for s in out.splitlines() if s.startswith("RESULT")][-1].split()
    return (tuple(float(v) for v in line[1:4]), int(line[4]), int(line[5]),
            err.count("fastsdf: kernel cache:"))


def _cache_files(cache):
    files = sorted(p for p in cache.rglob("*") if p.is_file() and p.suffix in (".py", ".nbi",
                                                                                ".nbc"))
    assert any(p.suffix == ".nbi" for p in files) and any(p.suffix == ".nbc" for p in files)
    return files


def _truncate(p):
    data = p.read_bytes()
    p.write_bytes(data[:len(data) // 2])


def _flip(p):
    data = bytearray(p.read_bytes())
    data[len(data) * 2 // 3] ^= 0x40
    p.write_bytes(bytes(data))


@pytest.mark.slow
def test_damaged_cache_files_are_repaired_once(tmp_path):
    """Truncated, altered, emptied and foreign files: every process gets the right answer, the
    first one repairs and reports each damaged entry once, the next one loads cleanly; then the
    same with three processes racing on a damaged cache."""
    cache = tmp_path / "cache"
    value, hits, misses, reports = _parse(_run_cache_script(cache))
    assert (hits, misses, reports) == (0, 1, 0)
    files = _cache_files(cache)
    module = [p for p in files if p.suffix == ".py"]
    point = [p for p in files if ".point_vg-" in p.name]
    batch = [p for p in files if ".batch_vg_ser-" in p.name]
    assert len(module) == 1 and len(point) == 2 and len(batch) == 2
    _truncate(module[0])
    for p in point:  # a valid index in front of an altered data file
        if p.suffix == ".nbc":
            _flip(p)
    for p in batch:  # an empty index, a data file that is not a pickle at all
        p.write_bytes(b"" if p.suffix == ".nbi" else b"\x80\x05garbage" * 5)
    repaired = _parse(_run_cache_script(cache))
    assert repaired[0] == value  # the same answer, computed afresh
    assert repaired[2:] == (1, 3)  # recompiled; module, point_vg, batch_vg_ser reported once
    again = _parse(_run_cache_script(cache))
    assert again == (value, 1, 0, 0)  # loaded from the repaired cache, nothing to report

    for p in _cache_files(cache):
        _truncate(p)
    procs = [_run_cache_script(cache, background=True) for _ in range(3)]
    for p in procs:
        p.wait(timeout=600)
        p.stdout, p.stderr = p.stdout.read(), p.stderr.read()
        assert _parse(p)[0] == value
    assert _parse(_run_cache_script(cache)) == (value, 1, 0, 0)
    assert not [p.name for p in cache.rglob("*") if ".tmp" in p.name]  # no temporary leftovers
