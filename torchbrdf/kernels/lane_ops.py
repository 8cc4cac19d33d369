"""Lane-wise per-pixel linear algebra in C: ``torch.ops.torchbrdf.lane_ldl``, ``lane_lower_solve_``,
``lane_upper_solve_``, ``lane_coupling``, ``lane_schur`` and ``lane_cg``.

The recovery's Levenberg–Marquardt step solves, per pixel, small symmetric positive definite
systems stored lane-wise (matrices ``(n, n, P)``, vectors ``(n, ..., P)``: one contiguous lane
of ``P`` pixels per entry; :mod:`torchbrdf.recovery.pixel_systems` holds the PyTorch forms), and
its conjugate gradients couple the pixels through a 4-neighbour stencil on a ``S × S`` grid
(:mod:`torchbrdf.recovery.smoothness_prior`). In PyTorch each entry of a factorisation or a
substitution is one multiply-add over every pixel, a pass through memory per entry; here one C
loop does every entry of a block of pixels in cache (pixels innermost, so it vectorises), on
PyTorch's OpenMP threads.

Each operator but ``lane_cg`` performs the PyTorch form's floating-point operations in the same
order per element, compiled without FMA contraction (:data:`torchbrdf.kernels.build.CFLAGS`), so
the results are bit-identical to it; ``lane_cg`` (the whole CG loop in one call) sums its dot
products in float64 in an order of its own. CPU only, float32 or float64; no autograd (the solves are
linear algebra on already second-order terms); fake implementations for ``torch.compile``.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

__all__ = ["available", "lane_schur", "lane_ldl", "lane_lower_solve", "lane_upper_solve", "lane_coupling",
           "lane_cg", "coupling_operator", "PIVOT_FLOOR", "MAX_SIZE", "MAX_SCHUR"]

#: A pivot of ``LDLᵀ`` is at least this fraction of its matrix's diagonal entry plus the dtype's
#: smallest normal number (the value of :data:`torchbrdf.recovery.pixel_systems.PIVOT_FLOOR`).
PIVOT_FLOOR = 1e-12

#: The largest ``n`` of an ``n × n`` lane-wise system (the recovery's blocks are 7 × 7 at most).
MAX_SIZE = 16

#: The largest block :func:`lane_schur` takes (its float64 working arrays, ~180 KB, live on the
#: thread's stack: well within an OpenMP worker's, as :mod:`torchbrdf.kernels.schur_ops`'s).
MAX_SCHUR = 8

_SOURCE = r"""
#include <math.h>
typedef %(R)s R;
/* c + a b as ATen's addcmul rounds it on this CPU (MAC in R, MAC64 in float64): one fused
   multiply-add where its kernels are built with FMA (AVX2 and up), else a product and a sum */
#if %(FMA)d
#define MAC(a, b, c) %(FMAF)s((a), (b), (c))
#define MAC64(a, b, c) fma((a), (b), (c))
#else
#define MAC(a, b, c) ((c) + (a) * (b))
#define MAC64(a, b, c) ((c) + (a) * (b))
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
   dis = D^-1/2 (n, P), wx (n, S, S-1), wy (n, S-1, S); t (n, P) is scratch. The work-sharing loops
   of an enclosing parallel region. For the conjugate gradients (tb_lane_cg): with r, v is first
   set to r + beta v (the new search direction, a block at a time, as t reads it), and with part,
   part[row] gets the float64 sum over the grid row of v out (a dot product's share). */
/* The float64 sum over the n channels of a grid row (S values each, channel stride P) of a b: the
   compiler's vector lanes as separate partial sums (a dependent chain of additions would run at
   their latency), each channel's added in order: the same bits for a row whichever thread sums it. */
static double row_dot(long n, long S, long P, const R* a, const R* b) {
  double acc = 0.0;
  for (long c = 0; c < n; ++c) {
    const R* x = a + c * P;
    const R* y = b + c * P;
    double sum = 0.0;
    _Pragma("omp simd reduction(+:sum)") for (long j = 0; j < S; ++j) sum += (double)x[j] * (double)y[j];
    acc += sum;
  }
  return acc;
}

static void coupling_body(long n, long S, const R* low, const R* dis, const R* wx, const R* wy, R* v,
                          R* t, R* out, int subtract, const R* r, R beta, double* part) {
  const long P = S * S;
  #pragma omp for schedule(static)
  for (long p0 = 0; p0 < P; p0 += BLOCK) {  /* t = L^-T D^-1/2 v */
    const long nb = MIN(BLOCK, P - p0);
    if (r)
      for (long c = 0; c < n; ++c)
        for (long q = 0; q < nb; ++q) v[c * P + p0 + q] = MAC(v[c * P + p0 + q], beta, r[c * P + p0 + q]);
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
    if (part) part[row] = row_dot(n, S, P, v + p0, out + p0);
  }
}

void tb_lane_coupling(long n, long S, const R* low, const R* dis, const R* wx, const R* wy, const R* v,
                      R* t, R* out, int subtract, int nthreads) {
  #pragma omp parallel num_threads(nthreads)
  coupling_body(n, S, low, dis, wx, wy, (R*)v, t, out, subtract, 0, (R)0, 0);
}

/* Up to iters conjugate-gradient iterations on (I - K) y = G^-1 b (smoothness_prior._cg_iterations)
   from y (n, P) and its residual r (n, P), both updated in place; d, t, ad (n, P) and part (S)
   are scratch. The dot products are float64 sums per grid row, then over the rows in order: the
   same bits at any thread count. A breakdown (d^T A d not positive and finite) stops the
   iterations where they are. Returns the number of iterations taken. */
long tb_lane_cg(long n, long S, const R* low, const R* dis, const R* wx, const R* wy, R* y, R* r,
                R* d, R* t, R* ad, double* part, long iters, int nthreads) {
  const long P = S * S;
  double rr = 0.0;
  #pragma omp parallel for schedule(static) num_threads(nthreads)
  for (long row = 0; row < S; ++row) {
    for (long c = 0; c < n; ++c)
      for (long j = 0; j < S; ++j) d[c * P + row * S + j] = r[c * P + row * S + j];
    part[row] = row_dot(n, S, P, r + row * S, r + row * S);
  }
  for (long row = 0; row < S; ++row) rr += part[row];
  R beta = 0;
  long it = 0;
  for (; it < iters; ++it) {
    #pragma omp parallel num_threads(nthreads)
    coupling_body(n, S, low, dis, wx, wy, d, t, ad, 1, it > 0 ? r : 0, beta, part);
    double dad = 0.0;
    for (long row = 0; row < S; ++row) dad += part[row];
    if (!(isfinite(dad) && dad > 0)) break;
    const R alpha = (R)(rr / dad);
    #pragma omp parallel for schedule(static) num_threads(nthreads)
    for (long row = 0; row < S; ++row) {
      for (long c = 0; c < n; ++c) {
        const long o = c * P + row * S;
        for (long j = 0; j < S; ++j) {
          y[o + j] = MAC(d[o + j], alpha, y[o + j]);
          r[o + j] = MAC(-ad[o + j], alpha, r[o + j]);
        }
      }
      part[row] = row_dot(n, S, P, r + row * S, r + row * S);
    }
    double rr_new = 0.0;
    for (long row = 0; row < S; ++row) rr_new += part[row];
    beta = rr != 0 ? (R)(rr_new / rr) : (R)0;
    rr = rr_new;
  }
  return it;
}
/* LDL^T of the n x n float64 matrices a[i][j][q] (lower triangle read) of nb pixels: low (strict
   lower triangle) and d, the pivots floored at PIVOT |a_jj| + DBL_MIN, as tb_lane_ldl */
#define SB 64
#define SC 8
static void ldl_block(long n, long nb, double a[SC][SC][SB], double low[SC][SC][SB], double d[SC][SB]) {
  double col[SC][SB], coef[SB];
  for (long j = 0; j < n; ++j) {
    for (long i = j; i < n; ++i)
      for (long q = 0; q < nb; ++q) col[i][q] = a[i][j][q];
    for (long k = 0; k < j; ++k) {
      for (long q = 0; q < nb; ++q) coef[q] = low[j][k][q] * d[k][q];
      for (long i = j; i < n; ++i)
        for (long q = 0; q < nb; ++q) col[i][q] = MAC64(-low[i][k][q], coef[q], col[i][q]);
    }
    for (long q = 0; q < nb; ++q) {
      const double m = a[j][j][q] < 0 ? -a[j][j][q] : a[j][j][q];
      const double f = m * %(PIVOT)s + 2.22507385850720138309e-308, c = col[j][q];
      d[j][q] = (c != c || f != f) ? c + f : (c > f ? c : f);
    }
    for (long i = j + 1; i < n; ++i)
      for (long q = 0; q < nb; ++q) low[i][j][q] = col[i][q] / d[j][q];
  }
}

/* The coupled solve's per-pixel elimination (smoothness_prior.pcg): the (c, c) blocks hess (P, c, c)
   and rhs (P, c), reordered by order (the nu eliminated channels first), diag (P, c) (or NULL)
   added to the diagonal, in float64; the complement S = A - B D^-1 B^T of the last na = c - nu
   with lapd (P, na) on its diagonal, factored: low (na, na, P), dis = D^-1/2 (na, P) and
   b = rhs_a - B D^-1 rhs_u (na, P) in R; for the back substitution low_u (nu, nu, P), d_u (nu, P),
   bt = B^T (nu, na, P) and rhs_u (nu, P) in float64. */
void tb_lane_schur(long P, long c, long nu, const long* order, const R* hess, const R* diag, const R* rhs,
                   const R* lapd, double* low_u, double* d_u, double* bt, double* rhs_u, R* low, R* dis, R* b,
                   int nthreads) {
  const long na = c - nu;
  #pragma omp parallel for schedule(static) num_threads(nthreads)
  for (long p0 = 0; p0 < P; p0 += SB) {
    const long nb = MIN(SB, P - p0);
    double h[SC][SC][SB], r[SC][SB], lu[SC][SC][SB], du[SC][SB], s[SC][SC][SB], ls[SC][SC][SB], ds[SC][SB];
    double v[SC][SC][SB], sc[SB], coef[SB];
    for (long i = 0; i < c; ++i) {
      for (long j = 0; j < c; ++j)
        for (long q = 0; q < nb; ++q) h[i][j][q] = (double)hess[(p0 + q) * c * c + order[i] * c + order[j]];
      for (long q = 0; q < nb; ++q) r[i][q] = (double)rhs[(p0 + q) * c + order[i]];
      if (diag)
        for (long q = 0; q < nb; ++q) h[i][i][q] = h[i][i][q] + (double)diag[(p0 + q) * c + order[i]];
    }
    for (long i = 0; i < na; ++i)
      for (long j = 0; j < na; ++j)
        for (long q = 0; q < nb; ++q) s[i][j][q] = h[nu + i][nu + j][q];
    if (nu > 0) {
      ldl_block(nu, nb, h, lu, du);
      for (long k = 0; k < nu; ++k) {
        for (long i = 0; i < nu; ++i)
          for (long q = 0; q < nb; ++q) low_u[(k * nu + i) * P + p0 + q] = i < k ? lu[k][i][q] : 0.0;
        for (long q = 0; q < nb; ++q) d_u[k * P + p0 + q] = du[k][q];
        for (long a = 0; a < na; ++a)
          for (long q = 0; q < nb; ++q) v[k][a][q] = bt[(k * na + a) * P + p0 + q] = h[k][nu + a][q];
        for (long q = 0; q < nb; ++q) rhs_u[k * P + p0 + q] = r[k][q];
      }
      for (long k = 0; k + 1 < nu; ++k)  /* V = L_u^-1 B^T, y = L_u^-1 rhs_u (y in r) */
        for (long i = k + 1; i < nu; ++i) {
          for (long a = 0; a < na; ++a)
            for (long q = 0; q < nb; ++q) v[i][a][q] = MAC64(-lu[i][k][q], v[k][a][q], v[i][a][q]);
          for (long q = 0; q < nb; ++q) r[i][q] = MAC64(-lu[i][k][q], r[k][q], r[i][q]);
        }
      for (long k = 0; k < nu; ++k) {
        for (long q = 0; q < nb; ++q) sc[q] = 1.0 / sqrt(du[k][q]);
        for (long a = 0; a < na; ++a)
          for (long q = 0; q < nb; ++q) v[k][a][q] = v[k][a][q] * sc[q];
        for (long q = 0; q < nb; ++q) du[k][q] = sc[q];  /* (the scale, for the next loop) */
      }
      for (long k = 0; k < nu; ++k) {
        for (long i = 0; i < na; ++i)
          for (long j = 0; j <= i; ++j)
            for (long q = 0; q < nb; ++q) s[i][j][q] = MAC64(-v[k][i][q], v[k][j][q], s[i][j][q]);
        for (long q = 0; q < nb; ++q) coef[q] = r[k][q] * du[k][q];
        for (long i = 0; i < na; ++i)
          for (long q = 0; q < nb; ++q) r[nu + i][q] = MAC64(-v[k][i][q], coef[q], r[nu + i][q]);
      }
    }
    for (long i = 0; i < na; ++i)
      for (long q = 0; q < nb; ++q) s[i][i][q] = s[i][i][q] + (double)lapd[(p0 + q) * na + i];
    ldl_block(na, nb, s, ls, ds);
    for (long i = 0; i < na; ++i) {
      for (long j = 0; j < na; ++j)
        for (long q = 0; q < nb; ++q) low[(i * na + j) * P + p0 + q] = j < i ? (R)ls[i][j][q] : (R)0;
      for (long q = 0; q < nb; ++q) dis[i * P + p0 + q] = (R)(1.0 / sqrt(ds[i][q]));
      for (long q = 0; q < nb; ++q) b[i * P + p0 + q] = (R)r[nu + i][q];
    }
  }
}
"""

_lock = threading.Lock()
_kernels: dict[torch.dtype, object] = {}
_CTYPES = {torch.float32: ("float", "1.17549435082228750797e-38"),
           torch.float64: ("double", "2.22507385850720138309e-308")}


def _kernel(dtype: torch.dtype):
    """``(library, ldl, solve, coupling, schur, cg)`` for ``dtype`` (built once; None: not here)."""
    if dtype in _kernels:
        return _kernels[dtype]
    with _lock:
        if dtype not in _kernels:
            from torchbrdf.kernels import build

            ctype, tiny = _CTYPES[dtype]
            src = _SOURCE % {"R": ctype, "N": MAX_SIZE, "PIVOT": repr(PIVOT_FLOOR), "TINY": tiny,
                             "FMA": int(_aten_fuses()), "FMAF": "fmaf" if ctype == "float" else "fma"}
            p, lg, i = ctypes.c_void_p, ctypes.c_long, ctypes.c_int
            symbols: dict[str, tuple[Sequence[Any], Any]] = {"tb_lane_ldl": ([lg, lg, p, p, p, i], None),
                       "tb_lane_solve": ([lg, lg, lg, p, p, i, i], None),
                       "tb_lane_coupling": ([lg, lg, p, p, p, p, p, p, p, i, i], None),
                       "tb_lane_schur": ([lg, lg, lg] + [p] * 12 + [i], None),
                       "tb_lane_cg": ([lg, lg] + [p] * 10 + [lg, i], lg)}
            lib = build.load_kernel(src, "lane_ops", symbols)
            _kernels[dtype] = None if lib is None else (lib, lib.tb_lane_ldl, lib.tb_lane_solve,
                                                        lib.tb_lane_coupling, lib.tb_lane_schur,
                                                        lib.tb_lane_cg)
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
    low, d = m.new_empty(m.shape), m.new_empty(m.shape[1:])  # (contiguous, as the fake's)
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
    torch.autograd.graph.increment_version(v)  # (as an in-place operator marks its output)
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
    t, out = v.new_empty(v.shape), v.new_empty(v.shape)
    _fn(v.dtype, 3)(n, size, *(m.data_ptr() for m in mats), v.data_ptr(), t.data_ptr(), out.data_ptr(),
                    int(subtract), torch.get_num_threads())
    return out


def _cg(n: int, size: int, mats: list[Tensor], y: Tensor, r: Tensor, iters: int) -> Tensor:
    """The C call of :func:`lane_cg` on checked, contiguous matrices: a new ``y``."""
    y, r = y.contiguous().clone(), r.contiguous().clone()
    scratch = [y.new_empty(y.shape) for _ in range(3)]
    part = y.new_empty(size, dtype=torch.float64)
    _fn(y.dtype, 5)(n, size, *(m.data_ptr() for m in mats), y.data_ptr(), r.data_ptr(),
                    *(t.data_ptr() for t in scratch), part.data_ptr(), int(iters), torch.get_num_threads())
    return y


def _schur(hess: Tensor, diag: Tensor | None, rhs: Tensor, order: list[int], nu: int, lapd: Tensor
           ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    if hess.dim() != 3 or hess.shape[1] != hess.shape[2] or not 0 < hess.shape[1] <= MAX_SCHUR:
        raise ValueError(f"lane_ops: hess must be (P, c, c) with 1 <= c <= MAX_SCHUR = {MAX_SCHUR}, "
                         f"got {tuple(hess.shape)}")
    p, c = hess.shape[0], hess.shape[1]
    if sorted(order) != list(range(c)) or not 0 <= nu < c:
        raise ValueError(f"lane_ops: order must be a permutation of range({c}) and 0 <= nu < {c}, "
                         f"got {order}, {nu}")
    _check("hess", hess, (p, c, c), hess.dtype)
    for name, t, shape in (("diag", diag, (p, c)), ("rhs", rhs, (p, c)), ("lapd", lapd, (p, c - nu))):
        if t is not None:
            _check(name, t, shape, hess.dtype)
    na, f64 = c - nu, torch.float64
    hess, rhs, lapd = hess.contiguous(), rhs.contiguous(), lapd.contiguous()
    diag = None if diag is None else diag.contiguous()
    idx = torch.tensor(order, dtype=torch.long)
    low_u, d_u = hess.new_empty((nu, nu, p), dtype=f64), hess.new_empty((nu, p), dtype=f64)
    bt, rhs_u = hess.new_empty((nu, na, p), dtype=f64), hess.new_empty((nu, p), dtype=f64)
    low, dis, b = hess.new_empty((na, na, p)), hess.new_empty((na, p)), hess.new_empty((na, p))
    _fn(hess.dtype, 4)(p, c, nu, idx.data_ptr(), hess.data_ptr(), None if diag is None else diag.data_ptr(),
                       rhs.data_ptr(), lapd.data_ptr(), low_u.data_ptr(), d_u.data_ptr(), bt.data_ptr(),
                       rhs_u.data_ptr(), low.data_ptr(), dis.data_ptr(), b.data_ptr(),
                       torch.get_num_threads())
    return low_u, d_u, bt, rhs_u, low, dis, b


@torch.library.custom_op("torchbrdf::lane_schur", mutates_args=())
def _lane_schur_op(hess: Tensor, diag: Tensor | None, rhs: Tensor, order: list[int], nu: int, lapd: Tensor
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    return _schur(hess, diag, rhs, order, nu, lapd)


@_lane_schur_op.register_fake
def _(hess, diag, rhs, order, nu, lapd):
    p, c = hess.shape[0], hess.shape[1]
    na, f64 = c - nu, torch.float64
    return (hess.new_empty((nu, nu, p), dtype=f64), hess.new_empty((nu, p), dtype=f64),
            hess.new_empty((nu, na, p), dtype=f64), hess.new_empty((nu, p), dtype=f64),
            hess.new_empty((na, na, p)), hess.new_empty((na, p)), hess.new_empty((na, p)))


@torch.library.custom_op("torchbrdf::lane_ldl", mutates_args=())
def _lane_ldl_op(m: Tensor) -> tuple[Tensor, Tensor]:
    return _ldl(m)


@_lane_ldl_op.register_fake
def _(m):  # (contiguous whatever m's strides: the C loop writes fresh contiguous tensors)
    return m.new_empty(m.shape), m.new_empty(m.shape[1:])


@torch.library.custom_op("torchbrdf::lane_lower_solve_", mutates_args=("v",))
def _lane_lower_op(low: Tensor, v: Tensor) -> None:
    _solve(low, v, False)


@torch.library.custom_op("torchbrdf::lane_upper_solve_", mutates_args=("v",))
def _lane_upper_op(low: Tensor, v: Tensor) -> None:
    _solve(low, v, True)


@torch.library.custom_op("torchbrdf::lane_coupling", mutates_args=())
def _lane_coupling_op(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, v: Tensor,
                      subtract: bool) -> Tensor:
    n, size, mats = _bind(low, d_isqrt, wx, wy)
    _check("v", v, (n, size * size), low.dtype)
    return _couple(n, size, mats, v.contiguous(), subtract)


@_lane_coupling_op.register_fake
def _(low, d_isqrt, wx, wy, v, subtract):
    return v.new_empty(v.shape)


@torch.library.custom_op("torchbrdf::lane_cg", mutates_args=())
def _lane_cg_op(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, y: Tensor, r: Tensor,
                iters: int) -> Tensor:
    n, size, mats = _bind(low, d_isqrt, wx, wy)
    _check("y", y, (n, size * size), low.dtype)
    _check("r", r, (n, size * size), low.dtype)
    return _cg(n, size, mats, y, r, iters)


@_lane_cg_op.register_fake
def _(low, d_isqrt, wx, wy, y, r, iters):
    return y.new_empty(y.shape)


def _direct(*tensors: Tensor | None) -> bool:
    """Whether to call the C loops directly (eager) rather than through the operator: the
    dispatcher's work per call (~tens of µs) is a CG iteration's cost on a small map; under
    torch.compile or a torch.func transform the operator is what they must see, and with an
    input that needs a gradient autograd must (its "no autograd" error, not a detached result)."""
    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        return False
    return not (torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors))


def lane_schur(hess: Tensor, diag: Tensor | None, rhs: Tensor, order: list[int], nu: int, lapd: Tensor
               ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The per-pixel elimination before :func:`torchbrdf.recovery.smoothness_prior.pcg`'s
    iterations, in one pass (bit-identical to its PyTorch form).

    Args:
        hess: ``(P, c, c)`` each pixel's symmetric block, ``c ≤`` :data:`MAX_SCHUR`; float32 or
            float64, CPU.
        diag: ``(P, c)`` added to the blocks' diagonal, or None; ``hess``'s dtype.
        rhs: ``(P, c)`` the right-hand sides; ``hess``'s dtype.
        order: a permutation of ``range(c)``: the ``nu`` channels eliminated per pixel first,
            then the ``na = c − nu`` coupled ones.
        nu: how many channels are eliminated (``0 ≤ nu < c``).
        lapd: ``(P, na)`` added to the complement's diagonal (the Laplacian's); ``hess``'s dtype.

    Returns:
        ``(low_u (nu, nu, P), d_u (nu, P), bt (nu, na, P), rhs_u (nu, P))`` in float64: the
        eliminated block's ``LDLᵀ`` (:func:`lane_ldl`), the coupling ``Bᵀ`` and the right-hand
        sides (for the back substitution); ``(low (na, na, P), d_isqrt (na, P), b (na, P))`` in
        ``hess``'s dtype: the ``LDLᵀ`` of ``S = A − B D⁻¹ Bᵀ + diag(lapd)`` with ``d_isqrt =
        D^-½``, and ``b = rhs_a − B D⁻¹ rhs_u``. Lane-wise, in the reordered channels.

    Raises:
        ValueError: a shape, dtype or device the kernel cannot read, or a bad ``order`` (named).
    """
    order = [int(a) for a in order]
    if _direct(hess, diag, rhs, lapd):
        return _schur(hess, diag, rhs, order, int(nu), lapd)
    return _lane_schur_op(hess, diag, rhs, order, int(nu), lapd)


def lane_ldl(m: Tensor) -> tuple[Tensor, Tensor]:
    """``LDLᵀ`` of ``m (n, n, P)`` lane-wise (its lower triangle read), as
    :func:`torchbrdf.recovery.pixel_systems.ldl_factor`: ``low (n, n, P)`` (the strict lower
    triangle of ``L``, zeros elsewhere) and the pivots ``d (n, P)``, each at least
    :data:`PIVOT_FLOOR` of its diagonal entry plus the dtype's smallest normal number. ``m``'s
    dtype (float32 or float64), CPU.

    Raises:
        ValueError: a shape, dtype or device the kernel cannot read (named).
    """
    return _ldl(m) if _direct(m) else _lane_ldl_op(m)


def lane_lower_solve(low: Tensor, v: Tensor) -> Tensor:
    """``v ← L⁻¹ v`` in place (``L`` unit lower triangular from :func:`lane_ldl`), ``low (n, n, P)``,
    ``v (n, ..., P)`` contiguous, ``low``'s dtype, CPU. Returns ``v``."""
    _solve(low, v, False) if _direct(low, v) else _lane_lower_op(low, v)
    return v


def lane_upper_solve(low: Tensor, v: Tensor) -> Tensor:
    """``v ← L⁻ᵀ v`` in place, as :func:`lane_lower_solve`. Returns ``v``."""
    _solve(low, v, True) if _direct(low, v) else _lane_upper_op(low, v)
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


def lane_cg(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor, y: Tensor, r: Tensor, iters: int) -> Tensor:
    """Conjugate-gradient iterations on ``(I − K) y = G⁻¹ b`` (:func:`lane_coupling`'s ``K``) in one
    call: the loop of :func:`torchbrdf.recovery.smoothness_prior.pcg`.

    ``low``, ``d_isqrt``, ``wx``, ``wy`` as for :func:`lane_coupling`; ``y (n, P)`` the start and
    ``r (n, P)`` its residual ``G⁻¹ b − (I − K) y``, finite; ``iters ≥ 0`` iterations at most.
    Each iteration is two passes over the vectors (the operator with the new search direction
    and ``dᵀ(I − K)d``; the updates of ``y`` and ``r`` with ``rᵀr``); the dot products are summed
    in float64 by grid rows, then over the rows in order, so the result has the same bits at any
    thread count (not those of the PyTorch loop, whose float32 BLAS dot products round
    otherwise). A breakdown (``dᵀ(I − K)d`` not positive and finite) stops the iterations there,
    as the PyTorch loop does. One dtype (float32 or float64), CPU. Returns a new ``(n, P)``
    tensor; ``y`` and ``r`` are left as they are.

    Raises:
        ValueError: a shape, dtype or device the kernel cannot read, or ``iters < 0`` (named).
    """
    if int(iters) < 0:
        raise ValueError(f"lane_cg: iters must be >= 0, got {iters}")
    if not _direct(low, d_isqrt, wx, wy, y, r):
        return _lane_cg_op(low, d_isqrt, wx, wy, y, r, int(iters))
    n, size, mats = _bind(low, d_isqrt, wx, wy)
    _check("y", y, (n, size * size), low.dtype)
    _check("r", r, (n, size * size), low.dtype)
    return _cg(n, size, mats, y, r, int(iters))


def coupling_operator(low: Tensor, d_isqrt: Tensor, wx: Tensor, wy: Tensor
                      ) -> Callable[[Tensor, bool], Tensor]:
    """:func:`lane_coupling` bound to its matrices (checked once, for a CG loop's many calls):
    a function of ``(v (n, P), subtract)``."""
    n, size, mats = _bind(low, d_isqrt, wx, wy)
    bound_grad = any(m.requires_grad for m in mats)  # (once: a CG loop calls this many times)

    def apply(v: Tensor, subtract: bool) -> Tensor:
        if not _direct() or ((bound_grad or v.requires_grad) and torch.is_grad_enabled()):
            return _lane_coupling_op(*mats, v, bool(subtract))
        if v.shape != (n, size * size) or v.dtype != low.dtype or v.device != low.device:
            _check("v", v, (n, size * size), low.dtype)  # raises, naming it
        return _couple(n, size, mats, v.contiguous(), subtract)

    return apply
