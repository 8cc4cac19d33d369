"""The recovery's unknowns: unconstrained per-pixel parameters and the maps they decode to.

Each pixel has ``N_PARAMS`` = 7 unknowns: logits of base colour (3), specular and roughness (the
latter onto ``[R_MIN, R_MAX]``) and a normal slope ``(p, q)`` with ``n ∝ (p, q, 1)``.
Metallic is held apart (a class per pixel, or a continuous value in the final stage).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


N_PARAMS = 7  # logit base (3), logit specular, logit roughness, slope p, slope q


R_MIN, R_MAX = 0.03, 1.0  # roughness range the logit maps onto (alpha floor is 1e-3)


def decode_slots(n_t: int = N_PARAMS) -> tuple[tuple[int, ...], ...]:
    """The unknowns (columns of ``theta``, then metallic as column 7) whose decode tangents share a row.

    For the first ``n_t`` unknowns (7, or 8 with a continuous metallic): each of the base-colour,
    specular, roughness (and metallic) logits moves one channel of its own parameter in
    :func:`decode`, so one direction along all of them holds their tangents at once (row 0);
    each normal slope moves the whole normal (rows 1 and 2).
    """
    return ((0, 1, 2, 3, 4, 7) if n_t > N_PARAMS else (0, 1, 2, 3, 4)), (5,), (6,)


def decode_pattern(n_t: int = N_PARAMS) -> dict[str, list[tuple[int, int, int]]]:
    """The non-zero ``(unknown, channel, row)`` tangents of :func:`decode`'s parameters.

    Rows as in :func:`decode_slots`; ``n_t`` as there (metallic has a tangent only with 8).
    """
    pattern = {"base_color": [(0, 0, 0), (1, 1, 0), (2, 2, 0)], "specular": [(3, 0, 0)],
               "roughness": [(4, 0, 0)], "normal": [(j, c, j - 4) for j in (5, 6) for c in range(3)]}
    if n_t > N_PARAMS:
        pattern["metallic"] = [(7, 0, 0)]
    return pattern


def logit(x: Tensor, lo: float = 0.0, hi: float = 1.0, eps: float = 1e-4) -> Tensor:
    """The logit of ``x`` (any shape) mapped from ``[lo, hi]`` onto [0, 1], clamped ``eps`` inside its ends."""
    t = ((x - lo) / (hi - lo)).clamp(eps, 1 - eps)
    return torch.log(t) - torch.log1p(-t)


def decode(theta: Tensor, metal: Tensor) -> dict:
    """Principled parameters ``(P, C)`` from unconstrained ``theta (P, 7)`` and ``metal (P, 1)``."""
    s = torch.sigmoid(theta[:, 0:5])  # one op for the five logits (decode runs ~700 times a fit)
    # (no arithmetic with Python numbers: under vmap of jvp, as the fit's Jacobian runs it, each
    # such op takes a decomposition's slow path; this form halves that call's fixed cost)
    lo, hi = (torch.full((1,), v, dtype=theta.dtype, device=theta.device) for v in (R_MIN, R_MAX))
    rough = torch.lerp(lo, hi, s[:, 4:5])  # (filled on the device: no copy from the host, no sync)
    n = F.pad(theta[:, 5:7], (0, 1), value=1.0)
    n = n * torch.rsqrt((n * n).sum(-1, keepdim=True))
    return {"base_color": s[:, 0:3], "specular": s[:, 3:4], "roughness": rough, "metallic": metal,
            "normal": n}


def decode_jvp(x: Tensor, metal: Tensor, tangents: Tensor) -> tuple[dict, dict]:
    """:func:`decode` and its derivatives along ``K`` directions of the unknowns, in closed form.

    ``x (P, 7)``: theta, with ``metal (P, 1)``; or ``(P, 8)``: theta and a continuous metallic
    (``metal`` is then unused); ``tangents (K, P, x's columns)``. Returns ``(params, dparams)``:
    :func:`decode`'s dict and one of ``(K, P, C)`` tangents for each of its entries (metallic's
    only with 8 columns), in ``x``'s dtype, on its device: what ``torch.func.vmap`` of
    ``torch.func.jvp`` of :func:`decode` gives, without the transforms' work per call. Each
    tangent is the derivative rule autograd's forward mode applies to that step of
    :func:`decode`, in its order of operations, so the two agree to the last bit: per channel
    ``σ' = (1 − σ) σ`` of the five logits (``sigmoid_backward``) and the roughness's
    ``σ' (R_MAX − R_MIN)``; the normal ``n = u / |u|``, ``u = (p, q, 1)``, through
    ``d|u|⁻¹ = −½ d(u·u) |u|⁻³``.
    """
    theta, metal_t = (x[:, :7], x[:, 7:8]) if x.shape[1] == 8 else (x, None)
    p = decode(theta, x[:, 7:8] if metal_t is not None else metal)
    ds = torch.ops.aten.sigmoid_backward(tangents[..., 0:5], torch.sigmoid(theta[:, 0:5]))
    lo, hi = (torch.full((1,), v, dtype=x.dtype, device=x.device) for v in (R_MIN, R_MAX))
    u = F.pad(theta[:, 5:7], (0, 1), value=1.0)
    inv = torch.rsqrt((u * u).sum(-1, keepdim=True))
    du = F.pad(tangents[..., 5:7], (0, 1), value=0.0)
    d_uu = (du * u + du * u).sum(-1, keepdim=True)
    d_inv = -0.5 * d_uu * inv.pow(3)
    dp = {"base_color": ds[..., 0:3], "specular": ds[..., 3:4], "roughness": ds[..., 4:5] * (hi - lo),
          "normal": d_inv * u + du * inv}
    if metal_t is not None:
        dp["metallic"] = tangents[..., 7:8]
    return p, dp


def encode(params: dict) -> Tensor:
    """Inverse of :func:`decode` for ``(P, C)`` parameter tensors."""
    n = params["normal"]
    nz = n[:, 2:3].clamp(min=0.05)
    return torch.cat(
        (
            logit(params["base_color"]),
            logit(params["specular"]),
            logit(params["roughness"], R_MIN, R_MAX),
            n[:, 0:1] / nz,
            n[:, 1:2] / nz,
        ),
        -1,
    )
