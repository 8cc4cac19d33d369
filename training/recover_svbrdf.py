"""``python -m training.recover_svbrdf``: SVBRDF recovery (the same as ``torchbrdf-recover``).

See :mod:`torchbrdf.recovery.svbrdf` and ``docs/recovery.md``.
"""

from torchbrdf.recovery.svbrdf import cli

if __name__ == "__main__":
    cli()
