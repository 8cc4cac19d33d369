"""An evaluation set built differently from :mod:`torchbrdf.capture.synthetic`.

``photo_capture(folder, name, seed, size)`` writes a capture folder (``capture.json`` + EXRs +
``gt/``) whose material maps come from scikit-image's bundled photographs, rendered by a forward
model other than the one the recovery fits, with light-calibration error:

* **maps from photographs**: base colour from the photo's colour (grey photos are tinted),
  roughness and the metal mask from its structure (local contrast, thresholds), normals from a
  height field = the smoothed luminance;
* **glossy materials** (``glazed_brick``, ``coffee``, ``coins``) whose highlights miss most of
  the sample: the 16 ring lights' mirror highlights fall on a ring of radius ~0.9;
* **forward model**: Lambertian diffuse (the fit uses Burley's), GGX with *exact* dielectric
  Fresnel (index from ``specular``; the fit uses Schlick) and height-correlated Smith masking
  (the fit uses the separable form), metals with Schlick F0 = base colour;
* **calibration error** (``calibration=True``): each light's true intensity is the stated one
  × (1 + N(0, 0.03)) and its true position the stated one + N(0, 0.01) per axis (0.01 scene
  units: 1 cm if a unit is a metre; the lights are ~2.5 units away), while ``capture.json``
  states the nominal values.

Seeds < 100 are for tuning, seeds ≥ 100 are held out (``training.evaluate --set photo``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

import torchbrdf
from torchbrdf.brdf.diffuse import diffuse_burley
from torchbrdf.capture.format import check_capture_destination, default_file_names, pixel_points, write_capture
from torchbrdf.capture.synthetic import DEFAULT_CAMERA, add_noise, light_layout, write_maps

PHOTO_MATERIALS = ("glazed_brick", "coffee", "coins", "gravel", "grass")
GLOSSY = ("glazed_brick", "coffee", "coins")


def _photo(name: str) -> np.ndarray:
    import skimage.data

    img = getattr(skimage.data, name)().astype(np.float64) / 255.0
    return img if img.ndim == 3 else img[..., None].repeat(3, -1)


def _crop(img: np.ndarray, gen: np.random.Generator, size: int, frac=(0.6, 0.9)) -> Tensor:
    h, w = img.shape[:2]
    side = int(min(h, w) * gen.uniform(*frac))
    y0, x0 = int(gen.integers(0, h - side + 1)), int(gen.integers(0, w - side + 1))
    t = torch.from_numpy(img[y0:y0 + side, x0:x0 + side]).permute(2, 0, 1)[None]
    return F.interpolate(t, size=(size, size), mode="area")[0].float()  # (3, S, S)


def _gauss(x: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of ``(S, S)`` with reflect padding."""
    r = max(1, int(3 * sigma))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype) / sigma) ** 2)
    k = k / k.sum()
    img = F.pad(x[None, None], (r, r, r, r), mode="reflect")
    img = F.conv2d(img, k.view(1, 1, 1, -1))
    return F.conv2d(img, k.view(1, 1, -1, 1))[0, 0]


def _normals(height: Tensor) -> Tensor:
    """Unit normals ``(3, S, S)`` of a height ``(S, S)`` over [-1, 1]² (numpy gradient: one-sided at borders)."""
    s = height.shape[-1]
    gy, gx = np.gradient(height.double().numpy(), 2.0 / s)
    n = torch.stack((torch.from_numpy(-gx), torch.from_numpy(gy), torch.ones(s, s, dtype=torch.float64)), 0)
    return (n / n.norm(dim=0, keepdim=True)).float()


def _norm01(x: Tensor) -> Tensor:
    lo, hi = torch.quantile(x.flatten(), 0.02), torch.quantile(x.flatten(), 0.98)
    return ((x - lo) / (hi - lo).clamp(min=1e-6)).clamp(0, 1)


def photo_material(name: str, seed: int, size: int = 256) -> dict[str, Tensor]:
    """Principled maps ``(C, S, S)`` derived from a scikit-image photograph (see the module doc)."""
    gen = np.random.default_rng(10_000 + seed)
    s = size / 256  # structure scales with the resolution
    if name == "glazed_brick":  # glazed bricks (glossy), rough mortar; grey photo tinted
        lum = _crop(_photo("brick"), gen, size).mean(0)
        sm = _gauss(lum, 2.0 * s)
        brick = _norm01(sm) < 0.5  # the photo's mortar lines are bright
        hue = torch.tensor(gen.uniform([0.45, 0.12, 0.06], [0.75, 0.35, 0.2]), dtype=torch.float32)
        base = torch.where(brick, hue[:, None, None] * (0.6 + 0.6 * lum), torch.tensor([0.55, 0.53, 0.5])[:, None, None] * (0.7 + 0.5 * lum))
        contrast = _norm01(_gauss((lum - sm).abs(), 3.0 * s))
        rough = torch.where(brick, gen.uniform(0.12, 0.2) + 0.15 * contrast, 0.8 + 0.1 * contrast)
        spec = torch.where(brick, torch.full_like(lum, gen.uniform(0.45, 0.65)), torch.full_like(lum, 0.35))
        metal = torch.zeros_like(lum)
        height = 0.01 * _gauss(brick.float(), 1.5 * s) + 0.004 * _gauss(lum, 1.0 * s)
    elif name == "coffee":  # glossy glazed ceramic/paint: the photo's colour, roughness from structure
        rgb = _crop(_photo("coffee"), gen, size)
        lum = rgb.mean(0)
        base = 0.04 + 0.8 * rgb
        grad = _norm01(_gauss((lum - _gauss(lum, 2.0 * s)).abs(), 2.0 * s))
        rough = gen.uniform(0.12, 0.18) + 0.25 * grad
        spec = torch.full_like(lum, gen.uniform(0.4, 0.6))
        metal = torch.zeros_like(lum)
        height = 0.006 * _gauss(lum, 2.0 * s)
    elif name == "coins":  # metal discs (glossy) on a rough dark dielectric
        lum = _crop(_photo("coins"), gen, size, frac=(0.7, 0.95)).mean(0)
        sm = _gauss(lum, 2.0 * s)
        coin = (_norm01(sm) > 0.45).float()
        coin = (_gauss(coin, 1.0 * s) > 0.5).float()  # tidy mask
        gold = torch.tensor(gen.uniform([0.8, 0.6, 0.35], [0.95, 0.8, 0.55]), dtype=torch.float32)
        base = torch.where(coin > 0.5, gold[:, None, None] * (0.85 + 0.15 * lum),
                           torch.tensor([0.12, 0.13, 0.15])[:, None, None] * (0.6 + 0.8 * lum))
        rough = torch.where(coin > 0.5, gen.uniform(0.2, 0.3) + 0.1 * _norm01(lum), torch.full_like(lum, 0.75))
        spec = torch.full_like(lum, 0.5)
        metal = coin
        height = 0.015 * _gauss(coin, 2.0 * s) + 0.004 * _gauss(lum, 1.0 * s)
    elif name == "gravel":  # rough stone
        lum = _crop(_photo("gravel"), gen, size).mean(0)
        hue = torch.tensor(gen.uniform([0.4, 0.35, 0.3], [0.6, 0.55, 0.5]), dtype=torch.float32)
        base = hue[:, None, None] * (0.3 + 0.9 * lum)
        rough = 0.55 + 0.35 * _norm01(_gauss((lum - _gauss(lum, 2.0 * s)).abs(), 2.0 * s))
        spec = torch.full_like(lum, 0.5)
        metal = torch.zeros_like(lum)
        height = 0.02 * _gauss(lum, 1.5 * s)
    elif name == "grass":  # leaves: green albedo, medium gloss
        lum = _crop(_photo("grass"), gen, size).mean(0)
        hue = torch.tensor(gen.uniform([0.1, 0.3, 0.05], [0.25, 0.5, 0.15]), dtype=torch.float32)
        base = hue[:, None, None] * (0.4 + 1.0 * lum)
        rough = 0.3 + 0.3 * (1 - _norm01(_gauss(lum, 1.5 * s)))
        spec = torch.full_like(lum, 0.45)
        metal = torch.zeros_like(lum)
        height = 0.01 * _gauss(lum, 1.5 * s)
    else:
        raise ValueError(f"photo_material: unknown name {name!r}; expected one of {PHOTO_MATERIALS}")
    return {"base_color": base.clamp(0.03, 0.95).float(), "roughness": rough.clamp(0.05, 1)[None].float(),
            "metallic": metal[None].float(), "specular": spec.clamp(0, 1)[None].float(),
            "normal": _normals(height)}


def render_other_model(maps: dict, lights, camera=DEFAULT_CAMERA, diffuse: str = "lambert") -> Tensor:
    """Images ``(L, 3, S, S)`` of ``maps`` under point lights, by a model other than the fitted one.

    Lambertian diffuse ``base (1 − metallic) / π`` (``diffuse="burley"``: Burley's, as the fitted
    model has it); GGX (α = roughness²) with height-correlated Smith masking; exact dielectric
    Fresnel with the index whose F0 is ``0.08 specular`` for dielectrics, Schlick with F0 = base
    colour for metals.

    Under Burley's diffuse, the principled model's roughness also shapes the diffuse lobe, so a
    rough Lambertian material is not best fitted at its own roughness (docs/recovery.md, Known limits);
    ``"burley"`` keeps the rest of the mismatch and takes that part out.
    """
    if diffuse not in ("lambert", "burley"):
        raise ValueError(f"render_other_model: diffuse must be 'lambert' or 'burley', got {diffuse!r}")
    pos, inten = lights
    s = maps["base_color"].shape[-1]
    p = pixel_points(s, s).reshape(-1, 3).double()
    n = maps["normal"].reshape(3, -1).T.double()
    base = maps["base_color"].reshape(3, -1).T.double()
    rough = maps["roughness"].reshape(-1, 1).double()
    metal = maps["metallic"].reshape(-1, 1).double()
    spec = maps["specular"].reshape(-1, 1).double()
    cam = torch.as_tensor(camera, dtype=torch.float64)
    v = F.normalize(cam - p, dim=-1)
    ior = torchbrdf.ior_from_f0((0.08 * spec).clamp(min=1e-4))
    out = []
    for k in range(pos.shape[0]):
        dl = pos[k].double() - p
        d2 = (dl * dl).sum(-1, keepdim=True)
        l = dl / d2.sqrt()
        alpha = (rough * rough).clamp(min=1e-3)
        if diffuse == "burley":
            h = F.normalize(l + v, dim=-1)
            dot = lambda a, b: (a * b).sum(-1, keepdim=True)  # noqa: E731
            fd = diffuse_burley(dot(n, l).clamp(min=0), dot(n, v).clamp(min=0), dot(l, h), base, rough) * (1 - metal)
        else:
            fd = base * (1 - metal) / math.pi
        fs_d = torchbrdf.microfacet(l, v, n, alpha=alpha, fresnel="dielectric", ior=ior, masking="smith_correlated")
        fs_m = torchbrdf.microfacet(l, v, n, alpha=alpha, fresnel="schlick", f0=base, masking="smith_correlated")
        f = fd + (1 - metal) * fs_d + metal * fs_m
        nl = (n * l).sum(-1, keepdim=True).clamp(min=0)
        img = f * inten[k].double() * nl / d2
        out.append(img.T.reshape(3, s, s))
    return torch.stack(out).float()


def calibrated_lights(seed: int, lights: int = 16, error: bool = True):
    """``(nominal, true)`` light sets ``(positions (L, 3), intensities (L, 3))``: the true ones carry
    intensity × (1 + N(0, 0.03)) and position + N(0, 0.01) per axis when ``error``."""
    pos, inten = light_layout(lights)
    if not error:
        return (pos, inten), (pos, inten)
    gen = torch.Generator().manual_seed(50_000 + seed)
    scale = 1 + 0.03 * torch.randn(pos.shape[0], 1, generator=gen)
    dpos = 0.01 * torch.randn(pos.shape, generator=gen)
    return (pos, inten), (pos + dpos, inten * scale)


def photo_capture(folder, name: str, seed: int, size: int = 256, lights: int = 16, noise: float = 0.01,
                  calibration: bool = True, diffuse: str = "lambert", overwrite: bool = False) -> Path:
    """Write a photo-derived capture folder (``capture.json`` states the nominal lights); returns it.

    ``diffuse``: the forward model's diffuse lobe (:func:`render_other_model`); ``overwrite``:
    replace a capture already in ``folder`` (refused without it, see ``write_capture``)."""
    folder = Path(folder)
    nominal, true = calibrated_lights(seed, lights, calibration)
    check_capture_destination(folder, default_file_names(len(nominal[0])), overwrite)  # before gt/ is written
    maps = photo_material(name, seed, size)
    with torch.no_grad():
        img = render_other_model(maps, true, diffuse=diffuse)
        img = add_noise(img, noise, seed)
    write_maps(folder / "gt", maps, previews=False)
    write_capture(folder, img, nominal, DEFAULT_CAMERA, overwrite=overwrite)
    torch.save({"true_intensity": true[1], "true_position": true[0]}, folder / "true_lights.pt")
    return folder
