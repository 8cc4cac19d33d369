"""Agreement with Mitsuba 3's ``principled`` BSDF where the two models coincide.

Mitsuba's ``principled`` (the 2015 Disney BSDF) equals Burley's 2012 model only for
metallic = 1 and clearcoat = 0 (no dielectric, sheen or transmission lobes): then both are the
anisotropic GGX lobe with Schlick Fresnel toward ``base_color`` and the separable anisotropic
Smith G. Mitsuba's ``eval`` includes the ``cos θ_o`` foreshortening, ours does not.
Skipped unless the optional ``mitsuba`` extra (``pip install -e ".[mitsuba]"``) is installed.
"""

import numpy as np
import pytest
import torch

import torchbrdf

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def variant():
    try:
        mi.set_variant("llvm_ad_rgb")
    except Exception as exc:  # noqa: BLE001 - a missing LLVM or variant means "not available"
        pytest.skip(f"Mitsuba llvm_ad_rgb variant unavailable: {exc}")
    return "llvm_ad_rgb"


def _directions(rng, count, min_cos=0.1):
    def hemi():
        d = rng.normal(size=(count, 3))
        d[:, 2] = np.abs(d[:, 2])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d

    wi, wo = hemi(), hemi()
    keep = (wi[:, 2] > min_cos) & (wo[:, 2] > min_cos)
    return wi[keep], wo[keep]


@pytest.mark.parametrize("roughness, anisotropic", [(0.3, 0.0), (0.6, 0.0), (0.4, 0.5), (0.8, 0.9)])
def test_metallic_lobe_matches_mitsuba(variant, roughness, anisotropic):
    rng = np.random.default_rng(int(roughness * 100 + anisotropic * 10))
    wi, wo = _directions(rng, 4096)
    base = [0.9, 0.6, 0.3]
    bsdf = mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": base},
                         "metallic": 1.0, "roughness": roughness, "anisotropic": anisotropic,
                         "clearcoat": 0.0, "spec_trans": 0.0, "sheen": 0.0})
    si = dr.zeros(mi.SurfaceInteraction3f, wi.shape[0])
    si.wi = mi.Vector3f(wi.T.astype(np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wo.T.astype(np.float32)))
    theirs = np.asarray(value, dtype=np.float64)
    theirs = theirs.T if theirs.shape[0] == 3 else theirs  # Color3f arrives channel-first

    # ours, in float64 on the float32-rounded directions Mitsuba saw; local frame x, y, n
    t = lambda a: torch.as_tensor(a.astype(np.float32).astype(np.float64))  # noqa: E731
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(wi.shape[0], 3)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(wi.shape[0], 3)
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(wi.shape[0], 3)
    l, v = t(wo), t(wi)
    ours = torchbrdf.principled(l, v, n, x, y, base_color=torch.tensor(base, dtype=torch.float64),
                                metallic=1.0, roughness=roughness, anisotropic=anisotropic, clearcoat=0.0)
    ours = (ours * l[:, 2:3]).numpy()
    rel = np.abs(ours - theirs) / np.maximum(np.abs(ours), 1e-12)
    assert np.median(rel) < 1e-5
    assert np.quantile(rel, 0.999) < 1e-3
