"""Runnable dataset scripts of the repository (``python -m datasets.generate``).

The library code they use lives in :mod:`torchbrdf.capture`; this folder is not installed.
"""
