"""Multi-light captures on disk (docs/capture_format.md): ``capture.json`` plus one RGB EXR per light.

A capture photographs the flat sample ``[-1, 1] x [-1, 1]`` at ``z = 0`` (+z up) under one
point light per image. :func:`load_capture` reads and validates a capture folder,
:func:`write_capture` writes one, and :func:`pixel_points` gives the world point each pixel
sees. Every error names the file (and the JSON entry) that is wrong.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np
import torch
from torch import Tensor

from torchbrdf._checks import excerpt
from torchbrdf.io import atomic_path, file_in_the_way, read_exr, write_exr

__all__ = ["CAPTURE_JSON", "Capture", "check_capture", "check_capture_destination", "default_file_names",
           "image_path", "load_capture", "pixel_points", "write_capture", "MAX_RADIANCE", "MAX_COORDINATE"]

#: Name of the description file inside a capture folder.
CAPTURE_JSON = "capture.json"

_LIGHT_TYPES = ("point",)

#: Largest light intensity and pixel value accepted. The fit squares values up to the BRDF's
#: peak (about 1000) times these, and float32 overflows at 3.4e38.
MAX_RADIANCE = 1e15
#: Largest light or camera coordinate accepted (the sample is 2 units wide); squared
#: distances stay far from float32's overflow.
MAX_COORDINATE = 1e6
#: Unknowns per pixel that the lights must determine: the normal (2), roughness, specular
#: and the albedo's level (its colour comes from the ratios of the channels).
UNKNOWNS_PER_PIXEL = 5
#: Light layouts whose directions' smallest singular value is below this fraction of the
#: largest leave the normals undetermined (all lights on one line, or in one plane, through
#: the sample).
DEGENERATE_LAYOUT = 0.05


@dataclass(frozen=True)
class Capture:
    """A loaded multi-light capture.

    Attributes:
        images: linear HDR radiance ``(L, 3, H, W)``, one image per light.
        light_positions: point-light positions ``(L, 3)`` in world space.
        light_intensities: RGB radiant intensities ``(L, 3)``, non-negative.
        camera_position: ``(3,)`` world position used for the per-pixel view vectors.
        width: image width W in pixels.
        height: image height H in pixels.
        files: image file names as listed in ``capture.json`` (relative to the folder).
    """

    images: Tensor
    light_positions: Tensor
    light_intensities: Tensor
    camera_position: Tensor
    width: int
    height: int
    files: tuple[str, ...]

    def __len__(self) -> int:
        """Number of lights (= images)."""
        return self.images.shape[0]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Capture:
        """Copy with every tensor moved/cast (``None`` keeps the current device/dtype)."""

        def move(t: Tensor) -> Tensor:
            return t.to(device=device if device is not None else t.device, dtype=dtype or t.dtype)

        return Capture(
            images=move(self.images),
            light_positions=move(self.light_positions),
            light_intensities=move(self.light_intensities),
            camera_position=move(self.camera_position),
            width=self.width,
            height=self.height,
            files=self.files,
        )

    def points(self) -> Tensor:
        """World point of every pixel ``(H, W, 3)`` (see :func:`pixel_points`)."""
        return pixel_points(self.width, self.height, device=self.images.device, dtype=self.images.dtype)


def pixel_points(
    width: int,
    height: int,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """World point seen by each pixel of a capture (docs/capture_format.md).

    Pixel (row i, column j) sees ``p = (-1 + (j + 0.5) 2 / W, 1 - (i + 0.5) 2 / H, 0)``:
    row 0 is the +y edge, column 0 the -x edge.

    Args:
        width: W, pixels per row.
        height: H, number of rows.
        device: device of the result.
        dtype: floating dtype of the result.

    Returns:
        ``(H, W, 3)`` points (channel-last vectors, like every direction in torchbrdf).

    Example:
        >>> pixel_points(2, 2)[0, 0]
        tensor([-0.5000,  0.5000,  0.0000])
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"pixel_points: width and height must be positive, got {width} x {height}")
    j = torch.arange(width, device=device, dtype=dtype)
    i = torch.arange(height, device=device, dtype=dtype)
    px = -1.0 + (j + 0.5) * (2.0 / width)
    py = 1.0 - (i + 0.5) * (2.0 / height)
    gy, gx = torch.meshgrid(py, px, indexing="ij")
    return torch.stack((gx, gy, torch.zeros_like(gx)), dim=-1)


# --------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------


def _require(obj: Mapping, key: str, where: str, json_path: Path):
    if key not in obj:
        raise ValueError(f"{json_path}: {where} is missing the key '{key}'")
    return obj[key]


def _positive_int(value, where: str, json_path: Path) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{json_path}: {where} must be a positive integer, got {value!r}")
    return value


def _vec3(value, where: str, json_path: Path, nonnegative: bool = False,
          limit: float = MAX_COORDINATE) -> list[float]:
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == 3
        and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)
    )
    if not ok:
        raise ValueError(f"{json_path}: {where} must be a list of 3 numbers, got {value!r}")
    if not all(math.isfinite(c) for c in value):
        raise ValueError(f"{json_path}: {where} must be finite, got {value!r}")
    if nonnegative and any(c < 0 for c in value):
        raise ValueError(f"{json_path}: {where} must be non-negative, got {value!r}")
    if any(abs(c) > limit for c in value):
        raise ValueError(f"{json_path}: {where} must lie within ±{limit:g} (the fit runs in float32), "
                         f"got {value!r}")
    return [float(c) for c in value]


def image_path(folder: str | os.PathLike, name: object, where: str) -> Path:
    """The path of image ``name`` inside the capture ``folder``, refusing names that leave it.

    Image names are relative paths inside the folder: an absolute path (POSIX or Windows,
    drive letters included), a ``..`` component, or a name that resolves outside the folder
    through a symlink is refused, so a capture cannot make the loader read, or the writer
    write, files elsewhere.

    Args:
        folder: the capture folder.
        name: the image name as listed in ``capture.json`` (or given to :func:`write_capture`).
        where: what the name is, for the message (e.g. ``"capture.json: images[2].file"``).

    Returns:
        ``folder / name``.

    Raises:
        ValueError: naming ``where`` and the offending name.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"{where} must be a non-empty string, got {name!r}")
    if "\0" in name:
        raise ValueError(f"{where}: image name {name!r} contains a NUL character")
    if PurePosixPath(name).is_absolute() or PureWindowsPath(name).drive or PureWindowsPath(name).root:
        raise ValueError(
            f"{where}: image name {name!r} is an absolute path; image names must be relative "
            "paths inside the capture folder"
        )
    if ".." in name.replace("\\", "/").split("/"):
        raise ValueError(
            f"{where}: image name {name!r} contains '..'; image names must stay inside the capture folder"
        )
    folder = Path(folder)
    path = folder / name
    root = folder.resolve()
    resolved = path.resolve()
    if resolved != root and root not in resolved.parents:
        raise ValueError(
            f"{where}: image name {name!r} resolves to '{resolved}', outside the capture folder "
            f"'{root}' (through a symlink); image names must stay inside the capture folder"
        )
    return path


def _check_lights(positions, intensities, where) -> None:
    """Refuse lights that cannot light the sample: zero intensity, or none above the plane.

    ``positions`` and ``intensities`` are sequences of finite xyz / RGB triples; ``where(k)``
    names light ``k``'s intensity in messages, ``where(None)`` the capture as a whole.
    """
    for k, inten in enumerate(intensities):
        if not any(c > 0 for c in inten):
            raise ValueError(
                f"{where(k)} is zero ({list(map(float, inten))}): a light that emits "
                "nothing lights nothing; give its intensity or drop the image"
            )
    if not any(p[2] > 0 for p in positions):
        raise ValueError(
            f"{where(None)}: no light is above the sample plane (every light position has z <= 0); "
            "the sample at z = 0 faces +z, so no image can show it lit"
        )
    for k, p in enumerate(positions):
        if p[2] <= 0:
            raise ValueError(
                f"{where(None)}: light {k} is at z = {p[2]:g}, on or below the sample plane; the sample at "
                "z = 0 faces +z, so its image cannot show it lit; drop the image or fix the position"
            )


def _check_pixels(image: Tensor, file: Path, width: int, height: int, json_path: Path) -> None:
    c, h, w = image.shape
    if (w, h) != (width, height):
        raise ValueError(
            f"{file}: image is {w}x{h} (width x height) but {json_path.name} says {width}x{height}"
        )
    bad = ~torch.isfinite(image)
    if bad.any():
        i, j, ch = (int(k) for k in bad.permute(1, 2, 0).nonzero()[0])  # first in reading order
        raise ValueError(
            f"{file}: {int(bad.sum())} non-finite pixel value(s) (NaN or inf), "
            f"first at row {i}, column {j}, channel {'RGB'[ch]}"
        )
    if not bool(image.any()):
        raise ValueError(f"{file}: every pixel is 0 (a blank or failed exposure?); such an image shows nothing")
    if not bool((image > 0).any()):
        raise ValueError(f"{file}: no pixel is positive; radiance cannot be negative, so this is not an "
                         "exposure of a lit sample (a sign or offset error?)")
    if float(image.abs().max()) > MAX_RADIANCE:
        raise ValueError(f"{file}: a pixel value reaches {float(image.abs().max()):g}, beyond "
                         f"±{MAX_RADIANCE:g} (the fit runs in float32); scale the images and intensities "
                         "down together")


def load_capture(
    folder: str | os.PathLike,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Capture:
    """Load and validate a capture folder (docs/capture_format.md).

    Args:
        folder: folder holding ``capture.json`` and the images it lists (paths relative to it).
        device: device of the returned tensors (default CPU).
        dtype: floating dtype of the returned tensors.

    Returns:
        A :class:`Capture` with images ``(L, 3, H, W)``, light positions and intensities
        ``(L, 3)`` and the camera position ``(3,)``.

    Raises:
        FileNotFoundError: the folder, ``capture.json`` or a listed image does not exist.
        NotADirectoryError: ``folder`` is a file.
        IsADirectoryError: a listed image is a folder.
        ValueError: malformed JSON, a missing or ill-typed key, an unsupported light type,
            a position that is not a finite 3-vector, a negative or non-finite intensity;
            an image name that is absolute, contains ``..`` or resolves (through a symlink)
            outside the folder; a light whose intensity is zero; a light or the camera on or
            below the sample plane (z <= 0); a coordinate beyond :data:`MAX_COORDINATE` or an
            intensity beyond :data:`MAX_RADIANCE`; a file listed twice; a ``capture.json``
            nested too deeply to parse; an image path that is not a regular file; an image
            that is not RGB, whose size differs from width/height, that has non-finite pixels,
            no positive pixel or a value beyond :data:`MAX_RADIANCE`, or the same pixels as
            another image. The message names the offending file and entry. Every
            ``capture.json`` check runs before any image is read.
    """
    folder = Path(folder)
    json_path, meta = _read_description(folder)
    width, height, cam_pos, entries = _capture_fields(meta, json_path)
    # First every entry (cheap, JSON only), then the images: bad descriptions fail up front.
    files, paths, positions, intensities = _image_entries(entries, folder, json_path)
    images = _read_images(paths, width, height, json_path)
    return Capture(
        images=torch.stack(images).to(device=device, dtype=dtype),
        light_positions=torch.tensor(positions, dtype=torch.float64).to(device=device, dtype=dtype),
        light_intensities=torch.tensor(intensities, dtype=torch.float64).to(device=device, dtype=dtype),
        camera_position=torch.tensor(cam_pos, dtype=torch.float64).to(device=device, dtype=dtype),
        width=width,
        height=height,
        files=tuple(files),
    )


def _read_description(folder: Path) -> tuple[Path, dict]:
    """``capture.json``'s path and its top-level object; errors name the folder or the file."""
    if not folder.is_dir():
        if folder.exists():
            raise NotADirectoryError(f"capture folder '{folder}' is a file, not a folder")
        raise FileNotFoundError(f"capture folder '{folder}' does not exist")
    json_path = folder / CAPTURE_JSON
    if not json_path.is_file():
        raise FileNotFoundError(f"{json_path}: missing; a capture folder needs a {CAPTURE_JSON}")
    try:
        meta = json.loads(json_path.read_text(encoding="utf-8"))
    except RecursionError as e:
        raise ValueError(f"{json_path}: nests lists or objects too deeply to read; a capture description "
                         "is a shallow object (docs/capture_format.md)") from e
    except json.JSONDecodeError as e:
        raise ValueError(f"{json_path}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from e
    except UnicodeDecodeError as e:
        raise ValueError(f"{json_path}: not UTF-8 text ({e})") from e
    if not isinstance(meta, dict):
        raise ValueError(f"{json_path}: the top level must be a JSON object, got {type(meta).__name__}")
    return json_path, meta


def _capture_fields(meta: dict, json_path: Path) -> tuple[int, int, list[float], list]:
    """Width, height, camera position and the ``images`` list of a description, checked."""
    width = _positive_int(_require(meta, "width", "the capture", json_path), "width", json_path)
    height = _positive_int(_require(meta, "height", "the capture", json_path), "height", json_path)
    camera = _require(meta, "camera", "the capture", json_path)
    if not isinstance(camera, dict):
        raise ValueError(f"{json_path}: camera must be an object, got {camera!r}")
    cam_pos = _vec3(_require(camera, "position", "camera", json_path), "camera.position", json_path)
    if cam_pos[2] <= 0:
        raise ValueError(f"{json_path}: camera.position is at z = {cam_pos[2]:g}, on or below the sample "
                         "plane; the sample at z = 0 faces +z, so a camera there cannot see it")
    entries = _require(meta, "images", "the capture", json_path)
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{json_path}: images must be a non-empty list")
    return width, height, cam_pos, entries


def _image_entries(entries: list, folder: Path, json_path: Path) -> tuple[list[str], list[Path], list, list]:
    """File names, image paths, light positions and intensities of the ``images`` entries, checked
    (JSON only: no image is opened)."""
    files: list[str] = []
    paths, positions, intensities = [], [], []
    for k, entry in enumerate(entries):
        where = f"images[{k}]"
        if not isinstance(entry, dict):
            raise ValueError(f"{json_path}: {where} must be an object, got {entry!r}")
        name = _require(entry, "file", where, json_path)
        paths.append(image_path(folder, name, f"{json_path}: {where}.file"))
        light = _require(entry, "light", where, json_path)
        if not isinstance(light, dict):
            raise ValueError(f"{json_path}: {where}.light must be an object, got {light!r}")
        kind = _require(light, "type", f"{where}.light", json_path)
        if kind not in _LIGHT_TYPES:
            raise ValueError(
                f"{json_path}: {where}.light has unsupported type {kind!r} (supported: {list(_LIGHT_TYPES)})"
            )
        pos = _vec3(
            _require(light, "position", f"{where}.light", json_path), f"{where}.light.position", json_path
        )
        inten = _vec3(
            _require(light, "intensity", f"{where}.light", json_path),
            f"{where}.light.intensity",
            json_path,
            nonnegative=True,
            limit=MAX_RADIANCE,
        )
        if name in files:
            raise ValueError(f"{json_path}: {where}.file {name!r} is listed already as "
                             f"images[{files.index(name)}].file; each light needs its own image")
        files.append(name)
        positions.append(pos)
        intensities.append(inten)
    _check_lights(
        positions,
        intensities,
        lambda k: f"{json_path}: images[{k}].light.intensity" if k is not None else f"{json_path}",
    )
    return files, paths, positions, intensities


def _read_images(paths: list[Path], width: int, height: int, json_path: Path) -> list[Tensor]:
    """The listed images, each ``(3, H, W)``, checked (:func:`_check_pixels`) and distinct."""
    images: list[Tensor] = []
    for k, file in enumerate(paths):
        where = f"images[{k}]"
        listed = f"{file}: image listed as {where}.file in {json_path}"
        if file.is_dir():
            raise IsADirectoryError(f"{listed} is a directory, not a file")
        if not file.exists():
            raise FileNotFoundError(f"{listed} not found (no such file)")
        if not file.is_file():  # checked before opening: reading a FIFO would block
            raise ValueError(f"{listed} is not a regular file (a FIFO, socket or device)")
        try:
            image = read_exr(file, channels=("R", "G", "B"))
        except ValueError as e:
            raise ValueError(f"{file} ({where} in {json_path}): {e}") from e
        _check_pixels(image, file, width, height, json_path)
        same = next((j for j, earlier in enumerate(images) if torch.equal(earlier, image)), None)
        if same is not None:
            raise ValueError(f"{file} ({where} in {json_path}): the same pixels as {paths[same].name} "
                             f"(images[{same}]); each light needs its own exposure")
        images.append(image)
    return images


def check_capture(capture: Capture) -> list[str]:
    """What a loaded capture cannot determine, one warning per problem (empty: nothing found).

    * Fewer lights than :data:`UNKNOWNS_PER_PIXEL`: each pixel has more unknowns than
      observations, so the maps come from the priors and the starting guess, not the data.
    * A degenerate light layout: the directions from the sample's centre to the lights
      span less than three dimensions (smallest singular value under
      :data:`DEGENERATE_LAYOUT` of the largest), so a normal's tilt in the missing
      direction trades against albedo.

    Args:
        capture: a :class:`Capture` (any device or dtype).

    Returns:
        One line per problem, each with what it costs.
    """
    n = len(capture)
    if n < UNKNOWNS_PER_PIXEL:
        return [f"the capture has {n} light(s) for {UNKNOWNS_PER_PIXEL} unknowns per pixel (normal 2, "
                "roughness, specular, albedo): the data cannot determine the maps, so they come from the priors and "
                "the starting guess (on synthetic captures with 1-2 lights the normals were off by about "
                "40 degrees); the confidence map is 0"]
    directions = capture.light_positions.double().cpu()
    directions = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    s = torch.linalg.svdvals(directions)
    ratio = float(s[-1] / s[0])
    if ratio < DEGENERATE_LAYOUT:
        return [f"the light directions nearly span only {int((s > DEGENERATE_LAYOUT * s[0]).sum())} "
                f"dimension(s) (smallest/largest singular value {ratio:.3g}): the normals' tilt along the "
                "missing direction cannot be told from an albedo change; the confidence map is 0"]
    return []


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _as_rows(value, what: str, count: int | None = None) -> np.ndarray:
    """``(L, 3)`` float64 array from a tensor/array/nested list."""
    arr = value.detach().cpu().double().numpy() if isinstance(value, Tensor) else np.asarray(value, float)
    if arr.ndim != 2 or arr.shape[1] != 3 or (count is not None and arr.shape[0] != count):
        want = f"({count}, 3)" if count is not None else "(L, 3)"
        raise ValueError(f"write_capture: {what} must have shape {want}, got {arr.shape}")
    return arr


def _light_fields(light: Mapping, where: str):
    """``light["position"], light["intensity"]``, or a ValueError naming ``where`` and its keys."""
    missing = [k for k in ("position", "intensity") if k not in light]
    if missing:
        raise ValueError(f"write_capture: {where} must have the keys 'position' and 'intensity'; "
                         f"{' and '.join(repr(k) for k in missing)} missing "
                         f"(it has {sorted(map(str, light))})")
    return light["position"], light["intensity"]


def _split_lights(lights) -> tuple[np.ndarray, np.ndarray]:
    """Light positions and intensities ``(L, 3)`` from any accepted ``lights`` form."""
    if isinstance(lights, Mapping):
        positions, intensities = _light_fields(lights, "lights")
        return _as_rows(positions, "light positions"), _as_rows(intensities, "light intensities")
    items = list(lights)

    def is_table(t) -> bool:
        return isinstance(t, (Tensor, np.ndarray)) and t.ndim == 2

    if len(items) == 2 and is_table(items[0]) and is_table(items[1]):
        return _as_rows(items[0], "light positions"), _as_rows(items[1], "light intensities")
    positions, intensities = [], []
    for k, light in enumerate(items):
        if isinstance(light, Mapping):
            kind = light.get("type", "point")
            if kind not in _LIGHT_TYPES:
                raise ValueError(f"write_capture: lights[{k}] has unsupported type {kind!r}")
            pos, inten = _light_fields(light, f"lights[{k}]")
        elif hasattr(light, "position") and hasattr(light, "intensity"):
            pos, inten = light.position, light.intensity  # e.g. torchbrdf.PointLight
        elif isinstance(light, (tuple, list)) and len(light) == 2:
            pos, inten = light
        else:
            raise ValueError(
                f"write_capture: lights[{k}] must be a (position, intensity) pair, a mapping with "
                f"'position' and 'intensity', or an object with those attributes; got {type(light).__name__}"
            )
        positions.append(_as_rows(torch.as_tensor(pos).reshape(1, -1), f"lights[{k}].position", 1)[0])
        intensities.append(_as_rows(torch.as_tensor(inten).reshape(1, -1), f"lights[{k}].intensity", 1)[0])
    if not positions:
        raise ValueError("write_capture: no lights given")
    return np.stack(positions), np.stack(intensities)


def write_capture(
    folder: str | os.PathLike,
    images: Tensor,
    lights: Mapping | Sequence,
    camera_position: Tensor | Sequence[float],
    *,
    files: Sequence[str] | None = None,
    half: bool = False,
    overwrite: bool = False,
) -> Path:
    """Write a capture folder (docs/capture_format.md): one RGB EXR per light, then ``capture.json``.

    Every file is written atomically, and ``capture.json`` last, so a reader never sees a
    description that lists images not yet on disk. The folder is created if needed.

    Args:
        folder: destination folder.
        images: linear radiance ``(L, 3, H, W)`` (or a sequence of ``(3, H, W)``), finite.
        lights: L point lights, as any of: a pair ``(positions, intensities)`` of ``(L, 3)``
            tensors/arrays; a mapping ``{"position": (L, 3), "intensity": (L, 3)}``; a
            sequence of L ``(position, intensity)`` pairs, of mappings with ``position`` and
            ``intensity`` keys, or of objects with ``.position`` / ``.intensity`` attributes
            (such as ``torchbrdf.PointLight``). Intensities are RGB and non-negative.
        camera_position: ``(3,)`` world position of the camera.
        files: image file names (default ``img_000.exr``, ``img_001.exr``, ...): relative
            paths inside ``folder``, with no ``..`` and no symlink leading out (see
            :func:`image_path`).
        half: store the images as half floats.
        overwrite: replace a capture already in ``folder`` (its ``capture.json``, the images it
            lists and any image file this call writes). Without it such a folder is refused, so
            an earlier capture is never lost or mixed with this one.

    Returns:
        The path of the written ``capture.json``.

    Raises:
        ValueError: on inconsistent counts or shapes, non-finite values, negative or zero
            intensities, no light above the sample plane, an all-zero image, or a file name
            that would leave ``folder`` — whatever :func:`load_capture` would refuse — and a
            ``folder`` that already holds a capture or one of the image files, without
            ``overwrite``, or that is (or lies under) a file. Nothing is written then.
    """
    images = _image_stack(images)
    count, _, height, width = images.shape
    positions, intensities = _checked_lights(lights, count)
    blank = ~images.flatten(1).any(dim=1)
    if blank.any():
        k = int(blank.nonzero()[0, 0])
        raise ValueError(f"write_capture: image {k} is all 0; the loader would reject it")
    cam = _checked_camera(camera_position)
    unlit = ~(images > 0).flatten(1).any(dim=1)
    out_of_range = (np.abs(positions) > MAX_COORDINATE).any() or (np.abs(cam) > MAX_COORDINATE).any()
    if unlit.any() or out_of_range or (intensities > MAX_RADIANCE).any() or images.abs().max() > MAX_RADIANCE:
        raise ValueError("write_capture: an image with no positive pixel, or a position or value beyond "
                         f"±{MAX_COORDINATE:g} / {MAX_RADIANCE:g}; the loader would reject it")
    folder = Path(folder)
    _refuse_a_file_in_the_way(folder)
    files = _file_names(files, count, folder)
    replaced = check_capture_destination(folder, files, overwrite)
    entries = []
    for k, name in enumerate(files):
        write_exr(folder / name, images[k], half=half)
        entries.append(
            {
                "file": name,
                "light": {
                    "type": "point",
                    "position": positions[k].tolist(),
                    "intensity": intensities[k].tolist(),
                },
            }
        )
    # One image entry per line: readable and diff-friendly, unlike indent=2 on short vectors.
    lines = [
        "{",
        f'  "width": {int(width)},',
        f'  "height": {int(height)},',
        f'  "camera": {json.dumps({"position": cam.tolist()})},',
        '  "images": [',
        ",\n".join(f"    {json.dumps(e)}" for e in entries),
        "  ]",
        "}",
    ]
    json_path = folder / CAPTURE_JSON
    with atomic_path(json_path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    for name in sorted(set(replaced) - set(files) - {CAPTURE_JSON}):  # the replaced capture's images
        if (folder / name).is_file():
            (folder / name).unlink()
    return json_path


def default_file_names(count: int) -> list[str]:
    """The image names :func:`write_capture` uses by default: ``img_000.exr`` ... (``count`` of them)."""
    digits = max(3, len(str(count - 1)))
    return [f"img_{k:0{digits}d}.exr" for k in range(count)]


def check_capture_destination(folder: str | os.PathLike, files: Sequence[str], overwrite: bool) -> list[str]:
    """Refuse to write a capture over another unless ``overwrite``.

    Args:
        folder: the capture folder about to be written.
        files: the image names about to be written (relative to ``folder``).
        overwrite: whether replacing an existing capture (and image files) is allowed.

    Returns:
        The image names the existing ``capture.json`` lists (empty when there is none, or when it
        is unreadable): with ``overwrite`` they belong to the capture being replaced.

    Raises:
        ValueError: when ``folder``, or the nearest of its parents that exists, is a file; without
            ``overwrite``, when ``folder`` holds ``capture.json`` or a file of ``files``, naming it.
    """
    folder = Path(folder)
    _refuse_a_file_in_the_way(folder)
    json_path = folder / CAPTURE_JSON
    clash = [json_path] if json_path.exists() else []
    clash += [folder / os.fspath(f) for f in files if (folder / os.fspath(f)).exists()]
    if clash and not overwrite:
        raise ValueError(f"write_capture: {clash[0]} already exists; pass overwrite=True to replace the "
                         f"capture in {folder}, or write to another folder")
    if not json_path.is_file():
        return []
    try:
        listed = [e["file"] for e in json.loads(json_path.read_text(encoding="utf-8"))["images"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    inside = []
    for name in listed:  # only names that stay inside the folder (image_path's rule) are removed
        try:
            image_path(folder, name, "capture.json")
        except ValueError:
            continue
        inside.append(name)
    return inside


def _refuse_a_file_in_the_way(folder: Path) -> None:
    """``folder``, or the nearest of its parents that exists, must be a folder (mkdir's own error
    names neither)."""
    if (blocked := file_in_the_way(folder)) is not None:
        raise ValueError(f"write_capture: {blocked} is a file, not a folder; cannot write a capture in {folder}")


def _image_stack(images: Tensor | Sequence) -> Tensor:
    """``(L, 3, H, W)`` detached images, checked finite (what :func:`load_capture` needs)."""
    if not isinstance(images, Tensor):
        images = torch.stack([torch.as_tensor(im) for im in images])
    images = images.detach()
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"write_capture: images must have shape (L, 3, H, W), got {tuple(images.shape)}")
    if not torch.isfinite(images).all():
        bad = int((~torch.isfinite(images)).nonzero()[0, 0])
        raise ValueError(f"write_capture: image {bad} has non-finite pixels; the loader would reject it")
    return images


def _checked_lights(lights: Mapping | Sequence, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Light positions and intensities ``(count, 3)`` float64, refused as :func:`load_capture` would."""
    positions, intensities = _split_lights(lights)
    if positions.shape[0] != count or intensities.shape[0] != count:
        raise ValueError(
            f"write_capture: {count} images but {positions.shape[0]} light positions "
            f"and {intensities.shape[0]} intensities"
        )
    if not (np.isfinite(positions).all() and np.isfinite(intensities).all()):
        raise ValueError("write_capture: light positions and intensities must be finite")
    if (intensities < 0).any():
        k = int(np.nonzero((intensities < 0).any(axis=1))[0][0])
        raise ValueError(f"write_capture: light {k} has a negative intensity {intensities[k].tolist()}")
    # What the loader refuses is refused here too, so a written capture always loads.
    _check_lights(
        positions.tolist(),
        intensities.tolist(),
        lambda k: f"write_capture: the intensity of light {k}" if k is not None else "write_capture",
    )
    return positions, intensities


def _checked_camera(camera_position: Tensor | Sequence[float]) -> np.ndarray:
    """The camera position ``(3,)`` float64: finite and above the sample plane."""
    cam = (
        camera_position.detach().cpu().double().numpy()
        if isinstance(camera_position, Tensor)
        else np.asarray(camera_position, float)
    )
    if cam.shape != (3,) or not np.isfinite(cam).all():
        raise ValueError(f"write_capture: camera_position must be a finite 3-vector, got {cam.tolist()}")
    if cam[2] <= 0:
        raise ValueError(f"write_capture: camera_position {cam.tolist()} is on or below the sample plane; "
                         "the loader would reject it")
    return cam


def _file_names(files: Sequence[str] | None, count: int, folder: Path) -> list[str]:
    """``count`` distinct image names inside ``folder`` (default ``img_000.exr`` ...); creates the
    folder only after every name is checked, then checks again for symlinks inside it."""
    if files is None:
        files = default_file_names(count)
    files = [os.fspath(f) if isinstance(f, os.PathLike) else f for f in files]
    if len(files) != count or len(set(files)) != count:
        raise ValueError(f"write_capture: need {count} distinct file names, got {excerpt(files)}")
    for k, name in enumerate(files):  # before anything is created: nothing lands outside
        image_path(folder, name, f"write_capture: files[{k}]")

    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(files):  # again now that the folder exists: symlinks inside it
        image_path(folder, name, f"write_capture: files[{k}]")
    return files
