"""The seed notebook, "Computational Graphs - Signed Distance Functions and Particle Physics"
(py-cgraph, 2017), run on fastsdf: every code cell in order, unchanged except for its import lines

    import cgraph as cg                         ->  import fastsdf.graph as cg
    import cgraph.sdf as sdf                    ->  import fastsdf as sdf
    import cgraph.app.particle_physics as phys  ->  import fastsdf.particles as phys
    from IPython.display import HTML            ->  (HTML is defined below: it saves the page)

and the IPython magic ``%matplotlib inline`` (not Python) turned into a comment. Two lines of the
notebook's own hand-written simulation (cell 16) no longer run on today's libraries and are
edited, marked ``[was ...]``: NumPy 2 reads the field spec ``('m', float, 1)`` as a shape-(1,)
field, and Matplotlib 3.5 removed ``PatchCollection(offset_position='data')`` (today the circles
are placed by ``offset_transform=ax.transData`` and sized by the data transform without its
translation, ``AffineDeltaTransform(ax.transData)``: with ``transData`` for both, the origin shift
is applied twice and every circle lands off the canvas). Each figure is
saved as ``OUT/cell_NN.png``. Each animation is written as a video file, ``OUT/cell_NN.mp4``
(``.gif`` without ffmpeg; ``pip install 'fastsdf[video]'`` provides one), with a small page
``OUT/cell_NN.html`` that plays it: the notebook's ``anim.to_html5_video()`` embeds the whole
video in the page, which for the 500-frame cell 22 would pass matplotlib's 20 MB embedding limit
(it then drops frames).

    python examples/seed_notebook.py [OUT]          # default OUT: ./notebook-out
    FASTSDF_EXAMPLE_SMALL=1 python examples/...     # tiny sizes (the test suite runs this)

With ``FASTSDF_EXAMPLE_SMALL=1`` the support code below caps particle counts at 50 and animation
frames at 3 (the cells themselves are unchanged).
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")

# ---- support code (not part of the notebook) -----------------------------------------------
OUT = sys.argv[1] if len(sys.argv) > 1 else "notebook-out"
os.makedirs(OUT, exist_ok=True)
SMALL = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
_cell_no = [0]
from fastsdf.viz.progress import progress as _progress  # noqa: E402
_cells_bar = _progress(22, "notebook cells")


def _cell(n):
    """End of notebook cell n: save and close its figures."""
    import matplotlib.pyplot as _plt
    _cell_no[0] = n
    _cells_bar.update(1)
    for k, num in enumerate(_plt.get_fignums()):
        suffix = "" if k == 0 else f"_{k}"
        _plt.figure(num).savefig(os.path.join(OUT, f"cell_{n:02d}{suffix}.png"), dpi=80)
    _plt.close("all")


def HTML(page):
    """Stand-in for IPython.display.HTML: writes the animation page of the current cell."""
    path = os.path.join(OUT, f"cell_{_cell_no[0] + 1:02d}.html")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(page)
    return path


import fastsdf.particles as _phys  # noqa: E402
_create_animation = _phys.create_animation


def _video_animation(fig, ax, sim, frames=300, **kwargs):
    """The notebook's create_animation, whose to_html5_video() writes OUT/cell_NN.mp4 and
    returns a page that plays the file instead of embedding it."""
    # The world alone, before the animation draws any particle: a test compares it with the
    # last frame to see that particles were drawn.
    fig.savefig(os.path.join(OUT, f"cell_{_cell_no[0] + 1:02d}_world.png"), dpi=80)
    anim = _create_animation(fig, ax, sim, frames=frames, **kwargs)

    def to_html5_video(embed_limit=None):
        from fastsdf.viz.video import ffmpeg_available
        from fastsdf.viz.render import save_animation
        name = f"cell_{_cell_no[0] + 1:02d}" + (".mp4" if ffmpeg_available() else ".gif")
        save_animation(anim, os.path.join(OUT, name), fps=30)
        fig.savefig(os.path.join(OUT, f"cell_{_cell_no[0] + 1:02d}_last.png"), dpi=80)
        if name.endswith(".gif"):
            return f'<img src="{name}">'
        return f'<video src="{name}" controls autoplay loop></video>'

    anim.to_html5_video = to_html5_video
    return anim


_phys.create_animation = _video_animation

if SMALL:
    _Sim, _anim = _phys.ParticleSimulation, _phys.create_animation

    class _SmallSimulation(_Sim):
        def __init__(self, f, n=100, *args, **kwargs):
            super().__init__(f, min(n, 50), *args, **kwargs)

    def _small_animation(fig, ax, sim, frames=300, **kwargs):
        return _anim(fig, ax, sim, frames=min(frames, 3), **kwargs)

    _phys.ParticleSimulation, _phys.create_animation = _SmallSimulation, _small_animation

# ---- In [1] ---------------------------------------------------------------------------------
import fastsdf.graph as cg
import fastsdf as sdf
import numpy as np
import matplotlib.pyplot as plt
# %matplotlib inline
np.seterr(all='ignore');
_cell(1)

# ---- In [2] ---------------------------------------------------------------------------------
def circle(center=[0,0], radius=1.):
    x = cg.Symbol('x')
    y = cg.Symbol('y')
    f = cg.sym_sqrt((x - center[0])**2 + (y - center[1])**2) - radius
    return cg.Function(f, [x,y])

c = circle()

# Evaluate c
print(c(0,0), c(1,0), c(100,100))
_cell(2)

# ---- In [3] ---------------------------------------------------------------------------------
print(c.f)
_cell(3)

# ---- In [4] ---------------------------------------------------------------------------------
fig, (ax0,ax1,ax2) = plt.subplots(1,3,figsize=(8,8))
sdf.plot_sdf(fig, ax0, c, show_isolines='zero', show_isolabels=True, show_quiver=False); ax0.set_title('Zero iso-level')
sdf.plot_sdf(fig, ax1, c, show_isolines='all', show_isolabels=True, show_quiver=False); ax1.set_title('Multiple iso-levels')
sdf.plot_sdf(fig, ax2, c, show_isolines='all', show_isolabels=False, show_quiver=True); ax2.set_title('Gradients')
plt.tight_layout()
_cell(4)

# ---- In [5] ---------------------------------------------------------------------------------
def halfspace(normal=[0,1], d=0):
    n = normal / np.linalg.norm(normal) # Ensure unit length
    x = cg.Symbol('x')
    y = cg.Symbol('y')
    f = x * n[0] + y * n[1] - d
    return cg.Function(f, [x,y])

h = halfspace()

fig, ax = plt.subplots()
sdf.plot_sdf(fig, ax, h, show_isolabels=True, show_isolines='zero');
_cell(5)

# ---- In [6] ---------------------------------------------------------------------------------
def union(f0, f1):
    x = cg.Symbol('x')
    y = cg.Symbol('y')
    f = cg.sym_min(f0.f, f1.f)

    return cg.Function(f, [x,y])
_cell(6)

# ---- In [7] ---------------------------------------------------------------------------------
def intersection(f0, f1):
    x = cg.Symbol('x')
    y = cg.Symbol('y')
    f = cg.sym_max(f0.f, f1.f)

    return cg.Function(f, [x,y])
_cell(7)

# ---- In [8] ---------------------------------------------------------------------------------
def difference(f0, f1):
    x = cg.Symbol('x')
    y = cg.Symbol('y')
    f = cg.sym_max(f0.f, -f1.f)

    return cg.Function(f, [x,y])
_cell(8)

# ---- In [9] ---------------------------------------------------------------------------------
c0 = circle(center=[-0.6, 0])
c1 = circle(center=[0.6, 0])

u = union(c0, c1)
i = intersection(c0, c1)
d = difference(c0, c1) # Pac-man, here we come

fig, (ax0,ax1,ax2) = plt.subplots(1, 3, figsize=(8,8))
sdf.plot_sdf(fig, ax0, u, show_isolines='zero'); ax0.set_title('Union')
sdf.plot_sdf(fig, ax1, i, show_isolines='zero'); ax1.set_title('Intersection')
sdf.plot_sdf(fig, ax2, d, show_isolines='zero'); ax2.set_title('Difference')
plt.tight_layout()
_cell(9)

# ---- In [10] --------------------------------------------------------------------------------
f = sdf.Circle() & sdf.Halfspace(normal=[0,1], d=0.5)

fig, ax = plt.subplots()
sdf.plot_sdf(fig, ax, f, show_isolines='zero');
_cell(10)

# ---- In [11] --------------------------------------------------------------------------------
with sdf.smoothness(10):
    f = sdf.Circle() & sdf.Halfspace(normal=[0,1], d=0.5)

fig, ax = plt.subplots()
sdf.plot_sdf(fig, ax, f, show_isolines='zero');
_cell(11)

# ---- In [12] --------------------------------------------------------------------------------
with sdf.transform(angle=-0.3):
    f = sdf.Circle() & sdf.Halfspace(normal=[0,1], d=0.5)

fig, ax = plt.subplots()
sdf.plot_sdf(fig, ax, f, show_isolines='zero');
_cell(12)

# ---- In [13] --------------------------------------------------------------------------------
def random_box():
    """Returns a random box."""
    return sdf.Box(
        minc=np.random.uniform(-0.3, -0.1, size=2),
        maxc=np.random.uniform(0.1, 0.3, size=2)
    )

def random_transform():
    """Returns a random transformation."""
    return sdf.transform(
        angle=np.random.uniform(-0.8, 0.8),
        offset=np.random.uniform(-2, 2, size=2)
    )

f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8) | sdf.Halfspace(normal=[-1, 1], d=-1.8)
for i in range(20):
    with random_transform(), sdf.smoothness(5):
        f |= random_box()

fig, ax = plt.subplots()
sdf.plot_sdf(fig, ax, f, show_quiver=False, show_isolines='zero');
_cell(13)

# ---- In [14] --------------------------------------------------------------------------------
import fastsdf.particles as phys
from matplotlib.collections import PatchCollection
from matplotlib.transforms import AffineDeltaTransform  # [added: see reset below]
_cell(14)

# ---- In [15] --------------------------------------------------------------------------------
class SimpleParticleSimulation:
    """Particle physics simulation."""

    def __init__(self, sdf, n=10, timestep=1/30):
        self.n = n
        self.dt = timestep
        self.sdf = sdf
        self.t = 0
        self.drawable = None

    def reset(self, ax):
        """Called by the animation module when restarting the simulation."""
        pass

    def update(self, ax, use_wall_time=False):
        """Called by the animation module to forward simulation by timestep seconds."""
        pass

    def handle_collisions(self):
        """Will be called from update to handle and resolve collisions."""
        pass
_cell(15)

# ---- In [16] --------------------------------------------------------------------------------
def reset(self, ax):
    """Called by the animation module when restarting the simulation."""
    self.t = 0

    # Initialize particles
    self.p = np.zeros(self.n, dtype=[
            ('x', float, 2), # Position x,y
            ('v', float, 2), # Velocity vx,vy
            ('m', float), # Mass     [was ('m', float, 1): a shape-(1,) field in NumPy 2]
            ('r', float)  # Radius   [was ('r', float, 1)]
        ])

    # Randomized start values
    self.p['x'] = np.random.multivariate_normal([0, 1.5], [[0.05, 0],[0, 0.05]], self.n)
    self.p['v'] = np.random.multivariate_normal([0, 0], [[0.1, 0],[0, 0.1]], self.n)
    self.p['m'] = np.random.uniform(1, 10, size=self.n)
    self.p['r'] = self.p['m'] * 0.01

    # Visualization as a collection of circles
    if self.drawable:
        self.drawable.remove()

    actors = [plt.Circle((0,0), radius=self.p['r'][i]) for i in range(self.n)]
    # [was offset_position='data', removed in Matplotlib 3.5: offsets in data coordinates, and
    #  circle radii scaled by the data transform without its translation]
    self.drawable = ax.add_artist(PatchCollection(actors, offset_transform=ax.transData,
                                                  transform=AffineDeltaTransform(ax.transData),
                                                  alpha=0.6, zorder=10))
    self.drawable.set_array(np.random.rand(len(actors)))

SimpleParticleSimulation.reset = reset
_cell(16)

# ---- In [17] --------------------------------------------------------------------------------
def update(self, ax, use_wall_time):
    """Called by the animation module to forward simulation by timestep seconds."""

    # Assumed here that the only force acting is gravity
    f = self.p['m'][:, np.newaxis] * np.array([0, -1])

    # Compute the dynamics
    dx = self.p['v']                    # dx/dt = v
    dv = f / self.p['m'][:, np.newaxis] # dv/dt = force / mass

    # Integrate using explicit Euler towards time t + dt
    self.p['x'] += dx * self.dt
    self.p['v'] += dv * self.dt

    self.handle_collisions()

    self.t += self.dt
    self.drawable.set_offsets(self.p['x'])
    return self.drawable,

SimpleParticleSimulation.update = update
_cell(17)

# ---- In [18] --------------------------------------------------------------------------------
# SDF world
f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8) | sdf.Halfspace(normal=[-1, 1], d=-1.8)

# Instance of the simulation
sp = SimpleParticleSimulation(f, n=10, timestep=1/30)

def run_animation(f, simulation, frames=300):
    """Run particle simulation and visualize result."""
    fig, ax = plt.subplots()
    sdf.plot_sdf(fig, ax, f, show_quiver=False, show_isolines='zero');
    plt.close()
    anim = phys.create_animation(fig, ax, simulation, frames=frames, repeat=True, use_wall_time=False)
    return anim.to_html5_video()

# from IPython.display import HTML   (HTML is the saver defined in the support code above)
HTML(run_animation(f, sp, frames=100))
_cell(18)

# ---- In [19] --------------------------------------------------------------------------------
def handle_collisions(self):
    # Evaluate the SDF at updated particle positions
    d, grads = self.sdf(self.p['x'][:, 0], self.p['x'][:, 1], compute_gradient=True)

    # Account for radius of particles
    d -= self.p['r']

    # Get ids of colliding particles
    cids = np.where(d <= 0)[0]

    # Stop particles
    self.p['x'][cids] -= d[cids, np.newaxis] * grads[cids]
    self.p['v'][cids] = 0

# Monkey patch method
SimpleParticleSimulation.handle_collisions = handle_collisions
_cell(19)

# ---- In [20] --------------------------------------------------------------------------------
f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8) | sdf.Halfspace(normal=[-1, 1], d=-1.8)
sp = SimpleParticleSimulation(f, n=10, timestep=1/30)
HTML(run_animation(f, sp, frames=120))
_cell(20)

# ---- In [21] --------------------------------------------------------------------------------
f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8) | sdf.Halfspace(normal=[-1, 1], d=-1.8)
with sdf.smoothness(10):
    f |= sdf.Circle(center=[0, 0.0], radius=0.5) & sdf.Halfspace(normal=[0.1, 1], d=0.3)

def gravity(p, t):
    """Close to planet surface gravity."""
    return p['m'][:, np.newaxis] * np.array([0, -1])

ps = phys.ParticleSimulation(f, n=100, timestep=1/30)
ps.force_generators += [gravity]

# Setup animation and run
HTML(run_animation(f, ps))
_cell(21)

# ---- In [22] --------------------------------------------------------------------------------
bounds=[(-2,2), (-2,2)] # World bounds to sample
g = sdf.GridSDF(f, bounds=bounds, samples=[400j, 400j])

ps = phys.ParticleSimulation(g, n=2000, timestep=1/30)
ps.force_generators += [gravity]

HTML(run_animation(g, ps, frames=500))
_cell(22)

_cells_bar.close()
print(f"notebook cells ran; figures, videos and their pages are in {OUT}/")
