"""Particles on the GPU (``device='cuda'``), run under numba-cuda's simulator (no GPU needed):
the CUDA step against the CPU's plain step, bit for bit, and the physics on the CUDA target.

The simulator runs each thread in Python (calling the CPU-compiled helpers), so sizes are tiny.
"""

import math
import os
import sys

import numpy as np
import pytest

if "numba.cuda" not in sys.modules:  # the simulator is chosen when numba.cuda is imported
    os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")

import fastsdf as sdf
from fastsdf import GridSDF, device
from fastsdf.particles import Drag, Gravity, ParticleSimulation
from fastsdf.shapes.scenes import seed_world

if not device.available():
    pytest.skip(
        "numba-cuda (or its simulator, NUMBA_ENABLE_CUDASIM=1) is not available",
        allow_module_level=True,
    )

from numba import njit

FLOOR = sdf.Halfspace(normal=[0, 1], d=0.0)  # solid below y = 0


def _pair(world, pos, vel, steps, forces=(), sweep=False, **kw):
    """The same particles stepped on the CPU and on the GPU; returns both simulations. Without
    ``sweep``, the CPU runs its plain step (no tunnelling sweep, no query skipping); with it,
    both run the package's default (the sweep; the CPU skips queries too, which changes no
    result)."""
    sims = []
    for dev in ("cpu", "cuda"):
        sim = ParticleSimulation(
            world,
            positions=pos,
            velocities=vel,
            radius=0.03,
            prevent_tunnelling=sweep,
            device=dev,
            **kw,
        )
        sim.force_generators += [Gravity(), *forces]
        sims.append(sim)
    if not sweep:
        sims[0].engine.skip = False  # every step queries, as the GPU's
    for sim in sims:
        sim.run(steps)
    sims[1].check()
    return sims


def _drop(n, seed):
    """Particles just above the seed world's disc and funnel walls, moving fast enough that
    most of them meet a surface within a few steps."""
    rng = np.random.default_rng(seed)
    pos = np.stack([rng.uniform(-1.2, 1.2, n), rng.uniform(0.35, 0.6, n)], axis=1)
    vel = np.stack([rng.uniform(-1, 1, n), rng.uniform(-3, -1, n)], axis=1)
    return pos, vel


@pytest.mark.parametrize("kind", ["grid", "exact"])
def test_cuda_sweep_matches_cpu_default_step(kind):
    """Fast particles (steps of several radii) that the tunnelling sweep catches: the GPU's
    step with the sweep against the CPU's default step, to 1e-12."""
    f = seed_world()
    world = GridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j]) if kind == "grid" else f
    pos, vel = _drop(16, seed=2)
    vel = vel * 3.0  # 0.1 to 0.3 per step against a radius of 0.03
    steps = 8
    cpu, gpu = _pair(world, pos, vel, steps, sweep=True)
    plain = _pair(world, pos, vel, steps)[1]
    xc, vc = cpu.host("x"), cpu.host("v")
    assert np.abs(plain.host("x") - xc).max() > 1e-3  # the sweep changed some steps
    free = vel + steps * cpu.dt * np.array([0.0, -1.0])
    assert np.sum(np.abs(vc - free).max(axis=1) > 1e-6) >= 6
    np.testing.assert_allclose(gpu.host("x"), xc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gpu.host("v"), vc, rtol=0, atol=1e-12)


def test_sweep_stops_tunnelling_through_a_thin_wall():
    """A wall 0.02 thick and a particle moving 0.5 per step: the plain step jumps over it, the
    sweep bounces it back."""
    wall = sdf.Box(minc=[-0.01, -5.0], maxc=[0.01, 5.0])
    ends = []
    for sweep in (False, True):
        sim = ParticleSimulation(
            wall,
            positions=[[-0.3, 0.0]],
            velocities=[[15.0, 0.0]],
            radius=0.005,
            timestep=1 / 30,
            prevent_tunnelling=sweep,
            device="cuda",
        )
        sim.run(3)
        sim.check()
        ends.append(sim.host("x")[0, 0])
    assert ends[0] > 0.5  # passed through
    assert ends[1] < -0.01  # bounced off the wall's near side


@pytest.mark.parametrize("kind", ["grid", "exact"])
def test_cuda_step_matches_cpu_plain_step(kind):
    f = seed_world()
    world = GridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[80j, 80j]) if kind == "grid" else f
    pos, vel = _drop(24, seed=1)
    steps = 12
    cpu, gpu = _pair(world, pos, vel, steps)
    xc, vc = cpu.host("x"), cpu.host("v")
    # contacts happened: the velocities are not those of free fall
    free = vel + steps * cpu.dt * np.array([0.0, -1.0])
    assert np.sum(np.abs(vc - free).max(axis=1) > 1e-6) >= 8
    np.testing.assert_allclose(gpu.host("x"), xc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gpu.host("v"), vc, rtol=0, atol=1e-12)
    assert gpu.t == cpu.t == steps * cpu.dt


def test_state_lives_on_the_device():
    sim = ParticleSimulation(FLOOR, positions=[[0.0, 1.0], [0.5, 2.0]], device="cuda")
    for name in ("x", "v", "m", "r", "cr", "cf"):
        # a numba device array (the simulator's has no __cuda_array_interface__)
        assert hasattr(sim.p[name], "copy_to_host") and not isinstance(sim.p[name], np.ndarray)
    assert sim.host("x").shape == (2, 2) and isinstance(sim.host("x"), np.ndarray)
    sim.p["cr"] = 0.25  # broadcast from the host
    np.testing.assert_array_equal(sim.host("cr"), [0.25, 0.25])
    sim.p["v"] = device.as_device(np.array([[1.0, 2.0], [3.0, 4.0]]))  # device to device
    np.testing.assert_array_equal(sim.host()["v"], [[1.0, 2.0], [3.0, 4.0]])


def test_every_state_has_the_one_mapping_surface():
    """The particles' state on the host and on the device and the grains' window share one
    mapping surface (FieldState): the same names, checks and messages."""
    from fastsdf.particles import ContactLaw
    from fastsdf.particles.state import FieldState

    pos = [[0.0, 1.0], [0.5, 2.0]]
    states = [ParticleSimulation(FLOOR, positions=pos, device=dev).p for dev in ("cpu", "cuda")] + [
        ParticleSimulation(FLOOR, positions=pos, radius=0.1, contacts=ContactLaw()).p
    ]
    for p in states:
        assert isinstance(p, FieldState) and len(p) == 2 and p.dtype == np.float64
        assert tuple(p.keys()) == p.FIELDS and "x" in p and "w" not in p
        assert p.x is p["x"] and p.nbytes >= 0
        with pytest.raises(KeyError, match=r"no (particle|grain) field 'w'; fields are"):
            p["w"]
        with pytest.raises(AttributeError):
            p.w  # noqa: B018
        with pytest.raises(TypeError, match=r"p\['v'\] must hold real numbers"):
            p["v"] = "fast"
        with pytest.raises(ValueError, match=r"p\['v'\] has shape \(2, 2\); cannot assign"):
            p["v"] = np.zeros(3)
        p["v"] = [1.5, -2.0]  # broadcast to every particle
        np.testing.assert_array_equal(p.host()["v"], [[1.5, -2.0], [1.5, -2.0]])
        np.testing.assert_array_equal(device.to_host(p["x"]), pos)


@pytest.mark.parametrize("integrator", ["symplectic", "euler"])
def test_free_fall(integrator):
    """Far from the floor: x_k = x0 + v0 k dt + g dt**2 k (k + 1) / 2 (semi-implicit Euler;
    k (k - 1) / 2 for explicit Euler), v_k = v0 + g k dt."""
    x0 = np.array([[0.0, 50.0], [1.0, 60.0], [-2.0, 70.0]])
    v0 = np.array([[0.5, 1.0], [-0.25, 0.0], [0.0, -2.0]])
    g = np.array([0.3, -9.81])
    dt, k = 0.01, 25
    sim = ParticleSimulation(
        FLOOR, positions=x0, velocities=v0, timestep=dt, integrator=integrator, device="cuda"
    )
    sim.force_generators.append(Gravity(acceleration=g))
    sim.run(10)
    sim.run(k - 10)
    sim.check()
    kk = k * (k + 1) / 2 if integrator == "symplectic" else k * (k - 1) / 2
    np.testing.assert_allclose(sim.host("x"), x0 + v0 * k * dt + g * dt**2 * kk, rtol=0, atol=1e-11)
    np.testing.assert_allclose(sim.host("v"), v0 + g * k * dt, rtol=0, atol=1e-12)
    assert math.isclose(sim.t, k * dt)


def test_particle_resting_on_a_floor_stays():
    r, dt = 0.05, 1 / 60
    sim = ParticleSimulation(
        FLOOR, positions=[[0.0, r], [1.0, r]], radius=r, timestep=dt, device="cuda"
    )
    sim.force_generators.append(Gravity(acceleration=(0.0, -9.81)))
    sim.run(120)
    sim.check()
    y = sim.host("x")[:, 1]
    # the plain step lets a particle sink by at most one step's fall before pushing it out
    assert np.all(y >= r - 9.81 * dt**2) and np.all(y <= r + 9.81 * dt**2)
    assert np.all(np.abs(sim.host("v")) <= 9.81 * dt)
    np.testing.assert_array_equal(sim.host("x")[:, 0], [0.0, 1.0])


def test_bounce_restitution_and_friction():
    """A disc hitting the floor at v = (0.4, -1) without gravity leaves it at (1 - cf) 0.4
    along it and cr * 1 away from it."""
    cr, cf = 0.5, 0.3
    sim = ParticleSimulation(
        FLOOR,
        positions=[[0.0, 0.3]],
        velocities=[[0.4, -1.0]],
        radius=0.1,
        timestep=0.01,
        cr=cr,
        cf=cf,
        device="cuda",
    )
    sim.run(40)
    sim.check()
    np.testing.assert_allclose(sim.host("v"), [[(1 - cf) * 0.4, cr * 1.0]], rtol=0, atol=1e-12)
    assert sim.host("x")[0, 1] > 0.1


def test_drag_on_the_gpu():
    """Linear drag alone (semi-implicit Euler): v_k = v0 (1 - c dt / m)**k."""
    c, dt, k = 0.4, 0.02, 30
    v0 = np.array([[1.0, -0.5], [0.0, 2.0]])
    sim = ParticleSimulation(
        FLOOR,
        positions=[[0.0, 10.0], [1.0, 12.0]],
        velocities=v0,
        radius=0.1,
        timestep=dt,
        device="cuda",
    )
    sim.force_generators.append(Drag(c))
    m = sim.host("m")
    sim.run(k)
    sim.check()
    expect = v0 * (1 - c * dt / m[:, None]) ** k
    np.testing.assert_allclose(sim.host("v"), expect, rtol=1e-12, atol=0)


@njit
def _swirl(x, y, vx, vy, m, t):
    """A user force depending on position, velocity, mass and time."""
    return m * (0.5 * math.cos(t) - 0.1 * vx), m * (-0.2 * y + 0.05 * x)


def test_user_njit_force_on_the_gpu():
    """Against the same semi-implicit Euler recurrence written in NumPy."""
    x0 = np.array([[0.0, 5.0], [1.0, 6.0], [-1.0, 4.5]])
    dt, k = 0.05, 20
    sim = ParticleSimulation(FLOOR, positions=x0, radius=0.02, timestep=dt, device="cuda")
    sim.force_generators.append(_swirl)
    sim.run(k)
    sim.check()
    x, v = x0.copy(), np.zeros_like(x0)
    for j in range(k):
        t = j * dt
        a = np.stack([0.5 * np.cos(t) - 0.1 * v[:, 0], -0.2 * x[:, 1] + 0.05 * x[:, 0]], 1)
        v = v + a * dt
        x = x + v * dt
    np.testing.assert_allclose(sim.host("v"), v, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sim.host("x"), x, rtol=0, atol=1e-12)


def test_parameters_are_launch_arguments():
    """A world with a runtime parameter: a floor at height h; changing sim.params moves it."""
    world = sdf.Halfspace(normal=[0, 1], d=sdf.Param("h", 0.0))
    sim = ParticleSimulation(
        world,
        positions=[[0.0, 1.5]],
        velocities=[[0.0, -1.0]],
        radius=0.1,
        timestep=0.05,
        cr=0.0,
        cf=0.0,
        device="cuda",
    )
    sim.params["h"] = 1.0
    sim.run(20)
    sim.check()
    assert abs(sim.host("x")[0, 1] - 1.1) < 1e-9  # stopped on the raised floor


def test_moving_world_matches_cpu():
    """A piston and a rising floor (moving walls): the GPU step against the CPU's step with
    the sweep and skipping off, which evaluates the world at the end of each step and
    responds relative to the wall."""
    piston = sdf.Halfspace(normal=[1, 0], d=sdf.Param("x0", -1.0) + sdf.Param("u", 0.5) * sdf.t)
    floor = sdf.Halfspace(normal=[0, 1], d=-1.0 + 0.4 * sdf.t)
    world = piston | floor
    rng = np.random.default_rng(3)
    pos = np.stack([rng.uniform(-0.95, 0.5, 16), rng.uniform(-0.95, -0.5, 16)], axis=1)
    vel = rng.normal(0, 0.5, size=(16, 2))
    cpu, gpu = _pair(world, pos, vel, 20)
    assert np.all(cpu.host("x")[:, 0] > cpu.t * 0.5 - 1.0 - 0.05)  # the piston pushed them
    np.testing.assert_allclose(gpu.host("x"), cpu.host("x"), rtol=0, atol=1e-12)
    np.testing.assert_allclose(gpu.host("v"), cpu.host("v"), rtol=0, atol=1e-12)


def test_frozen_particle_reported_by_check():
    sim = ParticleSimulation(FLOOR, positions=[[0.0, 1.0], [1.0, 1.0]], device="cuda")
    sim.force_generators.append(Gravity())
    sim.p["x"] = np.array([[0.0, 1.0], [np.nan, 1.0]])
    sim.run(3)
    with pytest.raises(ValueError, match=r"p\['x'\]\[1\]"):
        sim.check()
    sim.check()  # reported once
    assert np.isnan(sim.host("x")[1, 0]) and sim.host("x")[0, 1] < 1.0


def test_unsupported_on_the_gpu_say_so():
    band = sdf.NarrowBandGridSDF(
        FLOOR | sdf.Circle(radius=0.3), bounds=[(-1, 1), (-1, 1)], samples=[64, 64]
    )
    with pytest.raises(NotImplementedError, match="NarrowBandGridSDF"):
        ParticleSimulation(band, n=2, device="cuda")
    with pytest.raises(ValueError, match="float64"):
        ParticleSimulation(FLOOR, n=2, dtype=np.float32, device="cuda")
    with pytest.raises(NotImplementedError, match="prevent_tunnelling=False"):
        ParticleSimulation(sdf.Halfspace(normal=[0, 1], d=0.1 * sdf.t), n=2, device="cuda")
    with pytest.raises(NotImplementedError, match="rest_speed"):
        ParticleSimulation(FLOOR, n=2, rest_speed=0.1, device="cuda")
    with pytest.raises(ValueError, match="device"):
        ParticleSimulation(FLOOR, n=2, device="gpu")
    sim = ParticleSimulation(FLOOR, n=2, device="cuda")
    sim.force_generators.append(lambda p, t: np.zeros((2, 2)))
    with pytest.raises(TypeError, match="device='cuda'"):
        sim.run(1)


def test_save_holds_the_host_copy(tmp_path):
    sim = ParticleSimulation(FLOOR, positions=[[0.0, 1.0], [0.5, 2.0]], device="cuda")
    sim.force_generators.append(Gravity())
    sim.run(5)
    path = sim.save(tmp_path / "gpu.npz")
    back = ParticleSimulation.load(path)
    assert back.device == "cuda" and back.t == sim.t
    np.testing.assert_array_equal(back.host("x"), sim.host("x"))
    back.run(5)
    sim.run(5)
    np.testing.assert_array_equal(back.host("x"), sim.host("x"))


def test_kernels_compile_for_a_real_gpu():
    """The simulator runs the CPU-compiled helpers: this compiles the step kernels for sm_90
    with numba-cuda and the CUDA toolkit's NVVM and ptxas (no GPU needed; skipped without the
    toolkit; the grid with the sweep and the exact fallback, and a moving world): each
    assembles without register spills, and without FMA contraction
    (fewer FMA instructions than NVVM's default contracts, so the bits follow the CPU's)."""
    import json
    import subprocess

    from bench.cuda_particles import toolkit

    if toolkit() is None:
        pytest.skip("no CUDA toolkit (libdevice, ptxas); set CUDA_HOME")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="0")
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    res = subprocess.run(
        [sys.executable, "-m", "bench.cuda_particles", "--ptx", "grid+sweep,moving"],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    rows = [json.loads(line) for line in res.stdout.splitlines() if line.startswith("{")]
    assert {r["kernel"] for r in rows} == {"grid+sweep", "moving"}
    for r in rows:
        assert r["registers"] and r["spill_bytes"] == [0, 0], r
        assert r["fma_in_ptx"] < r["fma_if_contracted"], r


def test_assigning_another_world_moves_its_data_to_the_device():
    sim = ParticleSimulation(FLOOR, positions=[[0.0, 0.5]], radius=0.1, cr=0.0, device="cuda")
    sim.force_generators.append(Gravity())
    sim.sdf = GridSDF(sdf.Halfspace(normal=[0, 1], d=0.2), bounds=[(-1, 1), (-1, 1)])
    sim.run(60)
    sim.check()
    assert abs(sim.host("x")[0, 1] - 0.3) < 0.01  # resting on the new floor at 0.2


def test_trajectories_and_video_read_the_device_state(tmp_path):
    """The tools take a GPU simulation: an H5MD trajectory holds the device state of each frame
    (the same numbers as the CPU's run of the same particles), and a video is written."""
    pytest.importorskip("h5py")
    from fastsdf.io import TrajectoryRecorder, read_trajectory
    from fastsdf.viz import record_video

    grid = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j])
    frames = {}
    for dev in ("cpu", "cuda"):
        sim = ParticleSimulation(grid, n=60, timestep=1 / 30, seed=3, device=dev)
        sim.force_generators.append(Gravity())
        path = tmp_path / f"{dev}.h5"
        with TrajectoryRecorder(path, every=2, fields=("position", "velocity")) as rec:
            rec.run(sim, 6)
        frames[dev] = read_trajectory(path)
        last = device.to_host(sim.p["x"])
        np.testing.assert_array_equal(frames[dev]["position"][-1], last)
    assert frames["cuda"]["position"].shape == (4, 60, 2)
    np.testing.assert_allclose(
        frames["cuda"]["position"], frames["cpu"]["position"], rtol=0, atol=1e-12
    )
    pytest.importorskip("imageio_ffmpeg")
    video = tmp_path / "drop.mp4"
    record_video(sim, str(video), frames=3, steps_per_frame=1)
    assert video.stat().st_size > 1000
