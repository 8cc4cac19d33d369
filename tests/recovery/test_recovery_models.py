"""The recovery loop also fits with the SVBRDF-capture GGX model."""

import json

import pytest
import torch

from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.recovery.svbrdf import main


def test_recover_with_svbrdf_ggx_model(tmp_path, capsys):
    generate_capture(tmp_path / "cap", recipe="painted", seed=3, size=24, lights=8, noise=0.01)
    out = tmp_path / "out"
    assert main(["--capture", str(tmp_path / "cap"), "--out", str(out), "--model", "svbrdf_ggx",
                 "--iters", "10", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["model"] == "svbrdf_ggx" and report["iterations"] == 10
    for name in ["base_color.exr", "roughness.exr", "metallic.exr", "specular.exr", "normal.exr"]:
        assert (out / name).exists(), name
    # The fit reproduces a held-out captured light far above the noise-free-guess level.
    assert report["held_out_light"]["psnr"] > 28


def test_the_ggx_model_is_scored_with_its_own_renderer(tmp_path):
    """The report's PSNRs compare the capture with the GGX model's rendering of the maps
    (albedos mapped by hand here), not the principled model's."""
    from torchbrdf.brdf.svbrdf_ggx import svbrdf_ggx
    from torchbrdf.capture import load_capture
    from torchbrdf.capture.synthetic import render_capture
    from torchbrdf.recovery import RecoveryConfig, psnr, recover

    generate_capture(tmp_path / "cap", recipe="metal_inlay", seed=2, size=24, lights=8, noise=0.01)
    cap = load_capture(tmp_path / "cap")
    res = recover(cap, RecoveryConfig(model="svbrdf_ggx", iters=6, threads=1), progress=False)

    def ggx(l, v, n, x=None, y=None, base_color=None, metallic=None, specular=None, roughness=None):
        return svbrdf_ggx(l, v, n, diffuse_albedo=base_color * (1 - metallic),
                          specular_albedo=0.08 * specular * (1 - metallic) + base_color * metallic, roughness=roughness)

    maps = {k: res.maps[k] for k in ("base_color", "roughness", "metallic", "specular", "normal")}
    with torch.no_grad():
        pred = render_capture(maps, cap, cap.camera_position, brdf=ggx)
        principled_pred = render_capture(maps, cap, cap.camera_position, backend="compact")
    for k, name in enumerate(cap.files):
        assert res.report["per_image_psnr"][name] == pytest.approx(psnr(pred[k], cap.images[k]), abs=1e-3)
    # not vacuous: the principled renderer's scores of the same maps are other numbers
    assert max(abs(res.report["per_image_psnr"][name] - psnr(principled_pred[k], cap.images[k]))
               for k, name in enumerate(cap.files)) > 0.1
