"""Small symmetric positive definite systems, one per pixel, stored lane-wise.

A batch of ``n × n`` matrices is a tensor ``(n, n, P)``: entry ``(i, j)`` of every pixel's
matrix is one contiguous lane of ``P`` values, and a vector batch is ``(n, ..., P)``. Each step
of a factorisation or a substitution is then one multiply-add over all the pixels' lanes at
once: for the recovery's 2×2 to 7×7 blocks on maps of 128² pixels and more that is faster on
CPU than batched LAPACK calls (a fixed cost per small matrix) or a batched ``bmm``, and it runs
unchanged on a GPU, with no host synchronisation. (On a few thousand pixels the fixed cost of
each operation dominates instead.)

The factorisation is ``LDLᵀ`` (unit lower triangular ``L``, diagonal ``D``): no square root,
and a pivot that rounding leaves at or below zero is raised to :data:`PIVOT_FLOOR` of its
diagonal entry, so a numerically singular block gives a large but finite solution instead
of a NaN that a coupled solve would spread to every pixel.

On CPU tensors (float32, float64) the factorisation and the substitutions run as the C operators
of :mod:`torchbrdf.kernels.lane_ops` (every entry of a block of pixels in cache, one call instead
of one per entry), with bit-identical results; the PyTorch forms here serve elsewhere (CUDA, no
C compiler, the eager backend, autograd) and as the reference.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchbrdf.brdf import principled

#: A pivot of ``LDLᵀ`` is at least this fraction of its matrix's diagonal entry (plus the
#: dtype's smallest normal number). A positive definite block in float64 keeps its pivots far
#: above it; only a numerically singular one (a direction with no data and no damping) meets it.
PIVOT_FLOOR = 1e-12


def c_kernels(*tensors: Tensor | None, size: int) -> bool:
    """Whether the lane-wise C operators (:mod:`torchbrdf.kernels.lane_ops`) take these tensors
    (None entries are skipped) for ``size × size`` systems: all on the CPU in one dtype, float32
    or float64, none needing a gradient, no torch.func transform active, the fused backend "c"
    (:func:`torchbrdf.brdf.principled.fused_backend`: the eager backend, tensor subclasses or
    tracing keep the PyTorch forms), ``size`` at most
    :data:`torchbrdf.kernels.lane_ops.MAX_SIZE` and a C compiler here."""
    ts = [x for x in tensors if x is not None]
    t = ts[0]
    if t.device.type != "cpu" or t.dtype not in (torch.float32, torch.float64) or t.numel() == 0:
        return False
    if any(x.device != t.device or x.dtype != t.dtype for x in ts):
        return False
    if torch.is_grad_enabled() and any(x.requires_grad for x in ts):
        return False
    if torch._C._are_functorch_transforms_active():  # (the operators have no batching rules)
        return False
    if principled.fused_backend(t.device, t.dtype, ts, lambda: principled.FAST_PATH_MIN_LANES) != "c":
        return False
    from torchbrdf.kernels import lane_ops

    return size <= lane_ops.MAX_SIZE and lane_ops.available(t)


def to_lanes(m: Tensor, dtype: torch.dtype = torch.float64, order: list[int] | None = None) -> Tensor:
    """Batched matrices ``m (P, n, n)`` as lanes ``(k, k, P)`` in ``dtype``: always a fresh copy.

    ``order``: the ``k`` rows and columns to keep, in that order (None: all ``n`` as they are),
    so that the blocks of a reordered matrix are views. (Transposing in ``m``'s own dtype and
    then converting, lane by lane where reordered, is several times faster on CPU than a
    converting, transposing copy or a gather.)
    """
    n = m.shape[-1]
    flat = m.reshape(-1, n * n).T.contiguous()  # (n², P)
    if order is None:
        return flat.to(dtype, copy=True).view(n, n, -1)
    out = flat.new_empty((len(order), len(order), flat.shape[1]), dtype=dtype)
    for i, a in enumerate(order):
        for j, b in enumerate(order):
            out[i, j].copy_(flat[a * n + b])
    return out


def ldl_factor(m: Tensor) -> tuple[Tensor, Tensor]:
    """``LDLᵀ`` of symmetric positive definite matrices stored lane-wise.

    ``m (n, n, P)``: only its lower triangle is read. Returns ``low (n, n, P)``, whose strict
    lower triangle is that of ``L`` (the entries on and above the diagonal are left unwritten:
    the unit diagonal is implied, and no solve reads them), and ``d (n, P)``, the pivots, each
    at least :data:`PIVOT_FLOOR` of its diagonal entry. ``m``'s dtype and device.
    """
    if c_kernels(m, size=m.shape[0]):
        from torchbrdf.kernels import lane_ops

        return lane_ops.lane_ldl(m)
    n = m.shape[0]
    low = torch.empty_like(m)  # (zeroing it costs as much as the factorisation at n = 5)
    d = torch.empty_like(m[0])
    floor = torch.diagonal(m).abs().T.mul_(PIVOT_FLOOR).add_(torch.finfo(m.dtype).tiny)  # (n, P)
    for j in range(n):
        col = m[j:, j].clone()  # (n - j, P): column j of L D, from the diagonal down
        for k in range(j):
            col.addcmul_(low[j:, k], low[j, k] * d[k], value=-1.0)
        d[j] = torch.maximum(col[0], floor[j])
        low[j + 1:, j] = col[1:] / d[j]
    return low, d


def cholesky_factor(a: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factors ``(k, k, n)`` of ``n`` symmetric ``a (k, k, n)`` stored lane-wise,
    and ``(n,)`` bool whether each is positive definite to rounding (a factor that is not has
    a unit diagonal where it failed, so that solves with it stay finite). ``a``'s dtype and
    device. For callers that leave such pixels out; :func:`ldl_factor` floors their pivots
    instead."""
    k = a.shape[0]
    low = torch.zeros_like(a)
    good = torch.ones(a.shape[-1], dtype=torch.bool, device=a.device)
    for j in range(k):
        d = a[j, j] - low[j, :j].pow(2).sum(0)
        ok = d > 0  # False for NaN too
        good &= ok
        low[j, j] = torch.where(ok, d, 1.0).sqrt()
        if j + 1 < k:
            low[j + 1:, j] = (a[j + 1:, j] - (low[j + 1:, :j] * low[j, :j]).sum(1)) / low[j, j]
    return low, good


def _lane(v: Tensor, like: Tensor) -> Tensor:
    """``v (k, P)`` shaped to broadcast against ``like (k, ..., P)``."""
    return v.reshape(v.shape[0], *([1] * (like.dim() - 2)), v.shape[-1])


def lower_solve(low: Tensor, v: Tensor) -> Tensor:
    """``v ← L⁻¹ v`` in place for the unit lower triangular ``L`` of :func:`ldl_factor`.

    ``low (n, n, P)``, ``v (n, ..., P)`` (any number of right-hand sides per pixel between).
    Returns ``v``.
    """
    if v.is_contiguous() and c_kernels(low, v, size=low.shape[0]):
        from torchbrdf.kernels import lane_ops

        return lane_ops.lane_lower_solve(low, v)
    n = low.shape[0]
    for k in range(n - 1):
        rest = v[k + 1:]
        rest.addcmul_(_lane(low[k + 1:, k], rest), v[k:k + 1], value=-1.0)
    return v


def upper_solve(low: Tensor, v: Tensor) -> Tensor:
    """``v ← L⁻ᵀ v`` in place, ``L`` and the shapes as in :func:`lower_solve`. Returns ``v``."""
    if v.is_contiguous() and c_kernels(low, v, size=low.shape[0]):
        from torchbrdf.kernels import lane_ops

        return lane_ops.lane_upper_solve(low, v)
    for k in range(low.shape[0] - 1, 0, -1):
        head = v[:k]
        head.addcmul_(_lane(low[k, :k], head), v[k:k + 1], value=-1.0)
    return v


def ldl_solve(low: Tensor, d_inv: Tensor, v: Tensor) -> Tensor:
    """``v ← (L D Lᵀ)⁻¹ v`` in place: ``low`` from :func:`ldl_factor`, ``d_inv (n, P)`` the
    reciprocals of its pivots, ``v (n, ..., P)``. Returns ``v``."""
    lower_solve(low, v)
    v.mul_(_lane(d_inv, v))
    return upper_solve(low, v)


def inverse_diagonal(m: Tensor) -> Tensor:
    """The diagonal ``(n, P)`` of each lane-wise matrix's inverse, ``m (n, n, P)`` positive definite.

    ``diag(M⁻¹)_i = Σ_k X_ki² / d_k`` with ``M = L D Lᵀ`` (:func:`ldl_factor`) and ``X = L⁻¹``,
    unit lower triangular like ``L``: only its strict lower triangle is computed, row by row
    (``X_ij = −Σ_{j≤k<i} L_ik X_kj``), none of the off-diagonal entries of ``M⁻¹``. ``m``'s
    dtype and device.
    """
    n = m.shape[0]
    low, d = ldl_factor(m)
    d_inv = 1.0 / d
    out = d_inv.clone()  # the k = i terms (X_ii = 1)
    rows: list[Tensor] = []  # rows[i] = X[i, :i]  (i, P)
    for i in range(n):
        x = -low[i, :i]  # the k = j terms (X_jj = 1)
        for k in range(1, i):
            x[:k].addcmul_(low[i, k], rows[k], value=-1.0)
        rows.append(x)
        out[:i].addcmul_(x * x, d_inv[i])
    return out
