"""The vectorizable elementary functions against the C library (numba's math.*)."""

import math
import re

import numpy as np
import pytest
from numba import njit

from fastsdf.backends.kernel.vmath import vexp, vlog, vlog1p


def _loop(fn):
    @njit(error_model="numpy")
    def apply(a, out):
        for i in range(a.shape[0]):
            out[i] = fn(a[i])

    return apply


@njit
def _mexp(x):
    return math.exp(x)


@njit
def _mlog(x):
    return math.log(x)


@njit
def _mlog1p(x):
    return math.log1p(x)


PAIRS = {"exp": (vexp, _mexp), "log": (vlog, _mlog), "log1p": (vlog1p, _mlog1p)}
_KERNELS = {}


def _run(name, a):
    if name not in _KERNELS:
        _KERNELS[name] = tuple(_loop(f) for f in PAIRS[name])
    kv, km = _KERNELS[name]
    a = np.ascontiguousarray(a, dtype=np.float64)
    ov, om = np.empty_like(a), np.empty_like(a)
    kv(a, ov)
    km(a, om)
    return ov, om


def _ulp_distance(a, b):
    """Distance in units in the last place, counting representable doubles between a and b
    (so the subnormals count as ulps too); NaN vs NaN is 0, NaN vs a number is inf."""
    ia, ib = a.view(np.int64), b.view(np.int64)
    # map the sign-magnitude bit patterns onto a monotonic integer line
    ia = np.where(ia < 0, np.int64(-(2**63)) - ia, ia)
    ib = np.where(ib < 0, np.int64(-(2**63)) - ib, ib)
    estimate = np.abs(ia.astype(np.float64) - ib.astype(np.float64))  # rounded for huge ints
    with np.errstate(over="ignore"):
        exact = np.abs(ia - ib).astype(np.float64)  # may wrap, but only where estimate is huge
    d = np.where(estimate < 2.0**60, exact, estimate)
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    d[nan_a & nan_b] = 0.0
    d[nan_a != nan_b] = np.inf
    return d


def _check(name, a, max_ulp=2.0):
    ov, om = _run(name, a)
    d = _ulp_distance(ov, om)
    worst = int(np.argmax(d))
    assert d[worst] <= max_ulp, (
        f"{name}({a[worst]!r}) = {ov[worst]!r}, C library {om[worst]!r}: {d[worst]} ulp"
    )
    # zeros and infinities exactly, sign included
    special = np.isinf(om) | (om == 0.0)
    np.testing.assert_array_equal(ov[special].view(np.int64), om[special].view(np.int64))
    return d


def _random_bits(n, seed):
    rng = np.random.default_rng(seed)
    return rng.integers(
        np.iinfo(np.int64).min, np.iinfo(np.int64).max, n, dtype=np.int64, endpoint=True
    ).view(np.float64)


def _around(values, steps=3):
    """Each value and its neighbours up to ``steps`` representable doubles away."""
    out = []
    for v in values:
        lo = hi = float(v)
        out.append(lo)
        for _ in range(steps):
            with np.errstate(over="ignore"):
                lo, hi = np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)
            out += [lo, hi]
    return np.array(out)


def _subnormals(n):
    rng = np.random.default_rng(6)
    return rng.integers(1, 2**52, n, dtype=np.int64).view(np.float64)


TINY = 5e-324
MIN_NORMAL = 2.2250738585072014e-308
MAX = 1.7976931348623157e308
EDGES = [
    0.0,
    -0.0,
    TINY,
    -TINY,
    MIN_NORMAL,
    -MIN_NORMAL,
    MIN_NORMAL / 3,
    MAX,
    -MAX,
    1.0,
    -1.0,
    0.5,
    2.0,
    math.sqrt(0.5),
    math.sqrt(2.0),
    2.0**-53,
    -(2.0**-53),
    2.0**-1022,
    np.inf,
    -np.inf,
    np.nan,
]


@pytest.mark.parametrize("name", list(PAIRS))
def test_random_bit_patterns(name):
    """Uniform random bit patterns: every exponent equally likely, NaNs and signs included."""
    _check(name, _random_bits(400_000, seed=len(name)))


@pytest.mark.parametrize("name", list(PAIRS))
def test_edges(name):
    _check(name, _around(EDGES))


def test_exp_ranges_and_bounds():
    rng = np.random.default_rng(1)
    overflow = 709.782712893384  # largest x with finite exp(x)
    normal = -708.3964185322641  # exp(x) below this is subnormal
    underflow = -745.1332191019411  # exp(x) below this rounds to 0
    samples = [
        rng.uniform(-750, 750, 200_000),
        rng.uniform(-1, 1, 100_000),
        rng.uniform(-746, -707, 100_000),
        rng.uniform(-1e-300, 1e-300, 10_000),
        _around([overflow, normal, underflow, 709.79, -745.2, 1e6, -1e6], steps=20),
    ]
    for a in samples:
        _check("exp", a)
    ov, _ = _run(
        "exp",
        np.array(
            [
                overflow,
                np.nextafter(overflow, np.inf),
                underflow,
                np.nextafter(underflow, -np.inf),
                0.0,
                -0.0,
            ]
        ),
    )
    assert np.isfinite(ov[0]) and ov[1] == np.inf
    assert ov[2] == TINY and ov[3] == 0.0
    assert ov[4] == 1.0 and ov[5] == 1.0  # exact


def test_log_ranges():
    rng = np.random.default_rng(2)
    for a in [
        rng.uniform(0, 3, 200_000),
        np.exp(rng.uniform(-745, 709, 200_000)),
        rng.uniform(0.999, 1.001, 100_000),
        _subnormals(100_000),
        _around([1.0, 2.0, 0.5, math.e, math.sqrt(2.0), math.sqrt(0.5)], steps=50),
    ]:
        _check("log", a)
        _check("log1p", a - 1.0)
    ov, _ = _run("log", np.array([0.0, -0.0, -1.0, np.inf, 1.0, 2.0**-1074]))
    assert ov[0] == -np.inf and ov[1] == -np.inf and np.isnan(ov[2]) and ov[3] == np.inf
    assert ov[4] == 0.0 and ov[5] == -1074 * math.log(2.0)


def test_log1p_ranges():
    rng = np.random.default_rng(3)
    for a in [
        rng.uniform(-1, 3, 200_000),
        np.exp(rng.uniform(-745, 709, 200_000)),
        -np.exp(rng.uniform(-745, 0, 200_000)),
        _around([-1.0, -0.2928932188134524, 0.41421356237309503, 2.0**-53, 1.0, 3.0], steps=50),
    ]:
        _check("log1p", a)
    tiny = np.array([1e-300, -1e-300, TINY, -TINY, -0.0, 1e-17])
    ov, _ = _run("log1p", tiny)
    np.testing.assert_array_equal(ov.view(np.int64), tiny.view(np.int64))  # log1p(x) = x exactly
    ov, _ = _run("log1p", np.array([-1.0, -1.5, np.inf, -np.inf]))
    assert ov[0] == -np.inf and np.isnan(ov[1]) and ov[2] == np.inf and np.isnan(ov[3])


def _has_avx2():
    import llvmlite.binding as ll

    return bool(ll.get_host_cpu_features().get("avx2", False))


# Packed float64 arithmetic on vector registers of any width (SSE2 xmm, AVX2 ymm, AVX-512 zmm).
PACKED = re.compile(r"\bv?(?:mul|add|sub|div|fmadd\d*|fmsub\d*|fnmadd\d*|min|max)pd\s.*%[xyz]mm")


@pytest.mark.skipif(
    not _has_avx2(),
    reason="host CPU without AVX2: LLVM's cost model may "
    "keep these loops scalar on older SIMD, which is not a regression",
)
@pytest.mark.parametrize("name", list(PAIRS))
def test_loops_vectorize(name):
    """A loop over an array calling the function compiles to packed vector instructions (the
    C library's math.* stays a scalar call per element)."""
    apply = _loop(PAIRS[name][0])
    apply(np.ones(4), np.empty(4))
    asm = "\n".join(apply.inspect_asm().values())
    packed = PACKED.findall(asm)
    assert len(packed) >= 5, f"{name}: no packed float64 arithmetic in the loop"
