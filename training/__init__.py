"""Runnable recovery, evaluation and fitting scripts of the repository.

Thin command-line wrappers around :mod:`torchbrdf.recovery`; this folder is not installed
(pip users have the ``torchbrdf-recover`` and ``torchbrdf-fit-merl`` commands).
"""
