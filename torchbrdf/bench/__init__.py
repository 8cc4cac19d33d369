"""Benchmarks: what each evaluation choice costs, measured side by side.

``python -m torchbrdf.bench`` (or ``torchbrdf-bench``) runs :mod:`torchbrdf.bench.brdf`;
``python -m torchbrdf.bench.shading`` measures the shader's memory and the environment
strategies' error against time; ``python -m torchbrdf.bench.recovery_panel`` scores the
recovery on a broad panel of materials (docs/recovery_panel.md).  Results go to ``--out``
(default ``bench_out/``).

May import anything in :mod:`torchbrdf`; nothing in the library imports it.
"""
