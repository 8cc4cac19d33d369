"""Fused kernels generated from the BRDF formulas: tracing, code generation, build and cache.

``fused`` traces the principled formula into a small expression graph, emits C for the
forward and the recompute-backward, builds it once per kernel family into a per-user cache
and wraps it as an autograd function. ``codegen_triton`` prints the same graphs as Triton
kernels for CUDA tensors; ``backend`` chooses between them (``torchbrdf.set_backend``).

May import: ``torchbrdf._math``, ``torchbrdf._checks`` and ``torchbrdf.brdf`` (the formulas it
traces).  Nothing above.
"""
