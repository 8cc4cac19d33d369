"""``python -m torchbrdf.bench.transforms``: gradients through ``torch.func`` against ``torch.autograd``.

The same gradient of ``principled(...).sum()`` w.r.t. a per-lane roughness, float32, both on
the fused kernels, the two ways alternating call by call (:mod:`torchbrdf.bench.timing`):
``torch.autograd.grad``, ``torch.func.grad`` (which records its backward in case a transform
around it differentiates again) and ``torch.func.vmap(torch.func.grad)`` over a batch of 4.
Prints a markdown table: median (min–max) seconds, and the ratio to ``autograd.grad`` where
the spreads are apart.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import torch

import torchbrdf
from torchbrdf.bench.timing import ratio_text, spread_text, time_alternating


def _inputs(N: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(0)
    up = torch.tensor([0.0, 0.0, 1.5])
    l, v, n = (torch.nn.functional.normalize(torch.randn(N, 3, generator=g) + up, dim=-1) for _ in range(3))
    return l, v, n, torch.rand(N, 3, generator=g), torch.rand(N, 1, generator=g)


def grad_paths(N: int, repeats: int) -> str:
    """Markdown table of the gradient's wall time by each route at ``N`` lanes."""
    l, v, n, base, rough = _inputs(N)

    def loss(r):
        return torchbrdf.principled(l, v, n, base_color=base, roughness=r).sum()

    def autograd_grad():
        r = rough.clone().requires_grad_()
        return torch.autograd.grad(loss(r), r)[0]

    batch = rough.unsqueeze(0).expand(4, N, 1).clone()
    variants = {
        "torch.autograd.grad": autograd_grad,
        "torch.func.grad": lambda: torch.func.grad(loss)(rough),
        "torch.func.vmap(torch.func.grad), 4 x": lambda: torch.func.vmap(torch.func.grad(loss))(batch),
    }
    old = torchbrdf.fast_path_enabled()
    torchbrdf.set_fast_path(True)
    try:
        times = time_alternating(variants, repeats)
    finally:
        torchbrdf.set_fast_path(old)
    ref = times["torch.autograd.grad"]
    lines = [f"N = 2^{N.bit_length() - 1} lanes, float32, {torch.get_num_threads()} threads, {repeats} alternating "
             f"rounds; load average (1 min) {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", "",
             "| route | seconds, median (min–max) | vs autograd.grad |", "|---|---|---|"]
    for name, s in times.items():
        lines.append(f"| `{name}` | {spread_text(s)} | {'—' if s is ref else ratio_text(s, ref)} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m torchbrdf.bench.transforms", description=__doc__.split("\n")[0])
    ap.add_argument("--log2n", type=int, default=20, help="log2 of the lanes (default 20)")
    ap.add_argument("--repeats", type=int, default=5, help="alternating rounds (default 5)")
    args = ap.parse_args(argv)
    print(grad_paths(1 << args.log2n, args.repeats))
    return 0


if __name__ == "__main__":
    sys.exit(main())
