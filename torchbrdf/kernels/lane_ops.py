"""Lane-wise per-pixel linear algebra in C: ``torch.ops.torchbrdf.lane_ldl``, ``lane_lower_solve_``,
``lane_upper_solve_`` and ``lane_coupling``.

The recovery's Levenberg–Marquardt step solves, per pixel, small symmetric positive definite
systems stored lane-wise (matrices ``(n, n, P)``, vectors ``(n, ..., P)``: one contiguous lane
of ``P`` pixels per entry; :mod:`torchbrdf.recovery.pixel_systems` holds the PyTorch forms), and
its conjugate gradients couple the pixels through a 4-neighbour stencil on a ``S × S`` grid
(:mod:`torchbrdf.recovery.smoothness_prior`). In PyTorch each entry of a factorisation or a
substitution is one multiply-add over every pixel, a pass through memory per entry; here one C
loop does every entry of a block of pixels in cache (pixels innermost, so it vectorises), on
PyTorch's OpenMP threads.

Each operator performs the PyTorch form's floating-point operations in the same order per
element, compiled without FMA contraction (:data:`torchbrdf.kernels.build.CFLAGS`), so the
results are bit-identical to it. CPU only, float32 or float64; no autograd (the solves are
linear algebra on already second-order terms); fake implementations for ``torch.compile``.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["available", "lane_ldl", "lane_lower_solve", "lane_upper_solve", "lane_coupling", "coupling_operator",
           "PIVOT_FLOOR", "MAX_SIZE"]

#: A pivot of ``LDLᵀ`` is at least this fraction of its matrix's diagonal entry plus the dtype's
#: smallest normal number (the value of :data:`torchbrdf.recovery.pixel_systems.PIVOT_FLOOR`).
PIVOT_FLOOR = 1e-12

#: The largest ``n`` of an ``n × n`` lane-wise system (the recovery's blocks are 7 × 7 at most).
MAX_SIZE = 16

_SOURCE = r"""
#include <math.h>
typedef %(R)s R;
/* c + a b as ATen's addcmul rounds it on this CPU: one fused multiply-add where its kernels
   are built with FMA (AVX2 and up), else a product and a sum */
#if %(FMA)d
#define MAC(a, b, c) %(FMAF)s((a), (b), (c))
#else
#define MAC(a, b, c) ((c) + (a) * (b))
#endif
#define BLOCK 256
#define MIN(a, b) ((a) < (b) ? (a) : (b))

/* LDL^T of m (n, n, P), lower triangle read; low (n, n, P) gets L's strict lower triangle (0
   elsewhere), d (n, P) the pivots, each at least PIVOT |m_jj| + TINY (NaN propagates). */
void tb_lane_ldl(long n, long P, const R* m, R* low, R* d, int nthreads) {
  #pragma omp parallel for schedule(static) num_threads(nthreads)
  for (long p0 = 0; p0 < P; p0 += BLOCK) {
    const long nb = MIN(BLOCK, P - p0);
    R col[%(N)d][BLOCK], coef[BLOCK];
    for (long j = 0; j < n; ++j) {
      for (long i = j; i < n; ++i)
        for (long q = 0; q < nb; ++q) col[i][q] = m[(i * n + j) * P + p0 + q];
      for (long k = 0; k < j; ++k) {
        for (long q = 0; q < nb; ++q) coef[q] = low[(j * n + k) * P + p0 + q] * d[k * P + p0 + q];
        for (long i = j; i < n; ++i) {
          const R* l = low + (i * n + k) * P + p0;
          for (long q = 0; q < nb; ++q) col[i][q] = MAC(-l[q], coef[q], col[i][q]);
        }
      }
      R* dj = d + j * P + p0;
      const R* mjj = m + (j * n + j) * P + p0;
      for (long q = 0; q < nb; ++q) {
        const R a = mjj[q] < 0 ? -mjj[q] : mjj[q];
        const R f = a * (R)%(PIVOT)s + (R)%(TINY)s;
        const R c = col[j][q];
        dj[q] = (c != c || f != f) ? c + f : (c > f ? c : f);
      }
      for (long i = 0; i <= j; ++i)
        for (long q = 0; q < nb; ++q) low[(i * n + j) * P + p0 + q] = 0;
      for (long i = j + 1; i < n; ++i)
        for (long q = 0; q < nb; ++q) low[(i * n + j) * P + p0 + q] = col[i][q] / dj[q];
    }
  }
}

/* v <- L^-1 v (upper = 0) or L^-T v (upper = 1) in place, v (n, r, P), low (n, n, P) */
void tb_lane_solve(long n, long r, long P, const R* low, R* v, int upper, int nthreads) {
  #pragma omp parallel for schedule(static) num_threads(nthreads)
  for (long p0 = 0; p0 < P; p0 += BLOCK) {
    const long nb = MIN(BLOCK, P - p0);
    if (!upper) {
      for (long k = 0; k + 1 < n; ++k)
        for (long i = k + 1; i < n; ++i) {
          const R* l = low + (i * n + k) * P + p0;
          for (long c = 0; c < r; ++c) {
            R* vi = v + (i * r + c) * P + p0;
            const R* vk = v + (k * r + c) * P + p0;
            for (long q = 0; q < nb; ++q) vi[q] = MAC(-l[q], vk[q], vi[q]);
          }
        }
    } else {
      for (long k = n - 1; k > 0; --k)
        for (long i = 0; i < k; ++i) {
          const R* l = low + (k * n + i) * P + p0;
          for (long c = 0; c < r; ++c) {
            R* vi = v + (i * r + c) * P + p0;
            const R* vk = v + (k * r + c) * P + p0;
            for (long q = 0; q < nb; ++q) vi[q] = MAC(-l[q], vk[q], vi[q]);
          }
        }
    }
  }
}

/* out = K v (subtract = 0) or v - K v (subtract = 1), K = D^-1/2 L^-1 N L^-T D^-1/2, where
   N v = sum over the 4 neighbours q of w_pq v_q on the S x S grid: vectors (n, P), low (n, n, P),
   dis = D^-1/2 (n, P), wx (n, S, S-1), wy (n, S-1, S); t (n, P) is scratch. */
void tb_lane_coupling(long n, long S, const R* low, const R* dis, const R* wx, const R* wy, const R* v,
                      R* t, R* out, int subtract, int nthreads) {
  const long P = S * S;
  #pragma omp parallel num_threads(nthreads)
  {
    #pragma omp for schedule(static)
    for (long p0 = 0; p0 < P; p0 += BLOCK) {  /* t = L^-T D^-1/2 v */
      const long nb = MIN(BLOCK, P - p0);
      for (long c = 0; c < n; ++c)
        for (long q = 0; q < nb; ++q) t[c * P + p0 + q] = v[c * P + p0 + q] * dis[c * P + p0 + q];
      for (long k = n - 1; k > 0; --k)
        for (long i = 0; i < k; ++i) {
          const R* l = low + (k * n + i) * P + p0;
          R* ti = t + i * P + p0;
          const R* tk = t + k * P + p0;
          for (long q = 0; q < nb; ++q) ti[q] = MAC(-l[q], tk[q], ti[q]);
        }
    }
    #pragma omp for schedule(static)
    for (long row = 0; row < S; ++row) {  /* out = D^-1/2 L^-1 N t, a grid row at a time */
      const long p0 = row * S;
      for (long c = 0; c < n; ++c) {
        R* o = out + c * P + p0;
        const R* tr = t + c * P + p0;
        const R* w = wx + (c * S + row) * (S - 1);
        for (long j = 0; j + 1 < S; ++j) o[j] = w[j] * tr[j + 1];
        o[S - 1] = 0;
        for (long j = 1; j < S; ++j) o[j] = MAC(w[j - 1], tr[j - 1], o[j]);
        if (row + 1 < S) {
          const R* wd = wy + (c * (S - 1) + row) * S;
          for (long j = 0; j < S; ++j) o[j] = MAC(wd[j], tr[S + j], o[j]);
        }
        if (row > 0) {
          const R* wu = wy + (c * (S - 1) + row - 1) * S;
          for (long j = 0; j < S; ++j) o[j] = MAC(wu[j], tr[j - S], o[j]);
        }
      }
      for (long k = 0; k + 1 < n; ++k)
        for (long i = k + 1; i < n; ++i) {
          const R* l = low + (i * n + k) * P + p0;
          R* oi = out + i * P + p0;
          const R* ok = out + k * P + p0;
          for (long j = 0; j < S; ++j) oi[j] = MAC(-l[j], ok[j], oi[j]);
        }
      for (long c = 0; c < n; ++c) {
        R* o = out + c * P + p0;
        const R* s = dis + c * P + p0;
        const R* vr = v + c * P + p0;
        if (subtract)
          for (long j = 0; j < S; ++j) o[j] = vr[j] - o[j] * s[j];
        else
          for (long j = 0; j < S; ++j) o[j] = o[j] * s[j];
      }
    }
  }
}
"""

_lock = threading.Lock()
_kernels: dict[torch.dtype, object] = {}
_CTYPES = {torch.float32: ("float", "1.17549435082228750797e-38"),
           torch.float64: ("double", "2.22507385850720138309e-308")}


def _kernel(dtype: torch.dtype):
    """``(library, ldl, solve, coupling)`` for ``dtype`` (built once; None: it cannot be built here)."""
    if dtype in _kernels:
        return _kernels[dtype]
    with _lock:
        if dtype not in _kernels:
            from torchbrdf.kernels import build

            ctype, tiny = _CTYPES[dtype]
            src = _SOURCE % {"R": ctype, "N": MAX_SIZE, "PIVOT": repr(PIVOT_FLOOR), "TINY": tiny,
                             "FMA": int(_aten_fuses()), "FMAF": "fmaf" if ctype == "float" else "fma"}
            p, lg, i = ctypes.c_void_p, ctypes.c_long, ctypes.c_int
            symbols = {"tb_lane_ldl": ([lg, lg, p, p, p, i], None),
                       "tb_lane_solve": ([lg, lg, lg, p, p, i, i], None),
                       "tb_lane_coupling": ([lg, lg, p, p, p, p, p, p, p, i, i], None)}
            lib = build.load_kernel(src, "lane_ops", symbols)
            _kernels[dtype] = None if lib is None else (lib, lib.tb_lane_ldl, lib.tb_lane_solve,
                                                        lib.tb_lane_coupling)
        return _kernels[dtype]


def _aten_fuses() -> bool:
    """Whether ATen's CPU kernels here run with fused multiply-adds (its AVX2 and AVX-512 builds
    are compiled with FMA contraction, so ``addcmul`` rounds ``c + a b`` once)."""
    return torch.backends.cpu.get_cpu_capability() not in ("DEFAULT", "NO AVX", "VSX", "ZVECTOR")


def available(t: Tensor) -> bool:
    """Whether the operators run on tensors like ``t``: CPU, float32 or float64, with a C
    compiler (the kernels are built on the first call)."""
    if t.device.type != "cpu" or t.dtype not in _CTYPES:
        return False
    return _kernel(t.dtype) is not None


def _check(name: str, t: Tensor, shape: tuple[int, ...], dtype: torch.dtype) -> None:
    """Refuse what the C loops would read wrongly: they take raw CPU pointers of one float type."""
    if t.dtype not in _CTYPES or t.dtype != dtype:
        raise ValueError(f"lane_ops: {name} must be float32 or float64 (the first argument's {dtype}), "
                         f"got {t.dtype}")
    if t.device.type != "cpu":
        raise ValueError(f"lane_ops: {name} must be on the CPU (see available()), got {t.device}")
    if tuple(t.shape) != shape:
        raise ValueError(f"lane_ops: {name} must have shape {shape}, got {tuple(t.shape)}")


def _check_low(low: Tensor) -> int:
    if low.dim() != 3 or low.shape[0] != low.shape[1] or not 0 < low.shape[0] <= MAX_SIZE:
        raise ValueError(f"lane_ops: low must be (n, n, P) with 1 <= n <= MAX_SIZE = {MAX_SIZE}, "
                         f"got {tuple(low.shape)}")
    _check("low", low, tuple(low.shape), low.dtype)
    return low.shape[0]


def _fn(dtype: torch.dtype, which: int):
    k = _kernel(dtype)
    if k is None:
        raise RuntimeError("lane_ops: the C kernels cannot be built here (ask lane_ops.available first)")
    return k[which]


def _ldl(m: Tensor) -> tuple[Tensor, Tensor]:
    n = _check_low(m)
    m = m.contiguous()
    low, d = torch.empty_like(m), torch.empty_like(m[0])
    _fn(m.dtype, 1)(n, m.shape[2], m.data_ptr(), low.data_ptr(), d.data_ptr(), torch.get_num_threads())
    return low, d


def _solve(low: Tensor, v: Tensor, upper: bool) -> None:
    n = _check_low(low)
    if v.dim() < 2 or v.shape[0] != n or v.shape[-1] != low.shape[2]:
        raise ValueError(f"lane_ops: v must be ({n}, ..., {low.shape[2]}) like low, got {tuple(v.shape)}")
    _check("v", v, tuple(v.shape), low.dtype)
    if not v.is_contiguous():
        raise ValueError("lane_ops: v must be contiguous (it is solved in place)")
    low = low.contiguous()
    _fn(low.dtype, 2)(n, v[0].numel() // max(v.shape[-1], 1), low.shape[2], low.data_ptr(), v.data_ptr(),
                      int(upper), torch.get_num_threads())


def _bind(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor) -> tuple[int, int, list[Tensor]]:
    """``(n, S, contiguous [low, d_isqrt, wx, wy])`` of a coupling operator, checked."""
    n, p = _check_low(low), low.shape[2]
    size = int(round(p ** 0.5))
    if size * size != p or p == 0:
        raise ValueError(f"lane_ops: low's {p} pixels are not a square grid")
    for name, t, shape in (("d_isqrt", d_isqrt, (n, p)), ("wx", wx, (n, size, size - 1)),
                           ("wy", wy, (n, size - 1, size))):
        _check(name, t, shape, low.dtype)
    return n, size, [t.contiguous() for t in (low, d_isqrt, wx, wy)]


def _couple(n: int, size: int, mats: list[Tensor], v: Tensor, subtract: bool) -> Tensor:
    """The C call of :func:`lane_coupling` on checked, contiguous inputs."""
    t, out = torch.empty_like(v), torch.empty_like(v)
    _fn(v.dtype, 3)(n, size, *(m.data_ptr() for m in mats), v.data_ptr(), t.data_ptr(), out.data_ptr(),
                    int(subtract), torch.get_num_threads())
    return out


@torch.library.custom_op("torchbrdf::lane_ldl", mutates_args=())
def _lane_ldl_op(m: Tensor) -> tuple[Tensor, Tensor]:
    return _ldl(m)


@_lane_ldl_op.register_fake
def _(m):
    return torch.empty_like(m), torch.empty_like(m[0])


@torch.library.custom_op("torchbrdf::lane_lower_solve_", mutates_args=("v",))
def _lane_lower_op(low: Tensor, v: Tensor) -> None:
    _solve(low, v, False)


@torch.library.custom_op("torchbrdf::lane_upper_solve_", mutates_args=("v",))
def _lane_upper_op(low: Tensor, v: Tensor) -> None:
    _solve(low, v, True)


@torch.library.custom_op("torchbrdf::lane_coupling", mutates_args=())
def _lane_coupling_op(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, v: Tensor, subtract: bool) -> Tensor:
    n, size, mats = _bind(low, d_isqrt, wx, wy)
    _check("v", v, (n, size * size), low.dtype)
    return _couple(n, size, mats, v.contiguous(), subtract)


@_lane_coupling_op.register_fake
def _(low, d_isqrt, wx, wy, v, subtract):
    return torch.empty_like(v)


def _direct() -> bool:
    """Whether to call the C loops directly (eager) rather than through the operator: the
    dispatcher's work per call (~tens of µs) is a CG iteration's cost on a small map; under
    torch.compile or a torch.func transform the operator is what they must see."""
    return not torch.compiler.is_compiling() and not torch._C._are_functorch_transforms_active()


def lane_ldl(m: Tensor) -> tuple[Tensor, Tensor]:
    """``LDLᵀ`` of ``m (n, n, P)`` lane-wise (its lower triangle read), as
    :func:`torchbrdf.recovery.pixel_systems.ldl_factor`: ``low (n, n, P)`` (the strict lower
    triangle of ``L``, zeros elsewhere) and the pivots ``d (n, P)``, each at least
    :data:`PIVOT_FLOOR` of its diagonal entry plus the dtype's smallest normal number. ``m``'s
    dtype (float32 or float64), CPU.

    Raises:
        ValueError: a shape, dtype or device the kernel cannot read (named).
    """
    return _ldl(m) if _direct() else _lane_ldl_op(m)


def lane_lower_solve(low: Tensor, v: Tensor) -> Tensor:
    """``v ← L⁻¹ v`` in place (``L`` unit lower triangular from :func:`lane_ldl`), ``low (n, n, P)``,
    ``v (n, ..., P)`` contiguous, ``low``'s dtype, CPU. Returns ``v``."""
    _solve(low, v, False) if _direct() else _lane_lower_op(low, v)
    return v


def lane_upper_solve(low: Tensor, v: Tensor) -> Tensor:
    """``v ← L⁻ᵀ v`` in place, as :func:`lane_lower_solve`. Returns ``v``."""
    _solve(low, v, True) if _direct() else _lane_upper_op(low, v)
    return v


def lane_coupling(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, v: Tensor, subtract: bool) -> Tensor:
    """``K v`` (or ``v − K v`` with ``subtract``) for ``K = G⁻¹ N G⁻ᵀ``, ``G = L D^½``, on an
    ``S × S`` grid: one iteration's operator of the split-preconditioned conjugate gradients of
    :func:`torchbrdf.recovery.smoothness_prior.pcg`.

    ``low (n, n, P)`` the strict lower triangle of unit lower triangular ``L``, ``d_isqrt (n, P)``
    ``= D^-½``, ``N v = Σ_q w_pq v_q`` over each pixel's 4 neighbours with edge weights
    ``wx (n, S, S-1)`` and ``wy (n, S-1, S)`` (channel-first), ``v (n, P)``, ``P = S² > 0``
    row-major; one dtype (float32 or float64), CPU. Returns a new ``(n, P)`` tensor.

    Raises:
        ValueError: a shape, dtype or device the kernel cannot read (named).
    """
    return coupling_operator(low, d_isqrt, wx, wy)(v, subtract)


def coupling_operator(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor) -> Callable[[Tensor, bool], Tensor]:
    """:func:`lane_coupling` bound to its matrices (checked once, for a CG loop's many calls):
    a function of ``(v (n, P), subtract)``."""
    n, size, mats = _bind(low, d_isqrt, wx, wy)

    def apply(v: Tensor, subtract: bool) -> Tensor:
        if not _direct():
            return _lane_coupling_op(*mats, v, bool(subtract))
        if v.shape != (n, size * size) or v.dtype != low.dtype or v.device != low.device:
            _check("v", v, (n, size * size), low.dtype)  # raises, naming it
        return _couple(n, size, mats, v.contiguous(), subtract)

    return apply
