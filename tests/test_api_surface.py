"""The public names fixed by the contract stay importable with their argument order."""

import inspect

import torchbrdf


def test_contract_names_and_signature():
    ps = list(inspect.signature(torchbrdf.principled).parameters)
    assert ps[:5] == ["l", "v", "n", "x", "y"]
    for name in ["base_color", "metallic", "subsurface", "specular", "roughness", "specular_tint",
                 "anisotropic", "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss"]:
        assert name in ps
    defaults = {k: p.default for k, p in inspect.signature(torchbrdf.principled).parameters.items()}
    assert defaults["specular"] == 0.5 and defaults["sheen_tint"] == 0.5 and defaults["clearcoat_gloss"] == 1.0
    assert issubclass(torchbrdf.PrincipledBRDF, torchbrdf.torch.nn.Module) if hasattr(torchbrdf, "torch") else True


def test_all_names_exist():
    for name in torchbrdf.__all__:
        assert hasattr(torchbrdf, name), name
