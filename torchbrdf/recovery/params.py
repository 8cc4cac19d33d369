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
