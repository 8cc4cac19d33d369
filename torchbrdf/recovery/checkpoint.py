"""What a checkpoint or an output folder belongs to, and whether a checkpoint can be trusted.

A fingerprint identifies the capture (``capture.json`` and every image's size and SHA-256)
and every setting that changes the result. ``--resume`` and the batch's skipping compare
the same fingerprints. A checkpoint also carries a checksum of its state, and passes a
schema and a finiteness check before a run continues from it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchbrdf._types import PathLike
from torchbrdf.capture.format import CAPTURE_JSON, Capture
from torchbrdf.recovery.config import RecoveryConfig, Settings, settings_of

__all__ = ["RESULT_INDEPENDENT", "capture_fingerprint", "settings_fingerprint", "capture_differences",
           "settings_differences", "digest", "sha256_file", "folder_fingerprint", "state_checksum",
           "checkpoint_problems"]

#: Settings excluded from the fingerprint: they change the result at most by rounding (threads,
#: device: another reduction order) or not at all, so a checkpoint made with others resumes.
RESULT_INDEPENDENT = frozenset({"threads", "device", "checkpoint_every", "signal_at"})


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def capture_fingerprint(capture: PathLike | Capture, cap: Capture) -> dict:
    """What identifies the capture.

    For a folder: ``capture.json``'s SHA-256 and each image's size and SHA-256; for an
    in-memory :class:`Capture`, the SHA-256 of its tensors.
    """
    if isinstance(capture, Capture):
        h = hashlib.sha256()
        for t in (cap.images, cap.light_positions, cap.light_intensities, cap.camera_position):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
        return {"tensors": h.hexdigest()}
    return _files_fingerprint(Path(capture), cap.files)


def _files_fingerprint(folder: Path, files) -> dict:
    images = {name: {"size": (folder / name).stat().st_size, "sha256": sha256_file(folder / name)}
              for name in files}
    return {CAPTURE_JSON: sha256_file(folder / CAPTURE_JSON), "images": images}


def settings_fingerprint(cfg: RecoveryConfig | Settings) -> dict:
    """Every :class:`RecoveryConfig` field that changes the result, as JSON values.

    All fields but threads, device, checkpoint frequency and the test-only signal hook.
    """
    cfg = settings_of(cfg)
    out = {}
    for f in dataclasses.fields(cfg):
        if f.name not in RESULT_INDEPENDENT:
            out[f.name] = json.loads(json.dumps(getattr(cfg, f.name), default=repr))
    return out


def digest(obj: Any) -> str:  # Any: a JSON value
    """SHA-256 of a JSON value (keys sorted)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def capture_differences(old: dict, new: dict) -> list[str]:
    """What differs between two :func:`capture_fingerprint` results, one phrase per difference."""
    if "tensors" in old or "tensors" in new:
        return ["the capture's images or lights"] if old != new else []
    diffs = []
    if old.get(CAPTURE_JSON) != new.get(CAPTURE_JSON):
        diffs.append(CAPTURE_JSON)
    oi, ni = old.get("images", {}), new.get("images", {})
    changed = [n for n in ni if n in oi and oi[n] != ni[n]]
    added = [n for n in ni if n not in oi]
    removed = [n for n in oi if n not in ni]
    for what, names in (("changed", changed), ("new", added), ("missing", removed)):
        if names:
            more = f" and {len(names) - 3} more" if len(names) > 3 else ""
            diffs.append(f"{what} image(s) {', '.join(names[:3])}{more}")
    return diffs


def settings_differences(old: dict, new: dict) -> list[str]:
    """``"name old -> new"`` for each setting that differs between two settings fingerprints."""
    keys = sorted(set(old) | set(new))
    return [f"{k} {old.get(k, '(unset)')!r} -> {new.get(k, '(unset)')!r}"
            for k in keys if old.get(k) != new.get(k)]


def folder_fingerprint(folder: PathLike) -> dict | None:
    """:func:`capture_fingerprint` of a capture folder from its ``capture.json`` alone (no image decoded).

    None when ``capture.json`` or a listed image cannot be read: such a capture is never
    "already done".
    """
    folder = Path(folder)
    try:
        meta = json.loads((folder / CAPTURE_JSON).read_text(encoding="utf-8"))
        return _files_fingerprint(folder, [e["file"] for e in meta["images"]])
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return None


# --------------------------------------------------------------------------------------
# Checkpoint integrity
# --------------------------------------------------------------------------------------

#: The solver state's keys and the types their values must have.
STATE_SCHEMA: dict[str, tuple[type, ...]] = {
    "stage": (int,), "it": (int,), "global_it": (int,), "lr": (float, int), "theta": (list,), "lam": (list,),
    "metal": (Tensor, type(None)), "history": (list,), "events": (list,), "seconds": (float, int),
}
#: State entries whose tensors must be finite (the fitted parameters and their damping).
FINITE_STATE = ("theta", "lam", "metal", "light_log_scale", "light_offset")


def _feed(h, obj) -> None:
    if isinstance(obj, Tensor):
        t = obj.detach().cpu().contiguous().reshape(-1)
        h.update(f"T{t.dtype}{tuple(obj.shape)};".encode())
        h.update(t.view(torch.uint8).numpy().tobytes())
    elif isinstance(obj, dict):
        h.update(f"D{len(obj)};".encode())
        for k in sorted(obj, key=repr):
            _feed(h, k)
            _feed(h, obj[k])
    elif isinstance(obj, (list, tuple)):
        h.update(f"L{len(obj)};".encode())
        for v in obj:
            _feed(h, v)
    else:
        h.update(f"{type(obj).__name__}:{obj!r};".encode())


def state_checksum(state: dict, plan: list, torch_rng: Tensor) -> str:
    """SHA-256 over every value of a checkpoint's state, plan and RNG state (tensor bytes included).

    ``torch.load`` does not verify its archive's contents, so flipped bits in a tensor load
    silently; this checksum, stored in the checkpoint and compared on load, catches them.
    """
    h = hashlib.sha256()
    for part in (state, plan, torch_rng):
        _feed(h, part)
    return h.hexdigest()


def checkpoint_problems(blob: dict) -> list[str]:
    """Why a loaded checkpoint ``blob`` cannot be resumed: checksum, schema, finiteness (empty: fine)."""
    state, fp = blob.get("state"), blob.get("fingerprint") or {}
    if not isinstance(state, dict):
        return ["its state is not a dictionary"]
    missing = [k for k in STATE_SCHEMA if k not in state]
    if missing:
        return [f"its state lacks {', '.join(missing)}"]
    wrong = [k for k, types in STATE_SCHEMA.items()
             if not isinstance(state[k], types) or isinstance(state[k], bool)]
    if wrong:
        return [f"its state has the wrong type for {', '.join(wrong)}"]
    if "state_sha256" not in fp:
        return ["it carries no checksum (made by an older version)"]
    if fp["state_sha256"] != state_checksum(state, blob["plan"], blob["torch_rng"]):
        return ["its checksum does not match its contents (the file was altered or damaged)"]
    problems = []
    for key in FINITE_STATE:
        values = state.get(key)
        tensors = values if isinstance(values, list) else [values]
        if any(isinstance(t, Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all())
               for t in tensors):
            problems.append(f"its {key} holds non-finite values")
    if not all(isinstance(state[k], (int, float)) and math.isfinite(state[k]) for k in ("lr", "seconds")):
        problems.append("its lr or seconds is not finite")
    return problems
