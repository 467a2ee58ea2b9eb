"""How good a long run's first estimate of the time left is: the README's grain block and 5,000
grains poured into a box, each in a fresh process.

    python -m bench.progress_estimates [--frames 60] [--only readme|grains5000]

For each run it prints when the first estimate was shown (seconds after the run began), the
time left it said, the time the run then really took, and their ratio (within 2x: between 0.5
and 2). The 5,000 grains (radius 2 mm +-10%, ``ContactLaw(history=True, rolling_friction=0.3)``,
``Gravity((0, -9.81))``, the stiffness derived) fall as a column into a box 0.25 m wide: cheap
frames while they fall, dear ones while they land, cheaper ones at rest. Run it on a quiet
machine: the estimate measures the machine too.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# Prepended to each run: note every update of the outermost RunProgress, report at exit.
_PRELUDE = """
import atexit as _atexit, json as _json, sys as _sys
import fastsdf.notice as _notice
_seen = []
_update = _notice.RunProgress.update
def _noted(self, done):
    _update(self, done)
    if self._outer is None:
        now = _notice._clock()
        _seen.append((now - self._start, self._done, self.total, self.shown, self.remaining(now)))
_notice.RunProgress.update = _noted
def _report():
    _sys.stderr.write("PROGRESS " + _json.dumps(_seen) + "\\n")
_atexit.register(_report)
"""

_GRAINS_5000 = """
import numpy as np
import fastsdf as sdf
from fastsdf.particles import ContactLaw, Gravity, ParticleSimulation
r, w = 0.002, 0.25
box = sdf.Halfspace([0, 1], 0.0) | sdf.Halfspace([1, 0], -w / 2) | sdf.Halfspace([-1, 0], -w / 2)
rng = np.random.default_rng(0)
gx, gy = np.meshgrid((np.arange(50) - 24.5) * 2.3 * r, 0.01 + np.arange(100) * 2.3 * r)
pos = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-0.1, 0.1, (5000, 2)) * r
law = ContactLaw(history=True, rolling_friction=0.3)
sim = ParticleSimulation(box, positions=pos, radius=r * rng.uniform(0.9, 1.1, 5000), contacts=law)
sim.force_generators += [Gravity((0, -9.81))]
sim.run(FRAMES)
"""


def _readme_grain_block() -> str:
    with open(os.path.join(REPO, "README.md"), encoding="utf-8") as fh:
        blocks = re.findall(r"```python\n(.*?)```", fh.read(), re.S)
    return next(b for b in blocks if "contacts=law" in b)


def first_estimate(source: str) -> dict:
    """Run ``source`` in a fresh process; the first estimate shown against the truth."""
    env = dict(os.environ, MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, env.get("PYTHONPATH")) if p)
    with tempfile.TemporaryDirectory() as folder:  # (where the block writes its picture)
        done = subprocess.run(
            [sys.executable, "-c", _PRELUDE + source],
            cwd=folder,
            env=env,
            capture_output=True,
            text=True,
        )
    lines = [ln for ln in done.stderr.splitlines() if ln.startswith("PROGRESS ")]
    if done.returncode or not lines:
        return {"error": done.stderr[-2000:]}
    seen = json.loads(lines[-1][len("PROGRESS ") :])
    end = seen[-1][0]
    shown = [s for s in seen if s[3]]
    if not shown:
        return {"shown": False, "run_s": end}
    at, _, _, _, left = shown[0]
    return {"shown": True, "at_s": at, "said_left_s": left, "left_s": end - at, "run_s": end}


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    ap.add_argument("--frames", type=int, default=60, help="frames of the 5,000 grains")
    ap.add_argument("--only", choices=("readme", "grains5000"))
    a = ap.parse_args()
    runs = {
        "readme": ("the README's grain block", _readme_grain_block()),
        "grains5000": (
            f"5,000 grains into a box, {a.frames} frames",
            _GRAINS_5000.replace("FRAMES", str(a.frames)),
        ),
    }
    print("| run | first estimate at (s) | said left (s) | really left (s) | ratio | run (s) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for key, (what, source) in runs.items():
        if a.only and key != a.only:
            continue
        r = first_estimate(source)
        if "error" in r:
            print(f"| {what} | failed | | | | |\n{r['error']}")
        elif not r["shown"]:
            print(f"| {what} | not shown (a short run) | | | | {r['run_s']:.1f} |")
        else:
            print(
                f"| {what} | {r['at_s']:.1f} | {r['said_left_s']:.1f} | {r['left_s']:.1f} | "
                f"{r['said_left_s'] / r['left_s']:.2f} | {r['run_s']:.1f} |"
            )


if __name__ == "__main__":
    main()
