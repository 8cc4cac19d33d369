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
