"""Fused kernels generated from the BRDF formulas: tracing, code generation, build and cache.

``fused`` traces a formula of ``formula.FAMILIES`` (the principled BRDF, the SVBRDF-capture GGX, the
recovery's residual) into a small expression graph, emits C for the
forward and the recompute-backward and builds it once per kernel family into a per-user cache;
``ops`` is the entry point of the operators (``layout``: one call's memory layout;
``c_runner``/``triton_runner``: the kernels' calls; ``registration``: the custom operators and
their vmap rules; ``autograd``: their derivatives). ``codegen_triton`` prints the same graphs as Triton
kernels for CUDA tensors; ``backend`` chooses between them (``torchbrdf.set_backend``).
``schur_ops`` and ``lane_ops`` are the hand-written C kernels: linear algebra, not formulas (the
joint light step's per-pixel elimination; the LM step's per-pixel ``LDLᵀ``, triangular solves
and conjugate-gradient operator, bit-identical to their PyTorch forms).

May import: ``torchbrdf._math``, ``torchbrdf._checks``, ``torchbrdf.io`` (the per-user cache
folder) and ``torchbrdf.brdf.formula`` (the formulas it traces and their constants), never the
BRDF models that dispatch to the kernels.  Nothing above.
"""
