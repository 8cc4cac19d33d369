"""Images in and out: OpenEXR for linear HDR data, PNG for people to look at.

Layout conventions:

* Images are channel-first tensors ``(C, H, W)``; the writers also take ``(1, C, H, W)``.
* EXR channel names follow the usual OpenEXR convention: three channels are ``R, G, B``,
  four are ``R, G, B, A``, one is ``Y``. Other layouts need explicit names.
* Every writer is atomic: it writes a temporary file in the destination folder and then
  ``os.replace`` s it over the destination, so a reader (or a crash) never sees a
  half-written file. :func:`atomic_path` exposes the same mechanism for other writers
  (checkpoints, JSON reports).

PNG output goes through :func:`to_display` (exposure, optional tone map, sRGB encoding via
:func:`kornia.color.linear_rgb_to_rgb`) and is written by scikit-image.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Literal, overload

import numpy as np
import torch
from torch import Tensor

from torchbrdf._types import Device, PathLike

__all__ = [
    "TONEMAPS",
    "CACHE_ENV",
    "cache_root",
    "atomic_path",
    "read_exr",
    "to_display",
    "write_exr",
    "write_png",
]

#: Tone maps accepted by :func:`to_display` / :func:`write_png` (``None`` clips to [0, 1]).
TONEMAPS = (None, "clip", "reinhard", "aces")
#: The one environment variable naming torchbrdf's per-user cache (kernels, demo capture).
CACHE_ENV = "TORCHBRDF_CACHE_DIR"


def cache_root() -> str:
    """The per-user cache folder of torchbrdf (kernels, demo capture); not created here.

    ``$TORCHBRDF_CACHE_DIR``, else ``$XDG_CACHE_HOME/torchbrdf``, else ``~/.cache/torchbrdf``.
    A relative or empty ``$XDG_CACHE_HOME`` is ignored (the XDG spec calls it invalid), and
    so is a relative or empty ``$HOME`` (it would make the cache relative to the current
    folder): the home folder then comes from the user database.
    """
    d = os.environ.get(CACHE_ENV)
    if d:
        return os.path.abspath(os.path.expanduser(d))
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        home = os.environ.get("HOME", "")
        if not os.path.isabs(home):
            import pwd

            home = pwd.getpwuid(os.getuid()).pw_dir
        base = os.path.join(home, ".cache")
    return os.path.join(os.path.abspath(base), "torchbrdf")

_HALF_MAX = 65504.0  # largest finite float16: half EXRs saturate here instead of storing inf

# Default channel names per channel count, and the order read_exr reports known channels in.
_DEFAULT_NAMES = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
_CANONICAL_ORDER = ("R", "G", "B", "A", "Y")


# --------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------


def _default_file_mode() -> int:
    # mkstemp creates files 0600; give the final file the mode open() would have given it.
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _default_file_mode()


def fsync_dir(path: PathLike) -> None:
    """Flush a folder's entries to disk (after an atomic rename), best effort: a file system
    that cannot open or sync folders is left as it is."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """Context manager yielding a temporary path that replaces ``path`` on success.

    The temporary file lives in the destination folder (so ``os.replace`` is atomic on
    POSIX and Windows) and keeps the destination's suffix (so writers that pick a format by
    extension still work). If the block raises, the temporary file is removed and
    ``path`` is left untouched.

    Args:
        path: destination file. Its folder must exist.

    Yields:
        A ``Path`` to write to; it exists (empty) when the block starts.

    Raises:
        FileNotFoundError: if the destination folder does not exist.
        IsADirectoryError: if ``path`` is a folder.

    Example:
        >>> import json, tempfile, os
        >>> out = os.path.join(tempfile.mkdtemp(), "report.json")
        >>> with atomic_path(out) as tmp:
        ...     _ = tmp.write_text(json.dumps({"ok": True}))
        >>> open(out).read()
        '{"ok": true}'
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"cannot write '{path}': folder '{folder}' does not exist")
    if path.is_dir():
        raise IsADirectoryError(f"cannot write '{path}': it is a folder; name a file inside it")
    fd, tmp_name = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # Flush to disk before the rename so a crash cannot leave an empty destination.
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def file_in_the_way(folder: PathLike) -> Path | None:
    """The file that stops ``folder`` from being created or used as a folder, if any.

    That is ``folder`` itself, or the nearest of its parents that exists, when it is not a
    folder (mkdir's own error names neither); None when nothing is in the way.
    """
    folder = Path(os.path.abspath(folder))
    existing = next((p for p in (folder, *folder.parents) if p.exists()), None)
    return existing if existing is not None and not existing.is_dir() else None


def check_readable_file(path: Path, what: str) -> None:
    """Raise a message that says what is wrong with an input file path.

    Args:
        path: the file to be read.
        what: what it should be, for the message (e.g. ``"EXR file"``).

    Raises:
        IsADirectoryError: ``path`` is a folder.
        FileNotFoundError: nothing exists at ``path`` (a broken symlink counts as missing).
        ValueError: ``path`` exists but is not a regular file (a device, a FIFO, ...).
    """
    if path.is_dir():
        raise IsADirectoryError(f"{what} '{path}' is a directory, not a file")
    if not path.exists():
        raise FileNotFoundError(f"{what} '{path}' not found (no such file)")
    if not path.is_file():
        raise ValueError(f"{what} '{path}' is not a regular file")


# --------------------------------------------------------------------------------------
# OpenEXR
# --------------------------------------------------------------------------------------


_LIBRARY_OUTPUT_LOCK = threading.Lock()


@contextlib.contextmanager
def _library_output(into: list[str]) -> Iterator[None]:
    """Collect what native code prints to file descriptors 1 and 2 during the body into ``into``.

    The OpenEXR bindings print their own lines about a damaged file before raising; the
    caller's one-line error carries that text instead. The descriptors are process-wide, so
    one body at a time holds them.
    """
    with _LIBRARY_OUTPUT_LOCK, tempfile.TemporaryFile() as sink:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        saved = [os.dup(1), os.dup(2)]
        python_side = io.StringIO()  # the bindings' own Python-level prints
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            with contextlib.redirect_stdout(python_side), contextlib.redirect_stderr(python_side):
                yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            into.append(sink.read().decode("utf-8", errors="replace") + python_side.getvalue())


def _import_openexr():
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover - OpenEXR is a declared dependency
        raise ImportError("torchbrdf.io needs the OpenEXR Python bindings (pip install OpenEXR)") from e
    return OpenEXR


def _ordered_names(names: Sequence[str]) -> list[str]:
    """R, G, B, A, Y first (in that order), then every other channel alphabetically."""
    known = [c for c in _CANONICAL_ORDER if c in names]
    return known + sorted(c for c in names if c not in _CANONICAL_ORDER)


@overload
def read_exr(
    path: PathLike,
    channels: Sequence[str] | None = None,
    *,
    return_names: Literal[False] = False,
    dtype: torch.dtype = torch.float32,
    device: Device = None,
) -> Tensor: ...
@overload
def read_exr(
    path: PathLike,
    channels: Sequence[str] | None = None,
    *,
    return_names: Literal[True],
    dtype: torch.dtype = torch.float32,
    device: Device = None,
) -> tuple[Tensor, list[str]]: ...
def read_exr(
    path: PathLike,
    channels: Sequence[str] | None = None,
    *,
    return_names: bool = False,
    dtype: torch.dtype = torch.float32,
    device: Device = None,
) -> Tensor | tuple[Tensor, list[str]]:
    """Read a single-part OpenEXR image as a channel-first tensor.

    Half, float and uint channels are all converted to ``dtype``. Without ``channels``, the
    channels come out as R, G, B, A, Y (those present, in that order), then any others in
    alphabetical order — so an RGB file gives ``(3, H, W)`` in R, G, B order.

    Args:
        path: the ``.exr`` file. Only the first part of a multi-part file is read.
        channels: names of the channels to read, in the order wanted (e.g. ``("R", "G", "B")``
            to drop alpha). ``None`` reads all of them.
        return_names: also return the list of channel names, one per output channel.
        dtype: floating dtype of the result.
        device: device of the result (default: CPU).

    Returns:
        ``(C, H, W)`` tensor, or ``((C, H, W) tensor, names)`` when ``return_names`` is set.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        IsADirectoryError: if ``path`` is a folder.
        ValueError: if the file is not a readable OpenEXR image, uses channel subsampling,
            or lacks a requested channel.

    Example:
        >>> import os, tempfile
        >>> p = os.path.join(tempfile.mkdtemp(), "a.exr")
        >>> write_exr(p, torch.ones(3, 2, 4))
        >>> img, names = read_exr(p, return_names=True)
        >>> tuple(img.shape), names
        ((3, 2, 4), ['R', 'G', 'B'])
    """
    path = Path(path)
    check_readable_file(path, "EXR file")
    exr = _import_openexr()
    # The bindings raise a bare RuntimeError ("Unable to open ... for read") on any failure,
    # so check the magic number first to tell the user which problem they have.
    if not exr.isOpenExrFile(str(path)):
        raise ValueError(f"'{path}' is not an OpenEXR file (bad magic number or truncated header)")
    printed: list[str] = []
    try:
        with _library_output(printed), exr.File(str(path), separate_channels=True) as f:
            # A truncated or corrupt file loads with no parts (the bindings only print a warning).
            if not f.parts:
                raise ValueError("no readable part (truncated or corrupt pixel data)")
            stored = {name: ch.pixels for name, ch in f.channels().items()}
            sampling = {name: (ch.xSampling, ch.ySampling) for name, ch in f.channels().items()}
    except (RuntimeError, ValueError, IndexError) as e:
        said = " ".join(" ".join(printed).split())
        detail = f" (OpenEXR: {said[:200]})" if said else ""
        raise ValueError(f"could not read OpenEXR file '{path}': {e}{detail}") from e
    if printed and printed[0].strip():  # a file that read, with the library's remarks: pass them on
        sys.stderr.write(printed[0])
    if not stored:
        raise ValueError(f"OpenEXR file '{path}' has no channels")
    subsampled = [n for n, s in sampling.items() if tuple(s) != (1, 1)]
    if subsampled:
        raise ValueError(f"OpenEXR file '{path}': subsampled channels are not supported: {subsampled}")

    if channels is None:
        names = _ordered_names(list(stored))
    else:
        names = list(channels)
        missing = [c for c in names if c not in stored]
        if missing:
            raise ValueError(f"OpenEXR file '{path}' has no channel(s) {missing}; it has {sorted(stored)}")
    planes = [np.asarray(stored[c], dtype=np.float32) for c in names]
    image = torch.from_numpy(np.stack(planes, axis=0)).to(device=device, dtype=dtype)
    return (image, names) if return_names else image


def _as_chw(image, path: Path, what: str) -> Tensor:
    """Validate and return a detached CPU ``(C, H, W)`` tensor from ``(C, H, W)`` or ``(1, C, H, W)``."""
    image = torch.as_tensor(image).detach()
    shape = tuple(image.shape)
    if image.dim() == 4:
        if image.shape[0] != 1:
            raise ValueError(f"cannot write {what} '{path}': a (B, C, H, W) image needs B = 1, got {shape}")
        image = image[0]
    if image.dim() != 3:
        raise ValueError(f"cannot write {what} '{path}': expected (C, H, W) or (1, C, H, W), got {shape}")
    if image.shape[1] == 0 or image.shape[2] == 0:
        raise ValueError(f"cannot write {what} '{path}': empty image of shape {shape}")
    return image.cpu()


# Compression names accepted by write_exr -> attribute of the OpenEXR module.
_COMPRESSION_ATTRS = {
    "none": "NO_COMPRESSION",
    "rle": "RLE_COMPRESSION",
    "zips": "ZIPS_COMPRESSION",
    "zip": "ZIP_COMPRESSION",
    "piz": "PIZ_COMPRESSION",
    "pxr24": "PXR24_COMPRESSION",
}
_COMPRESSIONS = tuple(_COMPRESSION_ATTRS)


def write_exr(
    path: PathLike,
    image: Tensor,
    channels: Sequence[str] | None = None,
    half: bool = False,
    *,
    compression: str = "zip",
) -> None:
    """Write a linear image to a single-part scanline OpenEXR file, atomically.

    Args:
        path: destination ``.exr`` file; its folder must exist.
        image: ``(C, H, W)`` or ``(1, C, H, W)`` tensor (any dtype, any device; detached).
        channels: one name per channel. Default: ``Y`` for one channel, ``R, G, B`` for three,
            ``R, G, B, A`` for four; other channel counts need explicit names.
        half: store 16-bit half floats instead of 32-bit floats. Values beyond the half range
            are saturated to +-65504 rather than stored as infinity.
        compression: one of ``none``, ``rle``, ``zips``, ``zip`` (default, lossless), ``piz``,
            ``pxr24`` (pxr24 is lossy for float32).

    Raises:
        ValueError: on a bad shape, channel list or compression name.
        FileNotFoundError: if the destination folder does not exist.

    Example:
        >>> import os, tempfile
        >>> p = os.path.join(tempfile.mkdtemp(), "rough.exr")
        >>> write_exr(p, torch.full((1, 8, 8), 0.5))
        >>> read_exr(p, return_names=True)[1]
        ['Y']
    """
    path = Path(path)
    chw = _as_chw(image, path, "EXR")
    c = chw.shape[0]
    if channels is None:
        if c not in _DEFAULT_NAMES:
            raise ValueError(
                f"cannot write EXR '{path}': no default channel names for {c} channels; pass channels=[...]"
            )
        names = list(_DEFAULT_NAMES[c])
    else:
        names = [channels] if isinstance(channels, str) else list(channels)
        if len(names) != c:
            raise ValueError(f"cannot write EXR '{path}': {len(names)} names {names} for {c} channel(s)")
        if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
            raise ValueError(
                f"cannot write EXR '{path}': channel names must be unique non-empty strings, got {names}"
            )
    if compression not in _COMPRESSIONS:
        raise ValueError(
            f"cannot write EXR '{path}': unknown compression {compression!r}; use one of {_COMPRESSIONS}"
        )

    exr = _import_openexr()
    data = chw.to(torch.float32)
    if half:
        data = data.clamp(-_HALF_MAX, _HALF_MAX).to(torch.float16)  # NaN passes through clamp
    arrays = data.numpy()
    pixels = {n: np.ascontiguousarray(arrays[i]) for i, n in enumerate(names)}
    header = {
        "compression": getattr(exr, _COMPRESSION_ATTRS[compression]),
        "type": exr.scanlineimage,
    }
    with atomic_path(path) as tmp:
        with exr.File(header, pixels) as f:
            f.write(str(tmp))


# --------------------------------------------------------------------------------------
# Display: exposure, tone map, sRGB, PNG
# --------------------------------------------------------------------------------------


def _tonemap(x: Tensor, method: str | None) -> Tensor:
    if method is None or method == "clip":
        return x
    if method == "reinhard":
        # Reinhard et al. 2002, the global operator x / (1 + x) applied per channel.
        return x / (1.0 + x)
    if method == "aces":
        # Narkowicz 2015 rational fit of the ACES filmic curve, with the 0.6 input scale the fit
        # was made for; maps [0, inf) into [0, ~1).
        x = 0.6 * x
        return (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
    raise ValueError(f"unknown tonemap {method!r}; use one of {TONEMAPS}")


def to_display(image: Tensor, exposure: float = 0.0, tonemap: str | None = None, srgb: bool = True) -> Tensor:
    """Map linear radiance to display values in [0, 1]: exposure, tone map, clip, sRGB.

    Steps: multiply by ``2 ** exposure``; replace NaN by 0 and clamp negatives to 0 (sensor
    noise); apply the tone map; clip to [0, 1]; encode with the sRGB transfer curve
    (:func:`kornia.color.linear_rgb_to_rgb`). One-channel images are encoded like grey RGB.
    A fourth (alpha) channel is clipped but neither exposed, tone-mapped nor encoded.

    Args:
        image: linear image ``(*, C, H, W)`` with C in {1, 3, 4}.
        exposure: exposure in stops (EV); each +1 doubles the brightness.
        tonemap: ``None``/``"clip"`` (clip only), ``"reinhard"`` (x / (1 + x)) or ``"aces"``
            (Narkowicz's filmic fit).
        srgb: apply the sRGB transfer curve; set False for data maps (roughness, normals
            remapped to [0, 1]) that must be shown linearly.

    Returns:
        ``(*, C, H, W)`` tensor in [0, 1], same dtype as ``image`` (computed in float32 for
        half inputs). Differentiable.

    Example:
        >>> to_display(torch.tensor([0.0, 0.5, 4.0]).view(3, 1, 1)).flatten()
        tensor([0.0000, 0.7354, 1.0000])
    """
    if image.dim() < 3 or image.shape[-3] not in (1, 3, 4):
        raise ValueError(f"to_display expects a (*, C, H, W) image, C in 1, 3, 4; got {tuple(image.shape)}")
    if tonemap not in TONEMAPS:
        raise ValueError(f"unknown tonemap {tonemap!r}; use one of {TONEMAPS}")
    from kornia.color import linear_rgb_to_rgb

    out_dtype = image.dtype if image.is_floating_point() else torch.float32
    work = torch.float32 if out_dtype in (torch.float16, torch.bfloat16) else out_dtype
    x = image.to(work)
    alpha = x[..., 3:4, :, :].clamp(0.0, 1.0) if x.shape[-3] == 4 else None
    colour = x[..., :3, :, :] if alpha is not None else x
    colour = torch.nan_to_num(colour * (2.0**exposure), nan=0.0).clamp(min=0.0)
    colour = _tonemap(colour, tonemap).clamp(0.0, 1.0)  # aces can exceed 1 by a hair at large x
    if srgb:
        if colour.shape[-3] == 1:
            grey = colour.expand(*colour.shape[:-3], 3, *colour.shape[-2:])
            colour = linear_rgb_to_rgb(grey)[..., :1, :, :]
        else:
            colour = linear_rgb_to_rgb(colour)
        colour = colour.clamp(0.0, 1.0)
    out = colour if alpha is None else torch.cat((colour, alpha), dim=-3)
    return out.to(out_dtype)


def write_png(
    path: PathLike,
    image: Tensor,
    exposure: float = 0.0,
    tonemap: str | None = None,
    srgb: bool = True,
) -> None:
    """Write a linear image as an 8-bit PNG (atomically) after :func:`to_display`.

    Args:
        path: destination ``.png`` file; its folder must exist.
        image: linear ``(C, H, W)`` or ``(1, C, H, W)`` tensor, C in {1 (grey), 3 (RGB), 4 (RGBA)}.
        exposure: exposure in stops applied before tone mapping.
        tonemap: ``None``/``"clip"``, ``"reinhard"`` or ``"aces"``; see :func:`to_display`.
        srgb: encode with the sRGB curve (True for radiance and colours; False for data maps).

    Raises:
        ValueError: on a bad shape or tone map name.
        FileNotFoundError: if the destination folder does not exist.

    Example:
        >>> import os, tempfile
        >>> p = os.path.join(tempfile.mkdtemp(), "preview.png")
        >>> write_png(p, torch.rand(3, 16, 16) * 4.0, exposure=-1.0, tonemap="aces")
    """
    path = Path(path)
    chw = _as_chw(image, path, "PNG")
    if chw.shape[0] not in (1, 3, 4):
        raise ValueError(f"cannot write PNG '{path}': expected a (C, H, W) image with C = 1, 3 or 4, "
                         f"got shape {tuple(chw.shape)}")
    display = to_display(chw.to(torch.float32), exposure=exposure, tonemap=tonemap, srgb=srgb)
    pixels = (display * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()
    if pixels.shape[-1] == 1:
        pixels = pixels[..., 0]  # greyscale PNG
    from PIL import Image  # Pillow, the PNG codec under matplotlib and scikit-image's imsave

    with atomic_path(path) as tmp:
        Image.fromarray(pixels).save(tmp, format="PNG")
