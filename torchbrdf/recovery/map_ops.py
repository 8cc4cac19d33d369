"""Image operations on flat ``(P, C)`` maps of a square ``size × size`` image (row-major).

Neighbour means and counts, a banded-matrix Gaussian blur, dilation, upsampling and a
deterministic k-means: the spatial plumbing the recovery's stages share.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def neighbour_mean(x: Tensor, size: int) -> Tensor:
    """Mean ``(P, C)`` of each pixel's 4-neighbours that exist (2 in a corner, 3 on an edge)."""
    img = x.T.reshape(1, -1, size, size)
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=x.dtype, device=x.device)
    s = F.conv2d(img, k.view(1, 1, 3, 3).expand(img.shape[1], 1, 3, 3), padding=1, groups=img.shape[1])
    n = F.conv2d(torch.ones_like(img[:, :1]), k.view(1, 1, 3, 3), padding=1)
    return (s / n)[0].reshape(x.shape[1], -1).T


def blur(x: Tensor, size: int, sigma: float) -> Tensor:
    """Gaussian blur of a ``(P, C)`` map (zero padding: callers divide by a blurred weight).

    The normalised kernel is truncated at ``3 sigma`` (and at the map's size). Each separable
    pass is one product with the ``(size, size)`` banded matrix of the kernel (zero padding is
    its missing rows): the non-local windows are a quarter of the map wide, where a grouped
    convolution is 20x (float32) to 100x (float64) slower than the matrix product.
    """
    r = int(min(3 * sigma, size - 1))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype, device=x.device) / sigma) ** 2)
    i = torch.arange(size, device=x.device)
    off = i[None, :] - i[:, None]  # (size, size), symmetric band
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    band = torch.where(off.abs() <= r, (k / k.sum())[(off + r).clamp(0, 2 * r)], zero)
    c = x.shape[1]
    img = band @ (x.T.reshape(c, size, size) @ band)  # along x, then along y (band is symmetric)
    return img.reshape(c, -1).T


def kmeans(x: Tensor, k: int, iters: int = 8, return_centres: bool = False) -> Tensor:
    """Deterministic k-means labels of ``x (N, 3)`` (farthest-point start)."""
    k = min(k, x.shape[0])
    cent = [x.mean(0)]
    d = ((x - cent[0]) ** 2).sum(-1)
    for _ in range(k - 1):
        cent.append(x[int(torch.argmax(d))])
        d = torch.minimum(d, ((x - cent[-1]) ** 2).sum(-1))
    c = torch.stack(cent)
    for _ in range(iters):
        lab = torch.cdist(x, c).argmin(-1)
        cnt = torch.zeros(k, dtype=x.dtype, device=x.device).index_add_(0, lab, torch.ones_like(x[:, 0]))
        s = torch.zeros_like(c).index_add_(0, lab, x)
        c = torch.where(cnt[:, None] > 0, s / cnt.clamp(min=1)[:, None], c)
    return c if return_centres else torch.cdist(x, c).argmin(-1)


def dilate(mask: Tensor, size: int) -> Tensor:
    """``mask (P,)`` bool grown by one pixel in every direction (3×3)."""
    m = mask.reshape(1, 1, size, size).to(torch.float32)
    return (F.max_pool2d(m, 3, stride=1, padding=1) > 0).reshape(-1)


def upsample(x: Tensor, s0: int, s1: int, mode: str = "bilinear") -> Tensor:
    """A ``(s0², C)`` map resampled to ``(s1², C)`` (``F.interpolate`` with ``mode``; ``x``'s dtype, device)."""
    img = x.T.reshape(1, -1, s0, s0)
    kw = {"align_corners": False} if mode == "bilinear" else {}
    up = F.interpolate(img, size=(s1, s1), mode=mode, **kw)
    return up[0].reshape(x.shape[1], -1).T.contiguous()


def neighbour_count(label: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Number of metal pixels among each pixel's 8 neighbours, and the number of neighbours it has.

    ``label (P, 1)`` in {0, 1} → two ``(P, 1)`` maps. Pixels on the image edge have 5
    neighbours, corners 3: the outside is *absent*, not a copy of the edge (replicate padding
    made an edge pixel its own neighbour, so a wrong pixel on the edge outvoted its real
    neighbours and an edge row of one class could never be flipped by the rows inside).
    """
    img = label.T.reshape(1, 1, size, size)
    ones = torch.ones_like(img)
    s = F.avg_pool2d(F.pad(img, (1, 1, 1, 1)), 3, 1) * 9 - img
    n = F.avg_pool2d(F.pad(ones, (1, 1, 1, 1)), 3, 1) * 9 - ones
    return s.reshape(-1, 1), n.reshape(-1, 1)
