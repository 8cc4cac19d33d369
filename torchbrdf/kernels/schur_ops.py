"""A joint light step's per-pixel elimination as a PyTorch operator: ``torch.ops.torchbrdf.light_schur``.

A Gauss–Newton step on the lights with each pixel's 7 unknowns eliminated (a Schur complement,
as in bundle adjustment; :func:`torchbrdf.recovery.calibration.light_joint_step`) needs, per
pixel, ``A = JpᵀWJp + H``, its Cholesky factor ``L`` and ``Y = L⁻¹ [JpᵀWJg | gp]``, then
``Σ YᵀY`` over the pixels and, per light, ``Σ [Jg | r]ᵀ W [Jg | r]``. In PyTorch that is a few
hundred vector operations over ``(residuals, 7, pixels)`` arrays, each one a pass through
memory; here one C loop does each block of 8 pixels in cache (pixels innermost, so the 7×7
algebra vectorises across them), and ``Σ YᵀY`` stays one BLAS product per chunk of pixels.
CPU only (on a GPU the PyTorch form is one launch per operation over every pixel). The
operator has no autograd (its outputs are already second-order terms) and a fake
implementation for ``torch.compile``.

Everything runs in float64 from the loads on (``Σ YᵀY`` nearly cancels ``Σ JgᵀWJg`` along the
directions the maps almost absorb), whatever the inputs' dtype.
"""

from __future__ import annotations

import ctypes
import threading

import torch
from torch import Tensor

from torchbrdf.kernels import build
from torchbrdf.kernels.normal_eq_ops import unpack_jtj

__all__ = ["light_schur", "light_schur_op", "available", "MAX_RESIDUALS"]

#: The kernel keeps a block's ``(M, 7, 8)`` float64 working arrays on the thread's stack: at
#: most this many residuals per pixel (``3 L``; 256 lights, ~0.8 MB of stack, within the 2 MB
#: or more an OpenMP worker thread gets).
MAX_RESIDUALS = 768

_SOURCE = r"""
#include <math.h>
typedef %(R)s R;
#define BP 8
/* One chunk of n pixels (of N in cols' pixel dimension): per block of BP pixels, A, its
   Cholesky factor, Y = L^-1 [B | gp] (written pixels innermost to y (L G + 1, 7, n)) and, per
   pixel and light, the upper triangle of [Jg | r]^T W [Jg | r] (to pl (n, L, P)). base1: cols'
   first row is the base colour's three unknowns in one direction, each on its own channel's
   residuals (3 l + c for unknown c; the other channels' entries are zeros), then the other 4. */
void tb_light_schur(long n, long N, long M, long G, const R* cols, const R* res, const double* pg,
                    const double* ph, double damping, double huber, double* y, double* pl, int nthreads,
                    int base1) {
  const long L = M / 3, P = (G + 1) * (G + 2) / 2, K0 = base1 ? 5 : 7;
  #pragma omp parallel for schedule(static) num_threads(nthreads)
  for (long b0 = 0; b0 < n; b0 += BP) {
    const long nb = n - b0 < BP ? n - b0 : BP;
    double jp[M][7][BP], z[M][7][BP], rt[M][BP], w[M][BP];
    double a[7][7][BP], gp[7][BP], low[7][7][BP], f[BP], t[BP];
    /* each pixel's rows read in memory order (a loop over the pixels inside would stride by M) */
    for (long q = 0; q < BP; ++q) {
      for (long m = 0; m < M; ++m) rt[m][q] = q < nb ? (double)res[(b0 + q) * M + m] : 0.0;
      for (int i = 0; i < 7; ++i) {
        const long row = base1 ? (i < 3 ? 0 : i - 2) : i;
        for (long m = 0; m < M; ++m)
          jp[m][i][q] = q < nb && !(base1 && i < 3 && m %% 3 != i) ? (double)cols[(row * N + b0 + q) * M + m] : 0.0;
      }
    }
    for (long m = 0; m < M; ++m) {
      _Pragma("omp simd") for (long q = 0; q < BP; ++q) {
        double r = rt[m][q];
        double h = huber / (fabs(r) > 1e-30 ? fabs(r) : 1e-30);
        w[m][q] = h < 1.0 ? h : 1.0;  /* Huber: 3 noise deviations */
      }
      for (int i = 0; i < 7; ++i)
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) z[m][i][q] = jp[m][i][q] * w[m][q];
    }
    for (int i = 0; i < 7; ++i)
      _Pragma("omp simd") for (long q = 0; q < BP; ++q) {
        gp[i][q] = 0.0;
        for (int j = 0; j <= i; ++j) a[i][j][q] = 0.0;
      }
    for (long m = 0; m < M; ++m)
      for (int i = 0; i < 7; ++i) {
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) gp[i][q] += z[m][i][q] * rt[m][q];
        for (int j = 0; j <= i; ++j)
          _Pragma("omp simd") for (long q = 0; q < BP; ++q) a[i][j][q] += z[m][i][q] * jp[m][j][q];
      }
    for (int i = 0; i < 7; ++i)
      _Pragma("omp simd") for (long q = 0; q < BP; ++q) {
        const double d = a[i][i][q], k = q < nb ? ph[(b0 + q) * 7 + i] : 0.0;
        a[i][i][q] = d + (damping * d + 1e-9 + k);
        gp[i][q] += q < nb ? pg[(b0 + q) * 7 + i] : 0.0;
      }
    /* Cholesky; f = 0 marks a pixel left out (not positive definite, or past the chunk) */
    _Pragma("omp simd") for (long q = 0; q < BP; ++q) f[q] = q < nb ? 1.0 : 0.0;
    for (int j = 0; j < 7; ++j) {
      _Pragma("omp simd") for (long q = 0; q < BP; ++q) {
        double d = a[j][j][q];
        for (int k = 0; k < j; ++k) d -= low[j][k][q] * low[j][k][q];
        const int ok = d > 0;
        f[q] = ok ? f[q] : 0.0;
        low[j][j][q] = sqrt(ok ? d : 1.0);
      }
      for (int i = j + 1; i < 7; ++i)
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) {
          double s = a[i][j][q];
          for (int k = 0; k < j; ++k) s -= low[i][k][q] * low[j][k][q];
          low[i][j][q] = s / low[j][j][q];
        }
    }
    /* z = L^-1 (Jp^T W), one residual row at a time, and L^-1 gp: forward substitution */
    for (long m = 0; m < M; ++m)
      for (int k = 0; k < 7; ++k) {
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) t[q] = z[m][k][q] * f[q];
        for (int j = 0; j < k; ++j)
          _Pragma("omp simd") for (long q = 0; q < BP; ++q) t[q] -= z[m][j][q] * low[k][j][q];
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) z[m][k][q] = t[q] / low[k][k][q];
      }
    for (int k = 0; k < 7; ++k) {
      _Pragma("omp simd") for (long q = 0; q < BP; ++q) t[q] = gp[k][q] * f[q];
      for (int j = 0; j < k; ++j)
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) t[q] -= gp[j][q] * low[k][j][q];
      _Pragma("omp simd") for (long q = 0; q < BP; ++q) gp[k][q] = t[q] / low[k][k][q];
    }
    for (long l = 0; l < L; ++l) {
      double v[G + 1][3][BP], acc[P][BP];
      for (long q = 0; q < BP; ++q)
        for (long g = 0; g < G; ++g)
          for (int c = 0; c < 3; ++c)
            v[g][c][q] = q < nb ? (double)cols[((K0 + g) * N + b0 + q) * M + 3 * l + c] : 0.0;
      for (int c = 0; c < 3; ++c)
        _Pragma("omp simd") for (long q = 0; q < BP; ++q) v[G][c][q] = rt[3 * l + c][q];
      for (long g = 0; g < G; ++g)  /* Y's rows of light l: sum over its colours of z Jg */
        for (int i = 0; i < 7; ++i) {
          _Pragma("omp simd") for (long q = 0; q < BP; ++q)
            t[q] = z[3 * l][i][q] * v[g][0][q] + z[3 * l + 1][i][q] * v[g][1][q]
                   + z[3 * l + 2][i][q] * v[g][2][q];
          double* o = y + ((l * G + g) * 7 + i) * n + b0;
          if (nb == BP)  /* a whole block: vector stores */
            _Pragma("omp simd") for (long q = 0; q < BP; ++q) o[q] = t[q];
          else
            for (long q = 0; q < nb; ++q) o[q] = t[q];
        }
      for (long u = 0; u < P; ++u) _Pragma("omp simd") for (long q = 0; q < BP; ++q) acc[u][q] = 0.0;
      for (int c = 0; c < 3; ++c) {
        long u = 0;
        for (long i = 0; i <= G; ++i)
          for (long j = i; j <= G; ++j, ++u)
            _Pragma("omp simd") for (long q = 0; q < BP; ++q)
              acc[u][q] += f[q] * w[3 * l + c][q] * v[i][c][q] * v[j][c][q];
      }
      for (long q = 0; q < nb; ++q)
        for (long u = 0; u < P; ++u) pl[((b0 + q) * L + l) * P + u] = acc[u][q];
    }
    for (int i = 0; i < 7; ++i)
      for (long q = 0; q < nb; ++q) y[((L * G) * 7 + i) * n + b0 + q] = gp[i][q];
  }
}
"""

_lock = threading.Lock()
_kernels: dict[str, object] = {}


def _kernel(ctype: str):
    """The C function for inputs of C type ``ctype`` (built once; None: it cannot be built here)."""
    if ctype in _kernels:
        return _kernels[ctype]
    with _lock:
        if ctype not in _kernels:
            args = [ctypes.c_long] * 4 + [ctypes.c_void_p] * 4 + [ctypes.c_double] * 2 \
                + [ctypes.c_void_p] * 2 + [ctypes.c_int] * 2
            lib = build.load_kernel(_SOURCE % {"R": ctype}, "light_schur", {"tb_light_schur": (args, None)})
            # the library stays alive with its function
            _kernels[ctype] = None if lib is None else (lib, lib.tb_light_schur)
        return _kernels[ctype]


def available(r: Tensor) -> bool:
    """Whether :func:`light_schur` runs on residuals like ``r``: a CPU float32/float64 tensor
    of at most :data:`MAX_RESIDUALS` per pixel, with a C compiler (built on the first call)."""
    if r.device.type != "cpu" or r.dtype not in (torch.float32, torch.float64) or r.shape[-1] > MAX_RESIDUALS:
        return False
    return _kernel(_ctype(r.dtype)) is not None


def _ctype(dtype: torch.dtype) -> str:
    return "float" if dtype == torch.float32 else "double"


@torch.library.custom_op("torchbrdf::light_schur", mutates_args=())
def light_schur_op(r: Tensor, cols: Tensor, prior_g: Tensor, prior_h: Tensor, damping: float, huber: float,
                   chunk: int, base_one: bool = False) -> tuple[Tensor, Tensor]:
    """``(per_light (L, G+1, G+1), gram (L G + 1, L G + 1))``, float64: see :func:`light_schur`."""
    _check_memory(r, cols, prior_g, prior_h, chunk)
    n, M = r.shape
    G, L = cols.shape[0] - _pixel_rows(base_one), M // 3
    f64 = torch.float64
    P = (G + 1) * (G + 2) // 2
    per = torch.zeros(L, P, dtype=f64)
    gram = torch.zeros(L * G + 1, L * G + 1, dtype=f64)
    if n == 0:
        return unpack_jtj(per, G + 1), gram
    fn = _kernel(_ctype(r.dtype))
    if fn is None:
        raise RuntimeError("light_schur: the C kernel cannot be built here (ask schur_ops.available first)")
    r, cols = r.contiguous(), cols.contiguous()
    pg, ph = prior_g.to(f64).contiguous(), prior_h.to(f64).contiguous()
    item, nt = r.element_size(), torch.get_num_threads()
    y = torch.empty(L * G + 1, 7, min(chunk, n), dtype=f64)
    pl = torch.empty(min(chunk, n), L, P, dtype=f64)
    for lo in range(0, n, chunk):
        m = min(chunk, n - lo)
        yc = y if m == y.shape[-1] else torch.empty(L * G + 1, 7, m, dtype=f64)
        fn[1](m, n, M, G, cols.data_ptr() + lo * M * item, r.data_ptr() + lo * M * item,
              pg.data_ptr() + lo * 7 * 8, ph.data_ptr() + lo * 7 * 8, damping, huber, yc.data_ptr(),
              pl.data_ptr(), nt, int(base_one))
        flat = yc.view(L * G + 1, -1)
        gram.addmm_(flat, flat.T)
        per += pl[:m].sum(0)
    return unpack_jtj(per, G + 1), gram


@light_schur_op.register_fake
def _(r, cols, prior_g, prior_h, damping, huber, chunk, base_one=False):
    G, L = cols.shape[0] - _pixel_rows(base_one), r.shape[1] // 3
    return (r.new_empty((L, G + 1, G + 1), dtype=torch.float64),
            r.new_empty((L * G + 1, L * G + 1), dtype=torch.float64))


def _pixel_rows(base_one: bool) -> int:
    """The rows of ``cols`` along a pixel's 7 unknowns: 5 with the base colour in one direction."""
    return 5 if base_one else 7


def _check_memory(r: Tensor, cols: Tensor, prior_g: Tensor, prior_h: Tensor, chunk: int) -> None:
    """Refuse what the C loop would read wrongly: it takes raw CPU pointers of one float type
    and keeps a block's residuals on its stack (shapes: :func:`light_schur`)."""
    if r.dim() != 2:
        raise ValueError(f"light_schur: r must be (n, M), got shape {tuple(r.shape)}")
    if r.dtype not in (torch.float32, torch.float64) or cols.dtype != r.dtype:
        raise ValueError(f"light_schur: r and cols must share a dtype, float32 or float64, got {r.dtype}, {cols.dtype}")
    devices = {name: t.device for name, t in (("r", r), ("cols", cols), ("prior_g", prior_g), ("prior_h", prior_h))}
    if any(d.type != "cpu" for d in devices.values()):
        raise ValueError(f"light_schur: every tensor must be on the CPU (see available()), got {devices}")
    if not 0 < r.shape[1] <= MAX_RESIDUALS:  # (the loop's stack arrays have M rows: none is undefined in C)
        raise ValueError(f"light_schur: 1 to MAX_RESIDUALS = {MAX_RESIDUALS} residuals per pixel, got {r.shape[1]}")
    if chunk < 1:
        raise ValueError(f"light_schur: chunk must be a positive number of pixels, got {chunk}")


def light_schur(r: Tensor, cols: Tensor, prior_g: Tensor, prior_h: Tensor, damping: float, huber: float,
                chunk: int = 1024, base_one: bool = False) -> tuple[Tensor, Tensor]:
    """The per-pixel elimination of a joint light step, summed over the pixels.

    Args:
        r: ``(n, M)`` residuals, ``M = 3 L ≤`` :data:`MAX_RESIDUALS` light-major (``3 l + c``),
            every one finite; CPU, float32 or float64 (:func:`available`).
        cols: ``(7 + G, n, M)`` their derivatives along each pixel's 7 unknowns, then the ``G``
            unknowns of each light (a light's residuals depend only on its own), ``r``'s dtype;
            with ``base_one`` ``(5 + G, n, M)``: the first row along the three base-colour
            unknowns at once (unknown ``c`` moves only the residuals ``3 l + c`` of its own
            channel, so one direction gives all three columns; the rest of that row is not
            read as theirs), then the other four.
        prior_g, prior_h: ``(n, 7)`` the pixels' prior gradient and Hessian diagonal (zeros:
            none), finite, any float dtype, CPU.
        damping: ``A``'s diagonal grows by ``damping`` times itself plus ``1e-9``.
        huber: the Huber threshold: a residual's weight is ``min(1, huber / |r|)``.
        chunk: pixels per ``Σ YᵀY`` product (its float64 ``Y`` stays in cache).
        base_one: ``cols``' layout, as above; the same results, bit for bit, as the full layout
            with the other channels' entries of the base-colour rows zero.

    Returns:
        ``per_light (L, G+1, G+1)``: ``Σ [Jg | r]ᵀ W [Jg | r]`` per light, and ``gram (L G + 1,
        L G + 1)``: ``Σ [B | gp]ᵀ A⁻¹ [B | gp]`` (rows light-major, the last one ``gp``), with
        ``A = JpᵀWJp + H`` (``H``: the damping and ``prior_h``), ``B = JpᵀWJg`` and ``gp =
        JpᵀWr + prior_g``, float64 on the CPU. A pixel whose ``A`` is not positive definite to
        rounding adds nothing.

    Raises:
        ValueError: a shape, dtype or device the kernel cannot read (named).
    """
    _check_memory(r, cols, prior_g, prior_h, int(chunk))
    n, M = r.shape
    k0 = _pixel_rows(base_one)
    if cols.dim() != 3 or cols.shape[0] < k0 or tuple(cols.shape[1:]) != (n, M) or M % 3:
        raise ValueError(f"light_schur: cols must be ({k0} + G, {n}, {M}) with M = 3 L, got {tuple(cols.shape)}")
    if tuple(prior_g.shape) != (n, 7) or tuple(prior_h.shape) != (n, 7):
        raise ValueError(f"light_schur: the priors must have shape ({n}, 7), got {tuple(prior_g.shape)}, "
                         f"{tuple(prior_h.shape)}")
    return light_schur_op(r, cols, prior_g, prior_h, float(damping), float(huber), int(chunk), bool(base_one))
