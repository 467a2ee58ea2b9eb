"""How long each README block compiles, pasted alone into a fresh process after ``make demo``.

    python -m bench.readme_blocks [--cache DIR] [--no-demo] [--demo-particles N] [--small]

With a fresh kernel cache (``DIR``, default a new temporary folder: ``FASTSDF_CACHE_DIR`` and
``NUMBA_CACHE_DIR`` both point there), it runs ``fastsdf demo`` as ``make demo`` does (with
``--demo-particles`` particles, 20,000 by default: the kernels it compiles do not depend on the
count) and then each Python block of ``README.md`` in a fresh ``python``, and prints per block:
the seconds numba spent compiling (``numba:compile`` events, outermost), the seconds in numba's
compiler lock (compiling and loading from the cache), the wall time, and the dispatchers that
compiled, with any that compiled the same signature twice in one process. ``--small`` scales
the blocks' sizes down as the tests do. A block that compiles for more than a second after the
demo names what it compiled: the kernels the demo does not warm.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# Prepended to each block: time numba's compiles (events) and report them at exit as JSON.
_PRELUDE = """
import atexit as _atexit, collections as _collections, json as _json, sys as _sys
import threading as _threading, time as _time
from numba.core import event as _event
_T0 = _time.perf_counter()
_seen = _collections.Counter()
_log = {"compile_s": 0.0, "lock_s": 0.0, "background_s": 0.0, "compiled": [], "twice": []}
_depth = _collections.Counter()
_since = {}
class _Timer(_event.Listener):
    def on_start(self, ev):
        key = (_threading.get_ident(), ev.kind)
        if not _depth[key]:
            _since[key] = _time.perf_counter()
        _depth[key] += 1
        if ev.kind == "numba:compile" and ev.data:
            sig = (str(ev.data.get("dispatcher")), str(ev.data.get("args")))
            _seen[sig] += 1
            if _seen[sig] == 2:
                _log["twice"].append(list(sig))
    def on_end(self, ev):
        key = (_threading.get_ident(), ev.kind)
        _depth[key] -= 1
        if _depth[key]:
            return
        seconds = _time.perf_counter() - _since[key]
        main = _threading.current_thread() is _threading.main_thread()
        if ev.kind == "numba:compile":
            _log["compile_s" if main else "background_s"] += seconds
            name = getattr(ev.data.get("dispatcher"), "__name__", "?") if ev.data else "?"
            _log["compiled"].append([name + ("" if main else " (background)"), round(seconds, 2)])
        elif main:
            _log["lock_s"] += seconds
for _kind in ("numba:compile", "numba:compiler_lock"):
    _event.register(_kind, _Timer())
def _report():
    _log["wall_s"] = _time.perf_counter() - _T0
    _sys.stderr.write("READMEBLOCK " + _json.dumps(_log) + "\\n")
_atexit.register(_report)
"""


def _load_pictures_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "readme_pictures", os.path.join(REPO, "examples", "readme_pictures.py")
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(cache: str, demo: bool = True, demo_particles: int = 20_000, small: bool = False) -> list:
    """Run the demo (unless ``demo`` is False) and then each README block with the kernel
    cache ``cache``; returns one dict per block (its line, compile and lock seconds, wall
    time, what compiled, what compiled twice)."""
    pictures = _load_pictures_module()
    env = dict(os.environ, FASTSDF_CACHE_DIR=cache, NUMBA_CACHE_DIR=cache, MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, env.get("PYTHONPATH")) if p)
    if demo:
        with tempfile.TemporaryDirectory() as out:
            subprocess.run(
                [sys.executable, "-m", "fastsdf", "demo", "--particles", str(demo_particles)]
                + ["--steps", "30", "--frames", "3", "--out", out],
                env=env,
                check=True,
                capture_output=True,
            )
    with open(os.path.join(REPO, "README.md"), encoding="utf-8") as fh:
        blocks = pictures.python_blocks(fh.read())
    rows = []
    for line, source, _ in blocks:
        code = pictures.scale_down(source) if small else source
        with tempfile.TemporaryDirectory() as folder:
            script = os.path.join(folder, "block.py")
            with open(script, "w", encoding="utf-8") as fh:
                fh.write(_PRELUDE + code)
            done = subprocess.run(
                [sys.executable, script], cwd=folder, env=env, capture_output=True, text=True
            )
        report = [ln for ln in done.stderr.splitlines() if ln.startswith("READMEBLOCK ")]
        row = {"line": line, "returncode": done.returncode}
        if report:
            row.update(json.loads(report[-1][len("READMEBLOCK ") :]))
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    ap.add_argument("--cache", help="the kernel cache folder (default: a new, empty one)")
    ap.add_argument("--no-demo", action="store_true", help="do not run the demo first")
    ap.add_argument("--demo-particles", type=int, default=20_000)
    ap.add_argument("--small", action="store_true", help="the blocks' sizes scaled down")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as fresh:
        rows = run(a.cache or fresh, not a.no_demo, a.demo_particles, a.small)
    print(
        "| README block (line) | compiling (s) | in numba's compiler (s) | compiling in the "
        "background (s) | wall (s) | compiled (s) |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        if r["returncode"] != 0 or "compile_s" not in r:
            print(f"| {r['line']} | failed (exit {r['returncode']}) | | | | |")
            continue
        slow = sorted(r["compiled"], key=lambda c: -c[1])[:4]
        what = ", ".join(f"{n} {s:.1f}" for n, s in slow)
        twice = f"; twice: {r['twice']}" if r["twice"] else ""
        print(
            f"| {r['line']} | {r['compile_s']:.1f} | {r['lock_s']:.1f} | "
            f"{r['background_s']:.1f} | {r['wall_s']:.1f} | "
            f"{what}{twice} |"
        )


if __name__ == "__main__":
    main()
