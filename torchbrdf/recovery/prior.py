"""A learned prior for SVBRDF recovery: a compact U-Net that estimates principled maps from flash image(s).

* :class:`MapEstimator` -- the network: ``L`` images ``(B, L, 3, H, W)`` of a flat sample (the
  capture format, ``docs/capture_format.md``) plus their lights -> principled maps
  ``(B, 9, H, W)`` in :data:`torchbrdf.losses.PRINCIPLED_LAYOUT` order. Trained by
  ``python -m training.train_estimator`` (``docs/neural.md``).
* :class:`Prior` -- a trained estimator loaded from a file (:meth:`Prior.from_file`, or the
  weights shipped with the package, :meth:`Prior.default`) whose :meth:`Prior.predict` turns
  images or a :class:`~torchbrdf.capture.Capture` into a dict of ``(B, C, H, W)`` maps.
* :func:`prior_penalty` -- the confidence-weighted regulariser a solver adds to pull its maps
  toward the prior's where the captured data are silent; :func:`prior_weight` makes its
  weight from a recovery confidence map.
* :class:`LearnedPrior` -- a Prior's maps for one capture as :func:`~torchbrdf.recovery.recover`
  uses them (``prior=``): a Gaussian unary term (:func:`prior_unary`) with the network's measured
  errors (:func:`estimator_errors`, raised to what the capture shows by :func:`measured_map_errors`;
  :func:`measured_metallic_error` is reported), and its metallic as bounded odds in the class
  choice (:func:`class_prior_cost`, :func:`class_costs_with_prior`).

Input normalisation (:func:`estimator_inputs`): each image is divided by its light's intensity
and multiplied by the squared light distance at the sample's centre (so the network sees
``~ f * cos``, independent of the light's power), then ``log(x + 0.01)``; two channels of pixel
coordinates tell the network where each pixel lies relative to the flash.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchbrdf.capture.format import Capture, pixel_points
from torchbrdf.capture.synthetic import MAP_NAMES, light_layout
from torchbrdf.recovery.classes import class_evidence, evidence_threshold
from torchbrdf.recovery.params import N_PARAMS, R_MAX, R_MIN, encode

__all__ = ["MapEstimator", "Prior", "estimator_inputs", "prior_penalty", "prior_weight", "DEFAULT_WEIGHTS", "SHIPPED_WEIGHTS",
           "FALLBACK_MAP_ERRORS", "estimator_errors", "prior_maps_at", "prior_unary", "measured_metallic_error",
           "measured_map_errors", "class_prior_cost", "class_costs_with_prior", "METALLIC_ODDS_FLOOR",
           "LearnedPrior"]

DEFAULT_WEIGHTS = "estimator.pt"
"""File name of the shipped one-image weights inside the ``torchbrdf.weights`` package."""

#: The shipped weights by the images their estimator takes (:meth:`Prior.default`).
SHIPPED_WEIGHTS = {1: DEFAULT_WEIGHTS, 4: "estimator_ring4.pt"}

_LOG_OFFSET = 0.01  # as the rendering loss's log transform: compresses highlights, keeps dark detail


def estimator_inputs(images: Tensor, light_positions: Tensor, light_intensities: Tensor) -> Tensor:
    """Normalised network input: ``(B, L, 3, H, W)`` images -> ``(B, 3 L + 2, H, W)``.

    Args:
        images: linear radiance ``(B, L, 3, H, W)``.
        light_positions: ``(B, L, 3)`` or ``(L, 3)`` world positions.
        light_intensities: ``(B, L, 3)`` or ``(L, 3)`` RGB intensities (positive).

    Returns:
        ``log(images * |q|^2 / I + 0.01)`` per light, then the pixel coordinates ``x, y``.
    """
    if images.dim() != 5 or images.shape[2] != 3:
        raise ValueError(f"estimator_inputs: images must be (B, L, 3, H, W), got {tuple(images.shape)}")
    b, nl, _, h, w = images.shape
    pos = light_positions.to(images).expand(b, nl, 3)
    inten = light_intensities.to(images).expand(b, nl, 3)
    scale = (pos * pos).sum(-1, keepdim=True) / inten.clamp(min=1e-8)
    x = torch.log(torch.clamp(images * scale[..., None, None], min=0.0) + _LOG_OFFSET).reshape(b, 3 * nl, h, w)
    coords = pixel_points(w, h, device=images.device, dtype=images.dtype)[..., :2].permute(2, 0, 1)
    return torch.cat((x, coords.expand(b, 2, h, w)), 1)


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(min(8, cout // 4), cout), nn.LeakyReLU(0.1),
        nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(min(8, cout // 4), cout), nn.LeakyReLU(0.1),
    )


class MapEstimator(nn.Module):
    """Compact U-Net: flash image(s) -> principled maps.

    Args:
        lights: L, the images it takes (the flash first).
        width: channels of the first level (doubled per level).
        depth: number of 2x downsamplings; H and W are padded to a multiple of ``2 ** depth``.

    Shape:
        - Input: ``images (B, L, 3, H, W)``, ``light_positions`` and ``light_intensities``
          ``(B, L, 3)`` or ``(L, 3)``.
        - Output: ``(B, 9, H, W)``: base_color, roughness, metallic, specular in [0, 1]
          (sigmoids), then a unit tangent-space normal with z > 0.
    """

    def __init__(self, lights: int = 1, width: int = 16, depth: int = 3) -> None:
        super().__init__()
        if lights < 1 or width < 4 or depth < 1:
            raise ValueError(f"MapEstimator: need lights >= 1, width >= 4, depth >= 1; got {lights}, {width}, {depth}")
        self.config = {"lights": int(lights), "width": int(width), "depth": int(depth)}
        chans = [width * 2**i for i in range(depth + 1)]
        self.down = nn.ModuleList([_block(3 * lights + 2, chans[0])]
                                  + [_block(chans[i], chans[i + 1]) for i in range(depth)])
        self.up = nn.ModuleList([nn.ConvTranspose2d(chans[i + 1], chans[i], 2, stride=2) for i in range(depth)])
        self.merge = nn.ModuleList([_block(2 * chans[i], chans[i]) for i in range(depth)])
        self.head = nn.Conv2d(chans[0], 8, 1)
        with torch.no_grad():  # start from flat normals: most of a sample's surface is nearly flat
            self.head.weight[6:].zero_()
            if self.head.bias is not None:
                self.head.bias[6:].zero_()

    def forward(self, images: Tensor, light_positions: Tensor, light_intensities: Tensor) -> Tensor:
        if images.dim() != 5 or images.shape[1] != self.config["lights"]:
            raise ValueError(f"MapEstimator: images must be (B, {self.config['lights']}, 3, H, W), "
                             f"got {tuple(images.shape)}")
        x = estimator_inputs(images, light_positions, light_intensities)
        h, w = x.shape[-2:]
        m = 2 ** self.config["depth"]
        x = F.pad(x, (0, -w % m, 0, -h % m), mode="replicate")
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.avg_pool2d(x, 2))
            skips.append(x)
        for i in reversed(range(self.config["depth"])):
            x = self.merge[i](torch.cat((self.up[i](x), skips[i]), 1))
        out = self.head(x)[..., :h, :w]
        params = torch.sigmoid(out[:, :6])
        tilt = out[:, 6:8]
        normal = torch.cat((tilt, torch.ones_like(tilt[:, :1])), 1)
        return torch.cat((params, normal * torch.rsqrt((normal * normal).sum(1, keepdim=True))), 1)


def _as_batch(t: Tensor, b: int) -> Tensor:
    return t if t.dim() == 3 else t[None].expand(b, *t.shape)


class Prior:
    """A trained :class:`MapEstimator` with its model card, ready to predict maps.

    Use :meth:`from_file` or :meth:`default`; :meth:`save` writes the same format (a
    ``torch.save`` dict of the config, the state dict and the card, loaded with
    ``weights_only=True``).

    Attributes:
        model: the :class:`MapEstimator` (eval mode).
        card: the model card (training data, time, measured accuracy), a dict.
    """

    def __init__(self, model: MapEstimator, card: Mapping[str, Any] | None = None) -> None:
        self.model = model.eval()
        self.card = dict(card or {})

    @property
    def lights(self) -> int:
        """L, the number of images the estimator takes."""
        return int(self.model.config["lights"])

    @classmethod
    def from_file(cls, path: str | os.PathLike, map_location: torch.device | str = "cpu") -> Prior:
        """Load weights written by :meth:`save` (or ``python -m training.train_estimator``).

        Raises:
            FileNotFoundError: if ``path`` does not exist.
            ValueError: if the file is not an estimator checkpoint.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"Prior.from_file: no weights file at {path}")
        if not zipfile.is_zipfile(path):  # torch.save writes a zip archive; torch's own error here
            # would advise weights_only=False, which cannot help and is unsafe to follow
            raise ValueError(f"Prior.from_file: {path} is not a readable estimator checkpoint "
                             "(not a torch.save archive; expected weights written by Prior.save)")
        try:
            ckpt = torch.load(path, map_location=map_location, weights_only=True)
        except Exception as err:  # a truncated or foreign file: say which, with the cause
            raise ValueError(f"Prior.from_file: {path} is not a readable estimator checkpoint ({err})") from err
        if not isinstance(ckpt, dict) or not {"config", "state_dict"} <= set(ckpt):
            raise ValueError(f"Prior.from_file: {path} is not an estimator checkpoint "
                             "(expected a dict with 'config' and 'state_dict')")
        model = MapEstimator(**ckpt["config"])
        model.load_state_dict({k: v.float() for k, v in ckpt["state_dict"].items()})
        card = ckpt.get("card") or {}
        return cls(model, json.loads(card) if isinstance(card, str) else card)

    @classmethod
    def default(cls, lights: int | None = None) -> Prior:
        """An estimator shipped in the package (``torchbrdf/weights/``, :data:`SHIPPED_WEIGHTS`).

        Args:
            lights: the capture's light count: the shipped estimator taking the most images
                it has (4 lights or more: the one trained on the 4-light ring; fewer: the
                flash-image one). None: the flash-image one (``estimator.pt``).

        Raises:
            ValueError: if ``lights`` is below 1.
        """
        if lights is not None and lights < 1:
            raise ValueError(f"Prior.default: lights must be >= 1, got {lights}")
        name = SHIPPED_WEIGHTS[max(k for k in SHIPPED_WEIGHTS if k <= (lights or 1))]
        ref = resources.files("torchbrdf.weights").joinpath(name)
        with resources.as_file(ref) as path:
            return cls.from_file(path)

    def save(self, path: str | os.PathLike, half: bool = True) -> None:
        """Write the weights (float16 when ``half``, halving the file) and the card to ``path``."""
        state = {k: (v.half() if half and v.is_floating_point() else v) for k, v in self.model.state_dict().items()}
        tmp = Path(f"{path}.tmp{os.getpid()}")
        torch.save({"config": self.model.config, "state_dict": state, "card": json.dumps(self.card)}, tmp)
        os.replace(tmp, path)  # atomic: a reader never sees half a file

    def to(self, device: torch.device | str) -> Prior:
        """Move the network to ``device`` (in place); returns ``self``."""
        self.model.to(device)
        return self

    @property
    def layout(self) -> str:
        """The extra lights it was trained with (the card's ``data.layout``): ``"ring"``, the ring of
        :func:`~torchbrdf.capture.synthetic.light_layout`, or ``"random"`` (cards without it)."""
        data = self.card.get("data")
        return str(data.get("layout", "random")) if isinstance(data, Mapping) else "random"

    def capture_lights(self, capture: Capture) -> Tensor:
        """Indices ``(L,)`` of the capture's lights the estimator takes, the flash first.

        The flash is the light nearest the camera. An estimator trained on the ring of
        :func:`~torchbrdf.capture.synthetic.light_layout` (:attr:`layout`) then takes, for each
        light of the ring of ``L − 1``, the unused capture light nearest it in direction from the
        sample's centre: a 4-light capture gives its own lights, a 17-light ring the four nearest
        the layout the network learned (not three neighbours). Otherwise the next nearest the camera.

        Raises:
            ValueError: if the capture has fewer than ``L`` lights.
        """
        pos = capture.light_positions.double().cpu()
        if len(pos) < self.lights:
            raise ValueError(f"Prior.capture_lights: the estimator takes {self.lights} images, the capture has "
                             f"{len(pos)}")
        order = torch.argsort((pos - capture.camera_position.double().cpu()).norm(dim=-1), stable=True)
        if self.layout != "ring" or self.lights == 1:
            return order[: self.lights]
        chosen = [int(order[0])]
        dirs = pos / pos.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        ring, _ = light_layout(self.lights - 1, near_camera=False)
        for q in ring.double():
            cos = dirs @ (q / q.norm())
            cos[chosen] = -math.inf
            chosen.append(int(torch.argmax(cos)))
        return torch.tensor(chosen)

    @torch.no_grad()
    def predict(
        self,
        images: Tensor | Capture,
        light_positions: Tensor | None = None,
        light_intensities: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Estimate principled maps.

        Args:
            images: ``(B, L, 3, H, W)`` linear radiance (``L`` = :attr:`lights`, the flash
                first), or a :class:`~torchbrdf.capture.Capture`, whose lights
                :meth:`capture_lights` chooses.
            light_positions: ``(B, L, 3)`` or ``(L, 3)``; default the flash of
                :func:`~torchbrdf.capture.synthetic.light_layout` (required for ``L > 1``).
            light_intensities: like ``light_positions``; default that flash's intensity.

        Returns:
            ``base_color (B, 3, H, W)``, ``roughness``, ``metallic``, ``specular``
            ``(B, 1, H, W)`` and ``normal (B, 3, H, W)``, on the images' device, float32.
        """
        if isinstance(images, Capture):
            order = self.capture_lights(images)
            light_positions, light_intensities = images.light_positions[order], images.light_intensities[order]
            images = images.images[order][None]
        if not isinstance(images, Tensor) or images.dim() != 5 or images.shape[1:3] != (self.lights, 3):
            raise ValueError(f"Prior.predict: images must be (B, {self.lights}, 3, H, W) or a Capture, got "
                             f"{tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__}")
        if light_positions is None or light_intensities is None:
            if self.lights != 1:
                raise ValueError("Prior.predict: light_positions and light_intensities are required "
                                 f"for an estimator of {self.lights} images")
            pos, inten = light_layout(0, near_camera=True)
            light_positions = pos if light_positions is None else light_positions
            light_intensities = inten if light_intensities is None else light_intensities
        device = next(self.model.parameters()).device
        b = images.shape[0]
        out = self.model(images.to(device, torch.float32), _as_batch(light_positions.to(device, torch.float32), b),
                         _as_batch(light_intensities.to(device, torch.float32), b)).to(images.device)
        return dict(zip(MAP_NAMES, torch.split(out, list(MAP_NAMES.values()), dim=1)))


def prior_weight(confidence: Tensor, strength: float = 1.0) -> Tensor:
    """Per-pixel prior weight ``strength * (1 - confidence)``: full where the data are silent.

    Args:
        confidence: the recovery's confidence map in [0, 1], ``(1, H, W)`` or ``(B, 1, H, W)``
            (1: the data measured the pixel; 0: the priors inferred it).
        strength: the weight where the confidence is 0.
    """
    return strength * (1.0 - confidence.clamp(0.0, 1.0))


def prior_penalty(
    maps: Mapping[str, Tensor],
    prior_maps: Mapping[str, Tensor],
    weight: Tensor | float,
    map_weights: Mapping[str, float] | None = None,
) -> Tensor:
    """Confidence-weighted squared distance of ``maps`` to the prior's maps.

    ``sum over maps of map_weights[m] * mean over pixels of weight * |maps[m] - prior_maps[m]|^2``,
    summed over channels; maps missing from either dict are skipped. The prior maps are
    constants (detached): the penalty pulls ``maps`` toward them, never the reverse.

    Args:
        maps: name -> ``(B, C, H, W)`` or ``(C, H, W)`` maps being fitted.
        prior_maps: name -> maps of the same shapes (e.g. :meth:`Prior.predict`).
        weight: per-pixel weight broadcasting against the maps (e.g. ``(B, 1, H, W)`` from
            :func:`prior_weight`), or a float.
        map_weights: name -> weight (default 1 for each map).

    Returns:
        A 0-d tensor.

    Raises:
        ValueError: if a shared map's shapes differ.
    """
    total: Tensor | None = None
    for name, value in maps.items():
        if name not in prior_maps:
            continue
        target = prior_maps[name].detach().to(value)
        if target.shape != value.shape:
            raise ValueError(f"prior_penalty: map {name!r} is {tuple(value.shape)} but the prior's is "
                             f"{tuple(target.shape)}")
        w = (map_weights or {}).get(name, 1.0)
        term = w * (weight * (value - target).square().sum(-3, keepdim=True)).mean()
        total = term if total is None else total + term
    if total is None:
        raise ValueError(f"prior_penalty: no map in common between {sorted(maps)} and {sorted(prior_maps)}")
    return total


#: Per-map errors a :class:`Prior` assumes when its card measured none: about the best constant
#: maps' held-out RMSE (a network no better than a constant is no prior to lean on).
FALLBACK_MAP_ERRORS = {"base_color": 0.27, "roughness": 0.18, "metallic": 0.45, "specular": 0.065,
                       "normal": 0.05}


def estimator_errors(card: Mapping[str, Any]) -> dict[str, float]:
    """Each map's expected error (standard deviation, map units) from a model card.

    The held-out RMSE of ``base_color``, ``roughness``, ``metallic`` and ``specular``; for the
    normal, the per-component slope error of the card's mean angular error ``θ̄`` (a 2-D Gaussian
    slope error of deviation ``s`` has mean angle ``s·√(π/2)``, for small angles). Maps the card lacks take
    :data:`FALLBACK_MAP_ERRORS`. Floored at 1e-3 (a card claiming no error is not believed).
    """
    held = card.get("heldout") or {}
    out = dict(FALLBACK_MAP_ERRORS)
    for name in ("base_color", "roughness", "metallic", "specular"):
        if isinstance(held.get(f"{name}_rmse"), (int, float)):
            out[name] = float(held[f"{name}_rmse"])
    if isinstance(held.get("normal_mean_deg"), (int, float)):
        out["normal"] = math.radians(float(held["normal_mean_deg"])) / math.sqrt(math.pi / 2)
    return {k: max(v, 1e-3) for k, v in out.items()}


def prior_maps_at(maps: Mapping[str, Tensor], size: int) -> dict[str, Tensor]:
    """:meth:`Prior.predict`'s maps ``(1, C, H, W)`` (or ``(C, H, W)``) as ``(C, size, size)``.

    Area-averaged (a downsampled metallic is the fraction of metal), normals renormalised.
    """
    out = {}
    for name, m in maps.items():
        m = (m if m.dim() == 4 else m[None]).float()
        if m.shape[-2:] != (size, size):
            m = F.interpolate(m, size=(size, size), mode="area" if size <= m.shape[-1] else "bilinear")
        if name == "normal":
            m = m / m.norm(dim=1, keepdim=True).clamp(min=1e-8)
        out[name] = m[0]
    return out


def _flat(m: Tensor) -> Tensor:
    """A ``(C, S, S)`` map as the recovery's per-pixel rows ``(S², C)`` (row-major pixels)."""
    return m.reshape(m.shape[0], -1).T


def _scalar_terms(theta: Tensor, maps: Mapping[str, Tensor], errors: Mapping[str, float]
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The five scalar map channels (base colour RGB, specular, roughness) of ``theta (P, 7)``:
    their values ``(P, 5)``, slopes ``d value / d logit`` ``(P, 5)`` (at least 1e-6), the
    network's values ``(P, 5)`` from ``maps`` and its errors ``(5,)`` from ``errors``."""
    s = torch.sigmoid(theta[:, :5])
    lo = torch.tensor([0.0] * 4 + [R_MIN], dtype=theta.dtype, device=theta.device)
    span = torch.tensor([1.0] * 4 + [R_MAX - R_MIN], dtype=theta.dtype, device=theta.device)
    want = torch.cat([_flat(maps[k]).to(theta) for k in ("base_color", "specular", "roughness")], -1)
    sigma = torch.tensor([errors["base_color"]] * 3 + [errors["specular"], errors["roughness"]],
                         dtype=theta.dtype, device=theta.device)
    return lo + span * s, (span * s * (1 - s)).clamp(min=1e-6), want, sigma


def prior_unary(theta: Tensor, maps: Mapping[str, Tensor], noise_var: float, errors: Mapping[str, float],
                class_weight: Tensor | float = 1.0, information: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The learned prior as a unary term ``(target, precision)`` ``(P, 7)`` of the recovery's unknowns.

    A Gaussian on each map, centred on the network's value ``m_p`` with the network's measured
    error ``σ_m`` (:func:`estimator_errors`), in the fit's cost scale (squared log residuals):
    the posterior's ``Σ r²/σ² + Σ (m − m_p)²/σ_m²`` times the residual noise variance ``σ²``.
    The maps are sigmoids of the unknowns (:mod:`~torchbrdf.recovery.params`), so the term is
    linearised at the current unknowns ``θ`` as Gauss–Newton linearises the data: with
    ``m = g(θ)``, precision ``σ² g'(θ)² / σ_m²`` and target ``θ − (g(θ) − m_p) / g'(θ)`` give the
    same gradient and curvature there. The normal's slopes ``(p, q)`` are unknowns themselves
    (``n ∝ (p, q, 1)``): precision ``σ² / σ_n²`` toward the network's slopes. Against the data's
    own precision (their marginal information) the term is negligible where the images
    determine a value and decides it where they are silent.

    Args:
        theta: the current unknowns ``(P, 7)``.
        maps: ``base_color (3, S, S)``, ``roughness``, ``specular`` ``(1, S, S)`` and
            ``normal (3, S, S)`` at the level's size (``S² = P``, :func:`prior_maps_at`).
        noise_var: ``σ²``, the fit's per-residual noise variance (> 0).
        errors: name -> ``σ_m`` (:func:`estimator_errors`).
        class_weight: ``(P, 1)`` or a float scaling the precision per pixel: the prior's
            probability of the hypothesis being fitted (its maps are conditional on the class).
        information: the data's marginal information ``(P, 7)`` on each unknown
            (:func:`~torchbrdf.recovery.lm.marginal_information`), or None. Given, each
            precision ``π`` is scaled by its share of the posterior's, ``π / (π + info)``: whole
            where the images are silent, vanishing (as ``π² / info``) where they determine the
            unknown. The network's errors are shared across a material (a bias on a material
            pulls all of its pixels alike), which a Gaussian of independent errors would let
            shift every measured pixel by the same amount; the data decide there.

    Returns:
        ``target (P, 7)`` and ``precision (P, 7)`` (>= 0), in ``theta``'s dtype and device.
    """
    prior_theta = encode({k: _flat(maps[k]).to(theta) for k in ("base_color", "specular", "roughness", "normal")})
    value, slope, want, sigma = _scalar_terms(theta, maps, errors)
    # (a logit far out in a saturated tail is moved at most 8 by one linearisation)
    target = torch.cat((theta[:, :5] - ((value - want) / slope).clamp(-8.0, 8.0), prior_theta[:, 5:7]), -1)
    precision = torch.cat(((slope / sigma) ** 2, torch.full_like(theta[:, 5:7], errors["normal"] ** -2.0)), -1)
    precision = float(noise_var) * precision * class_weight
    if information is not None:
        information = information.to(precision).clamp(min=0.0)
        precision = precision * precision / (precision + information).clamp(min=1e-30)
    return target, precision


def measured_metallic_error(dielectric_cost: Tensor, metal_cost: Tensor, noise_var: float, metallic: Tensor,
                            error: float) -> float:
    """The network's metallic error on this capture, measured where the data decide the class.

    The data's probability of metal per pixel is ``p = sigmoid((c_d − c_m) / 2σ²)`` (the
    likelihood ratio of the two fits' costs at the noise variance ``σ²``); each pixel's squared
    error ``(p − m_p)²`` counts with its decisiveness ``(2p − 1)²`` (1 where the data decide,
    0 where the two fits tie). The result is the larger of that RMS and the card's ``error``: a
    capture can show the network worse than on its training distribution (a material unlike
    it called metal), never better.

    Args:
        dielectric_cost, metal_cost: each pixel's data cost ``(P, 1)`` under each hypothesis.
        noise_var: ``σ²`` of one residual (> 0).
        metallic: the network's metallic ``(P, 1)``.
        error: the card's metallic error ``σ_m``.
    """
    diff = torch.nan_to_num(dielectric_cost - metal_cost, nan=0.0, posinf=1e30, neginf=-1e30)
    p = torch.sigmoid(diff.double() / (2.0 * max(float(noise_var), 1e-30)))
    w = (2 * p - 1) ** 2
    if float(w.sum()) <= 0:
        return float(error)
    mse = float((w * (p - metallic.to(p)) ** 2).sum() / w.sum())
    return max(float(error), math.sqrt(mse))


def measured_map_errors(theta: Tensor, maps: Mapping[str, Tensor], noise_var: float, errors: Mapping[str, float],
                        information: Tensor) -> dict[str, float]:
    """The network's error ``σ_m`` on each map of this capture, measured where the data decide the map.

    Each pixel's deviation of the fit's value from the network's, ``g(θ) − m_p``, counts with the
    data's share of the posterior, ``info / (info + π)`` (``π`` the prior's precision at the
    card's error, as in :func:`prior_unary`): 1 where the images determine the value, 0 where
    they are silent. Per map the result is the larger of that weighted RMS and the card's
    error: the network's errors are mostly a bias shared by a material's pixels, which its
    measured pixels show, and a capture can show it worse than its card, never better (as
    :func:`measured_metallic_error`). The normal keeps the card's error.

    Args:
        theta: the fit's unknowns ``(P, 7)``.
        maps: the network's maps at the level (``(C, S, S)``, ``S² = P``; :func:`prior_maps_at`).
        noise_var: ``σ²`` as in :func:`prior_unary`; errors: the card's (:func:`estimator_errors`).
        information: the data's marginal information ``(P, 7)`` on ``theta``.

    Returns:
        name -> ``σ_m``, the keys of ``errors``.
    """
    value, slope, want, sigma = _scalar_terms(theta, maps, errors)
    prec = float(noise_var) * (slope / sigma) ** 2
    info = torch.nan_to_num(information[:, :5].to(prec), nan=0.0).clamp(min=0.0)
    share = info / (info + prec).clamp(min=1e-30)
    sq = share * torch.nan_to_num(value - want, nan=0.0) ** 2
    out = dict(errors)
    for name, cols in (("base_color", slice(0, 3)), ("specular", slice(3, 4)), ("roughness", slice(4, 5))):
        weight = float(share[:, cols].sum())
        if weight > 0:
            out[name] = max(float(errors[name]), math.sqrt(float(sq[:, cols].sum()) / weight))
    return out


#: The network's metallic read as a probability is believed to odds of at most 999:1. It is a
#: sigmoid trained on an L1 map loss and a rendering loss, not a calibrated probability (L1 pulls
#: a binary map to its median, 0 or 1): beyond 1e-3 its tails say nothing it was taught.
METALLIC_ODDS_FLOOR = 1e-3


def class_prior_cost(metallic: Tensor, noise_var: float) -> tuple[Tensor, Tensor]:
    """The prior's share ``(P, 1)`` each of a dielectric's and a metal's cost: ``−2 σ² log q_h``.

    The network's metallic ``m_p`` as its probability of metal, ``q_1 = m_p``, ``q_0 = 1 − m_p``,
    each within [:data:`METALLIC_ODDS_FLOOR`, 1 − it]: ``−2 log q_h`` is the class's prior cost in
    noise variances (a data cost is ``−2 σ² log L``), so the prior moves the class test's
    evidence by ``2 logit(q)``, at most ``2 ln 999 ≈ 13.8`` noise variances of ``σ²``. (A Gaussian
    ``σ² (h − m_p)² / σ_m²`` on the binary class moves it by ``(2 m_p − 1) / σ_m²``, unbounded as
    the network's error ``σ_m`` is small: a network wrong on a few pixels with 0.93 outweighed
    data rejecting metal at 200 noise variances.)

    Args:
        metallic: the network's metallic ``(1, S, S)`` (or ``(P, 1)``).
        noise_var: ``σ²`` as in :func:`prior_unary` (> 0).
    """
    m = _flat(metallic) if metallic.dim() == 3 else metallic
    q = m.clamp(METALLIC_ODDS_FLOOR, 1.0 - METALLIC_ODDS_FLOOR)
    scale = -2.0 * float(noise_var)
    return scale * torch.log1p(-q), scale * torch.log(q)


def class_costs_with_prior(dielectric_cost: Tensor, metal_cost: Tensor, prior_cost: tuple[Tensor, Tensor],
                           sigma2: float, n_residuals: int, false_metal_rate: float) -> tuple[Tensor, Tensor]:
    """Each class's cost ``(P, 1)`` for the class test: the data's plus the prior's, the prior's vote
    for metal dropped where the data decide dielectric.

    The class test (:func:`~torchbrdf.recovery.classes.choose_class`) calls a pixel metal only
    on evidence noise alone gives at most at ``false_metal_rate``; a pixel whose data evidence
    for metal (:func:`~torchbrdf.recovery.classes.class_evidence`) is below ``−τ``
    (:func:`~torchbrdf.recovery.classes.evidence_threshold`) is dielectric whatever its
    neighbours. There the data reject metal beyond what noise explains, and a network's metal
    is a false metal the test's rate does not bound (a confidently wrong network outweighs any
    likelihood ratio where its σ² exceeds the test's), so the prior's metal-favouring difference is removed:
    its cost advantage for metal is set to none. Its vote for dielectric, the test's null
    hypothesis, always counts (it can only lower the false-metal rate).

    Args:
        dielectric_cost, metal_cost: the data costs ``(P, 1)`` of the two fits (``n_residuals``
            residuals each).
        prior_cost: the prior's ``(dielectric, metal)`` costs ``(P, 1)`` (:func:`class_prior_cost`).
        sigma2: the capture's noise variance of one residual (the class test's).
        false_metal_rate: the class test's rate, which sets ``τ``.
    """
    tau = evidence_threshold(N_PARAMS, false_metal_rate)
    decided_dielectric = class_evidence(dielectric_cost, metal_cost, sigma2, n_residuals) < -tau
    prior_diel, prior_metal = prior_cost
    prior_diel = torch.where(decided_dielectric & (prior_diel > prior_metal), prior_metal, prior_diel)
    return dielectric_cost + prior_diel, metal_cost + prior_metal


class LearnedPrior:
    """A :class:`Prior`'s maps for one capture, as the recovery uses them: a unary prior and class odds.

    Args:
        maps: the network's maps at the working size, ``(C, S, S)`` each (:func:`prior_maps_at`).
        errors: name -> the network's expected error ``σ_m`` (:func:`estimator_errors` of its card).
    """

    def __init__(self, maps: Mapping[str, Tensor], errors: Mapping[str, float]) -> None:
        self.maps = dict(maps)
        self.errors = dict(errors)
        self._levels: dict[int, dict[str, Tensor]] = {}

    def at(self, size: int) -> dict[str, Tensor]:
        """The maps ``(C, size, size)`` at a level of the recovery (area-averaged; cached)."""
        if size not in self._levels:
            self._levels[size] = prior_maps_at({k: v[None] for k, v in self.maps.items()}, size)
        return self._levels[size]

    def metallic(self, size: int) -> Tensor:
        """The network's metallic ``(size², 1)`` at ``size``."""
        return _flat(self.at(size)["metallic"])

    def unary(self, theta: Tensor, metal: Tensor, noise_var: float, information: Tensor | None = None,
              errors: Mapping[str, float] | None = None) -> tuple[Tensor, Tensor]:
        """:func:`prior_unary` at ``theta (P, 7)`` for the hypothesis ``metal (P, 1)`` (0 dielectric,
        1 metal, or fractional): the prior's maps weighted by its probability of that class, each
        precision by its share of the posterior's where the data's ``information (P, 7)`` is given;
        ``errors`` replaces the card's (e.g. :func:`measured_map_errors`)."""
        size = int(round(math.sqrt(theta.shape[0])))
        m = self.metallic(size).to(metal)
        agree = metal * m + (1 - metal) * (1 - m)
        return prior_unary(theta, self.at(size), noise_var, errors or self.errors, agree, information)
