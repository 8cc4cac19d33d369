"""Which kernels evaluate the BRDF: ``torchbrdf.set_backend`` and ``TORCHBRDF_BACKEND``.

Backends (the names of set_backend and TORCHBRDF_BACKEND):

* ``"auto"`` (default): the fused C kernels on CPU tensors, the Triton kernels on CUDA tensors
  when Triton imports, the eager path otherwise;
* ``"eager"``: always the eager reference path (ATen operations; any device);
* ``"cpu"``: the fused C kernels for CPU tensors (other devices: eager);
* ``"triton"``: the Triton kernels for CUDA tensors, and for CPU tensors too when Triton runs
  in its interpreter (``TRITON_INTERPRET=1``, how the tests exercise the kernels without a
  GPU); eager where Triton cannot run.

:func:`set_backend` wins over the environment variable; ``set_backend(None)`` returns to it.

Relation to :func:`torchbrdf.set_fast_path`: that switch says *whether* a fused backend is used
(``False``: always eager, whatever the backend; ``True``: at every batch size; ``None``: from
``FAST_PATH_MIN_LANES`` lanes in ``auto`` mode), this one says *which*. A backend named
explicitly (``"cpu"``, ``"triton"``) applies at every batch size. ``TORCHBRDF_EAGER=1`` keeps
its old meaning, the same as ``"eager"``.

All three kernel families (C and Triton) are printed from the same traced graphs of
:mod:`torchbrdf.brdf.formula`.
"""

from __future__ import annotations

import os

import torch

__all__ = ["BACKENDS", "set_backend", "get_backend", "resolve"]

BACKENDS = ("auto", "eager", "cpu", "triton")

_setting: dict = {"backend": None}


def _check(name, what: str) -> str:
    if name not in BACKENDS:
        raise ValueError(f"{what}: expected one of {BACKENDS}, got {name!r}")
    return name


def set_backend(name: str | None) -> None:
    """Choose the kernels that evaluate :func:`torchbrdf.principled`.

    Args:
        name: ``"auto"``, ``"eager"``, ``"cpu"`` or ``"triton"`` (see the module docstring), or
            ``None`` to follow ``$TORCHBRDF_BACKEND`` again (default ``"auto"``).
    """
    _setting["backend"] = None if name is None else _check(name, "backend")


def explicit_backend() -> str | None:
    """The backend :func:`set_backend` chose, or ``None`` when ``$TORCHBRDF_BACKEND`` is followed
    (what to pass back to :func:`set_backend` to restore the setting)."""
    return _setting["backend"]


def get_backend() -> str:
    """The backend in force: :func:`set_backend`'s, else ``$TORCHBRDF_BACKEND``, else ``"auto"``."""
    if _setting["backend"] is not None:
        return _setting["backend"]
    env = os.environ.get("TORCHBRDF_BACKEND", "").strip().lower()
    if not env:
        return "eager" if os.environ.get("TORCHBRDF_EAGER", "") not in ("", "0") else "auto"
    return _check(env, "TORCHBRDF_BACKEND")


def _c_available() -> bool:
    from torchbrdf.kernels import fused

    return fused.available()


def _triton_available() -> bool:
    from torchbrdf.kernels import codegen_triton

    return codegen_triton.available()


def _interpret() -> bool:
    from torchbrdf.kernels import codegen_triton

    return codegen_triton.interpret_mode()


def resolve(device: torch.device) -> str:
    """The kernels used for tensors on ``device``: ``"eager"``, ``"c"`` or ``"triton"``."""
    b = get_backend()
    if b == "eager":
        return "eager"
    dev = torch.device(device).type
    if b == "cpu":
        return "c" if dev == "cpu" and _c_available() else "eager"
    if b == "triton":
        ok = dev == "cuda" or (dev == "cpu" and _interpret())
        return "triton" if ok and _triton_available() else "eager"
    # auto
    if dev == "cpu":
        return "c" if _c_available() else "eager"
    if dev == "cuda" and _triton_available() and not _interpret():
        return "triton"
    return "eager"
