"""Trajectory files: H5MD layout, read back by fastsdf and by pyh5md, frames survive a kill."""

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from fastsdf.io import TrajectoryRecorder, read_trajectory

h5py = pytest.importorskip("h5py")


class FakeSim:
    """The attributes a recorder reads (p, t, dt) and a run that moves particles predictably."""

    def __init__(self, n=50, dt=0.1):
        self.p = {
            "x": np.zeros((n, 2)),
            "v": np.ones((n, 2)),
            "m": np.full(n, 2.0),
            "r": np.full(n, 0.01),
        }
        self.p["x"][:, 0] = np.arange(n)
        self.t, self.dt, self.calls = 0.0, dt, []

    def run(self, k):
        self.calls.append(k)
        for _ in range(k):
            self.p["x"] += self.dt * self.p["v"]
            self.t += self.dt


def test_layout_is_h5md_and_reads_back(tmp_path):
    sim = FakeSim()
    path = tmp_path / "traj.h5"
    with TrajectoryRecorder(path, every=4, fields=("position", "velocity"), author="Ada") as rec:
        rec.run(sim, 10)
    assert sim.calls == [4, 4, 2]
    with h5py.File(path, "r") as f:
        assert list(f["h5md"].attrs["version"]) == [1, 1]
        assert f["h5md/author"].attrs["name"] == "Ada"
        assert f["h5md/creator"].attrs["name"] == "fastsdf"
        assert f["particles/all/box"].attrs["dimension"] == 2
        pos = f["particles/all/position"]
        assert pos["value"].shape == (4, 50, 2) and pos["value"].chunks[0] == 1
        np.testing.assert_array_equal(pos["step"][()], [0, 4, 8, 10])
        # step and time are shared (hard links), as H5MD allows
        assert f["particles/all/velocity/step"] == pos["step"]
    traj = read_trajectory(path)
    np.testing.assert_allclose(traj["time"], [0.0, 0.4, 0.8, 1.0])
    expected_x0 = np.arange(50)[None, :] + traj["time"][:, None]
    np.testing.assert_allclose(traj["position"][:, :, 0], expected_x0, atol=1e-12)
    assert traj["velocity"].shape == (4, 50, 2)


def test_pyh5md_reads_the_file(tmp_path):
    pyh5md = pytest.importorskip("pyh5md")
    sim = FakeSim()
    path = tmp_path / "traj.h5"
    with TrajectoryRecorder(path, every=5, fields=("position", "mass")) as rec:
        rec.run(sim, 15)
    with pyh5md.File(str(path), "r") as f:
        group = f.particles_group("all")
        pos = pyh5md.element(group, "position")
        np.testing.assert_array_equal(pos.step[()], [0, 5, 10, 15])
        np.testing.assert_allclose(pos.time[()], [0.0, 0.5, 1.0, 1.5])
        np.testing.assert_allclose(pos.value[-1], sim.p["x"])
        np.testing.assert_array_equal(pyh5md.element(group, "mass").value[2], sim.p["m"])


def test_real_simulation_bit_for_bit(tmp_path):
    from fastsdf.particles import Gravity, ParticleSimulation
    from fastsdf.shapes import Halfspace

    def make():
        s = ParticleSimulation(Halfspace([0.0, 1.0], -1.0), n=200, seed=4)
        s.force_generators.append(Gravity())
        return s

    sim, ref = make(), make()
    with TrajectoryRecorder(tmp_path / "t.h5", every=3, fields="position") as rec:
        rec.run(sim, 9)
    traj = read_trajectory(tmp_path / "t.h5")
    frames = [ref.p["x"].copy()]
    for _ in range(3):
        ref.run(3)
        frames.append(ref.p["x"].copy())
    np.testing.assert_array_equal(traj["position"], np.array(frames))
    assert traj["position"].dtype == np.float64


def test_float32_storage_and_bad_arguments(tmp_path):
    sim = FakeSim()
    with TrajectoryRecorder(tmp_path / "t.h5", dtype="float32") as rec:
        rec.record(sim)
    assert read_trajectory(tmp_path / "t.h5")["position"].dtype == np.float32
    for kw, word in (
        ({"every": 0}, "every"),
        ({"fields": ("pos",)}, "fields"),
        ({"group": "a/b"}, "group"),
        ({"dtype": "int32"}, "dtype"),
    ):
        with pytest.raises(ValueError, match=word):
            TrajectoryRecorder(tmp_path / "x.h5", **kw)
    rec = TrajectoryRecorder(tmp_path / "y.h5")
    rec.record(sim)
    sim.p["x"] = np.zeros((3, 2))
    with pytest.raises(ValueError, match="shape"):
        rec.record(sim)
    rec.close()


WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from types import SimpleNamespace
    from fastsdf.io import TrajectoryRecorder
    n = 20000
    sim = SimpleNamespace(p={"x": np.zeros((n, 2))}, t=0.0, dt=1.0)
    rec = TrajectoryRecorder(sys.argv[1], every=1)
    k = 0
    while True:
        sim.p["x"][:] = k          # frame k holds the value k everywhere
        sim.t = float(k)
        rec.record(sim)
        print(k, flush=True)       # frame k is flushed
        k += 1
""")


@pytest.mark.slow
def test_frames_flushed_before_a_kill_survive(tmp_path):
    path = str(tmp_path / "killed.h5")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, path], stdout=subprocess.PIPE, text=True, env=env
    )
    flushed = -1
    for line in proc.stdout:
        flushed = int(line)
        if flushed >= 12:
            break
    proc.send_signal(signal.SIGKILL)  # most likely in the middle of writing the next frame
    proc.wait()
    proc.stdout.close()
    traj = read_trajectory(path)
    frames = len(traj["step"])
    assert frames >= flushed + 1
    np.testing.assert_array_equal(traj["step"], np.arange(frames))
    for k in range(frames):
        assert np.all(traj["position"][k] == k), k
    # other readers open it too, in HDF5's SWMR read mode
    pyh5md = pytest.importorskip("pyh5md")
    with pyh5md.File(path, "r", swmr=True) as f:
        pos = pyh5md.element(f.particles_group("all"), "position")
        assert pos.step.shape[0] == frames and np.all(pos.value[frames - 1] == frames - 1)


def test_sharded_simulation_is_gathered_by_the_client(tmp_path):
    # DistributedSimulation has no p: the recorder asks for gather() (shards in order)
    local = FakeSim(n=30)

    class Sharded:
        t, dt = 0.0, 0.1

        def gather(self):
            return local.p

        def run(self, k):
            local.run(k)
            self.t = local.t

    with TrajectoryRecorder(tmp_path / "d.h5", every=2) as rec:
        rec.run(Sharded(), 4)
    traj = read_trajectory(tmp_path / "d.h5")
    np.testing.assert_array_equal(traj["step"], [0, 2, 4])
    np.testing.assert_allclose(traj["position"][-1], local.p["x"])
