"""The recovery's unknowns: unconstrained per-pixel parameters and the maps they decode to.

Each pixel has ``N_PARAMS`` = 7 unknowns: logits of base colour (3), specular and roughness (the
latter onto ``[R_MIN, R_MAX]``) and a normal slope ``(p, q)`` with ``n ∝ (p, q, 1)``.
Metallic is held apart (a class per pixel, or a continuous value in the final stage).
"""

from __future__ import annotations

from collections.abc import Sequence

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
    return _decoded(theta, metal)[0]


def _decoded(theta: Tensor, metal: Tensor) -> tuple[dict, Tensor, Tensor, Tensor, Tensor]:
    """:func:`decode`'s dict and the steps its tangents need: the logits' sigmoids ``s (P, 5)``,
    ``u = (p, q, 1)`` and ``|u|⁻¹`` ``(P, 3)``, ``(P, 1)``, the roughness's span ``(1,)``."""
    s = torch.sigmoid(theta[:, 0:5])  # one op for the five logits (decode runs ~700 times a fit)
    # (the bounds filled on the device: no copy from the host, no sync)
    lo, hi = (torch.full((1,), v, dtype=theta.dtype, device=theta.device) for v in (R_MIN, R_MAX))
    rough = torch.lerp(lo, hi, s[:, 4:5])
    u = F.pad(theta[:, 5:7], (0, 1), value=1.0)
    p, q = theta[:, 5:6], theta[:, 6:7]
    # u·u as (p² + q²) + 1, the order of the sum over u's three channels (the same bits), at a
    # third of the time of that reduction over rows of three on the CPU
    inv = torch.rsqrt(p * p + q * q + 1.0)
    return ({"base_color": s[:, 0:3], "specular": s[:, 3:4], "roughness": rough, "metallic": metal,
             "normal": u * inv}, s, u, inv, hi - lo)


# The derivative rules of decode's steps, as autograd's forward mode applies them (derivatives.yaml,
# in its order of operations: the same bits as torch.func.jvp of decode).

def _logit_tangents(t: Tensor, s: Tensor, span: Tensor) -> tuple[Tensor, Tensor]:
    """Tangents of the sigmoids ``(…, 5)`` along logit tangents ``t (…, 5)`` and the roughness's
    ``(…, 1)`` (its lerp: the sigmoid's tangent times the span)."""
    ds = torch.ops.aten.sigmoid_backward(t, s)  # t (1 − σ) σ
    return ds, ds[..., 4:5] * span


def _normal_tangent(t: Tensor, u: Tensor, inv: Tensor) -> Tensor:
    """Tangent ``(…, 3)`` of ``n = u |u|⁻¹`` along slope tangents ``t (…, 2)``: ``du = (t, 0)``,
    ``d|u|⁻¹ = −½ d(u·u) |u|⁻³``."""
    du = F.pad(t, (0, 1), value=0.0)
    d_inv = -0.5 * (du * u + du * u).sum(-1, keepdim=True) * inv.pow(3)
    return d_inv * u + du * inv


def decode_jvp(x: Tensor, metal: Tensor, tangents: Tensor) -> tuple[dict, dict]:
    """:func:`decode` and its derivatives along ``K`` directions of the unknowns, in closed form.

    ``x (P, 7)``: theta, with ``metal (P, 1)``; or ``(P, 8)``: theta and a continuous metallic
    (``metal`` is then unused); ``tangents (K, P, x's columns)``. Returns ``(params, dparams)``:
    :func:`decode`'s dict and one of ``(K, P, C)`` tangents for each of its entries (metallic's
    only with 8 columns), in ``x``'s dtype, on its device: what ``torch.func.vmap`` of
    ``torch.func.jvp`` of :func:`decode` gives, to the last bit (each step's forward-mode rule
    in autograd's order of operations), without the transforms' work per call.
    """
    theta = x[:, :7]
    p, s, u, inv, span = _decoded(theta, x[:, 7:8] if x.shape[1] == 8 else metal)
    ds, d_rough = _logit_tangents(tangents[..., 0:5], s, span)
    dp = {"base_color": ds[..., 0:3], "specular": ds[..., 3:4], "roughness": d_rough,
          "normal": _normal_tangent(tangents[..., 5:7], u, inv)}
    if x.shape[1] == 8:
        dp["metallic"] = tangents[..., 7:8]
    return p, dp


#: The ``(parameter, channel)`` entries of :func:`decode`'s result each unknown moves (columns
#: of ``theta``, then a continuous metallic): a logit its own channel, a slope the whole normal.
_MOVES = {0: (("base_color", 0),), 1: (("base_color", 1),), 2: (("base_color", 2),), 3: (("specular", 0),),
          4: (("roughness", 0),), 5: tuple(("normal", c) for c in range(3)),
          6: tuple(("normal", c) for c in range(3)), 7: (("metallic", 0),)}


def decode_directions(x: Tensor, metal: Tensor, rows: Sequence[Sequence[int]]) -> tuple[dict, dict]:
    """:func:`decode_jvp` along sums of unit directions, without forming the ``(K, P, C)`` products.

    Direction ``k`` is the sum of the unit vectors of the unknowns (columns of ``x``) listed in
    ``rows[k]``, each at most once (e.g. :func:`decode_slots`; an empty list: a zero direction);
    ``x``, ``metal`` as for :func:`decode_jvp`. Returns the same ``(params, dparams)`` (contiguous
    tangents, zero where a direction does not move a parameter; metallic's only with 8 columns),
    bit for bit: each logit's ``(1 − σ) σ`` is computed once per pixel and copied into the
    direction that moves it, and a direction along one slope takes the normal's rule with its
    zero terms written out (:func:`_slope_tangent`).
    """
    n_x = x.shape[1]
    for k, cols in enumerate(rows):
        for j in cols:
            if j not in _MOVES or j >= n_x:
                raise ValueError(f"decode_directions: rows[{k}] lists unknown {j}; x has {n_x} columns")
            if list(cols).count(j) > 1:
                raise ValueError(f"decode_directions: rows[{k}] lists unknown {j} twice (each row is a sum "
                                 f"of distinct unit vectors)")
    p, s, u, inv, span = _decoded(x[:, :7], x[:, 7:8] if n_x == 8 else metal)
    ds, d_rough = _logit_tangents(s.new_ones(1, 5), s, span)
    channels = {"base_color": 3, "specular": 1, "roughness": 1, "normal": 3, "metallic": 1 if n_x == 8 else 0}
    dp = {name: x.new_empty(len(rows), x.shape[0], c) for name, c in channels.items() if c}
    for k, cols in enumerate(rows):
        written = {m for j in cols for m in _MOVES[j]}
        for name, t in dp.items():  # zero what the direction does not move
            if sum((name, c) in written for c in range(t.shape[2])) < t.shape[2]:
                t[k].zero_()
        for j in cols:
            if j < 3:
                dp["base_color"][k, :, j] = ds[:, j]
            elif j in (3, 4):
                dp["specular" if j == 3 else "roughness"][k] = ds[:, 3:4] if j == 3 else d_rough
            elif j == 7:
                dp["metallic"][k] = 1.0
        slopes = [j - 5 for j in cols if j in (5, 6)]
        if len(slopes) == 1:
            _slope_tangent(slopes[0], u, inv, dp["normal"][k])
        elif slopes:
            dp["normal"][k] = _normal_tangent(u.new_ones(2), u, inv)
    return p, dp


def _slope_tangent(c: int, u: Tensor, inv: Tensor, out: Tensor) -> None:
    """:func:`_normal_tangent` along slope ``c`` (0: p, 1: q) alone into ``out (P, 3)``, the same bits.

    With ``du = e_c``: ``d(u·u)`` is ``u_c + u_c`` plus zeros (``+ 0``: a ``−0`` sum becomes
    ``+0``, in any order of the sum), and ``du · |u|⁻¹`` adds ``|u|⁻¹`` to channel ``c`` and ``+0``
    to the others.
    """
    uc = u[:, c:c + 1]
    d_inv = -0.5 * (uc + uc + 0.0) * inv.pow(3)
    torch.mul(d_inv, u, out=out)
    out.add_(0.0)
    out[:, c:c + 1] = d_inv * uc + inv


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
