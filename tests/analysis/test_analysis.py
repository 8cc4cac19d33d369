"""torchbrdf.analysis: albedo estimators, furnace tests, reciprocity, views; the explore report."""

import math

import re

import pytest
import torch

from torchbrdf.analysis import measures as A
from torchbrdf.analysis import slices
from torchbrdf.brdf.lambert import lambert
from torchbrdf.brdf.microfacet import microfacet
from torchbrdf.brdf.principled import principled

F64 = torch.float64
RGB = torch.tensor([0.8, 0.3, 0.1], dtype=F64)
ANGLES = torch.deg2rad(torch.tensor([0.0, 35.0, 70.0, 87.0], dtype=F64))


# --------------------------------------------------------------------------------------
# Directional albedo
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["quadrature", "mc"])
def test_lambert_albedo_is_its_colour(method):
    colour = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    est = A.directional_albedo(lambert, ANGLES, method, base_color=colour)
    assert est.value.shape == est.error.shape == (4, 3)
    err = (est.value - colour).abs()
    if method == "quadrature":
        # The only error is the kink where reflect(v, h) crosses the horizon; the estimate
        # (difference from the half-resolution rule) must bound it.
        assert (err <= est.error + 1e-9).all(), (err, est.error)
        assert err.max() < 5e-4
    else:
        # Default sampler here is the cosine/GGX mixture (roughness defaults to 0.5).
        assert (err <= 4 * est.error).all(), (err, est.error)
        # Pure cosine sampling: f cos / pdf = colour for every sample, zero variance.
        cos = A.directional_albedo(lambert, ANGLES, method, sampler="cosine", base_color=colour)
        assert torch.allclose(cos.value, colour.expand(4, 3), atol=1e-12)
        assert (cos.error < 1e-12).all()


def test_scalar_theta_gives_rgb():
    est = A.directional_albedo(lambert, 0.3, base_color=0.5)
    assert est.value.shape == (3,)
    assert torch.allclose(est.value, torch.full((3,), 0.5, dtype=F64), atol=1e-3)


CASES = [
    ("principled r=0.3", principled, dict(base_color=RGB, roughness=0.3)),
    ("principled r=0.1 metal", principled, dict(base_color=RGB, roughness=0.1, metallic=1.0)),
    ("principled clearcoat", principled, dict(base_color=RGB, roughness=0.5, clearcoat=1.0, clearcoat_gloss=0.5)),
    ("ggx dielectric", microfacet, dict(alpha=0.09, fresnel="dielectric")),
    ("beckmann schlick", microfacet, dict(alpha=0.2, distribution="beckmann", f0=0.04)),
]


@pytest.mark.parametrize("name,brdf,params", CASES, ids=[c[0] for c in CASES])
def test_quadrature_agrees_with_mc(name, brdf, params):
    q = A.directional_albedo(brdf, ANGLES, "quadrature", **params)
    mc = A.directional_albedo(brdf, ANGLES, "mc", samples=8192, seed=3, **params)
    # 4 standard errors of the MC estimate (a 1-in-16000 two-sided miss per value for a
    # Gaussian) plus the quadrature's own error estimate.
    tol = 4 * mc.error + q.error + 1e-9
    assert ((q.value - mc.value).abs() <= tol).all(), (q.value, mc.value, tol)
    # The deterministic rule is far tighter than MC at this cost.
    assert (q.error < mc.error + 1e-6).all()


def test_mc_samplers_agree():
    params = dict(alpha=0.2, fresnel="schlick", f0=0.5)
    th = torch.tensor([0.2, 1.2], dtype=F64)
    ref = A.directional_albedo(microfacet, th, **params)
    for sampler in ("cosine", "ggx", "mix"):
        mc = A.directional_albedo(microfacet, th, "mc", samples=16384, sampler=sampler, **params)
        assert ((mc.value - ref.value).abs() <= 4 * mc.error + ref.error).all(), sampler
    # GGX visible-normal sampling of a GGX lobe has far less variance than cosine sampling.
    cos = A.directional_albedo(microfacet, th, "mc", samples=4096, sampler="cosine", **params)
    ggx = A.directional_albedo(microfacet, th, "mc", samples=4096, sampler="ggx", **params)
    assert (ggx.error < 0.5 * cos.error).all()


def test_mc_with_clearcoat_sampling():
    # Burley's appendix B GTR1 sampler joins the mixture when a clearcoat is present.
    params = dict(base_color=RGB, roughness=0.5, clearcoat=1.0, clearcoat_gloss=0.9)
    th = torch.tensor([0.3, 1.3], dtype=F64)
    ref = A.directional_albedo(principled, th, **params)
    for sampler in ("mix", ("cosine", "gtr1")):
        mc = A.directional_albedo(principled, th, "mc", samples=8192, sampler=sampler, seed=5, **params)
        assert ((mc.value - ref.value).abs() <= 4 * mc.error + ref.error).all(), sampler
    with pytest.raises(ValueError, match="clearcoat"):
        A.directional_albedo(principled, 0.3, "mc", sampler="gtr1", base_color=RGB)


def test_bad_method_and_sampler():
    with pytest.raises(ValueError, match="method"):
        A.directional_albedo(lambert, 0.1, "simpson", base_color=0.5)
    with pytest.raises(ValueError, match="unknown density"):
        A.directional_albedo(lambert, 0.1, "mc", sampler="phong", base_color=0.5)
    with pytest.raises(ValueError, match="alpha_hint"):
        A.directional_albedo(lambda l, v, n, x=None, y=None: l[..., :1], 0.1, "mc", sampler="ggx")


@pytest.mark.parametrize("samples", [0, -3, (16, 0), (16,), (2.5, 96), "many", True])
def test_sample_counts_must_be_positive_ints(samples):
    for call in (
        lambda: A.directional_albedo(lambert, 0.1, samples=samples, base_color=0.5),
        lambda: A.directional_albedo(lambert, 0.1, "mc", samples=samples, base_color=0.5),
        lambda: A.weak_white_furnace("ggx", samples=samples),
        lambda: A.reciprocity_error(lambert, samples, base_color=0.5),
    ):
        with pytest.raises(ValueError, match="samples: expected a"):
            call()


def test_an_error_estimate_needs_a_rule_it_can_halve():
    """One θ node, four φ nodes or one MC sample would report no error (or NaN): refused."""
    for samples in (1, (1, 64), (16, 4)):
        with pytest.raises(ValueError, match=r"samples: expected an int or a pair of ints, at least \(2, 8\)"):
            A.directional_albedo(principled, 0.3, samples=samples, base_color=0.5, roughness=0.5)
        with pytest.raises(ValueError, match=r"at least \(2, 8\)"):
            A.weak_white_furnace("ggx", samples=samples if isinstance(samples, tuple) else (samples, 128))
    with pytest.raises(ValueError, match=r"samples: expected an int or a pair of ints, at least \(2, 1\)"):
        A.directional_albedo(lambert, 0.1, "mc", samples=1, base_color=0.5)
    mc_pair = A.directional_albedo(lambert, 0.1, "mc", samples=(64, 3), base_color=0.5)  # the first, as before
    torch.testing.assert_close(mc_pair.value, A.directional_albedo(lambert, 0.1, "mc", samples=64, base_color=0.5).value)
    with pytest.raises(ValueError, match="samples: expected an int of at least 1"):
        A.reciprocity_error(lambert, (4, 4), base_color=0.5)
    est = A.directional_albedo(principled, 0.3, samples=(2, 8), base_color=0.5, roughness=0.5)
    assert (est.error > 0).all()


# --------------------------------------------------------------------------------------
# Furnace tests and reciprocity
# --------------------------------------------------------------------------------------


def test_white_furnace():
    res = A.white_furnace(lambert, base_color=1.0)
    assert res.passed and abs(res.max_albedo - 1.0) < 1e-3
    # Microfacet with F = 1 and height-correlated Smith G loses energy (no multiple scattering).
    res = A.white_furnace(microfacet, alpha=0.5, fresnel="none")
    assert res.passed and res.max_albedo < 1.0
    # A BRDF reflecting 1.5x what it receives fails.
    res = A.white_furnace(lambert, base_color=1.5)
    assert not res.passed and res.max_albedo > 1.4


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_weak_white_furnace_holds(dist, alpha):
    est = A.weak_white_furnace(dist, alpha=alpha)
    assert est.value.shape == (6,)
    assert ((est.value - 1).abs() < 1e-3).all(), est.value


def test_weak_white_furnace_fails_for_mismatched_pair():
    # GGX's D with Beckmann's G1: the visible-normal projection no longer matches.
    est = A.weak_white_furnace("ggx", "beckmann", alpha=0.5)
    assert (est.value - 1).abs().max() > 0.05
    est = A.weak_white_furnace("beckmann", "ggx", alpha=0.5)
    assert (est.value - 1).abs().max() > 0.05


def test_reciprocity():
    res = A.reciprocity_error(
        principled,
        1024,
        base_color=RGB,
        roughness=0.3,
        metallic=0.3,
        subsurface=0.5,
        sheen=0.7,
        clearcoat=1.0,
        specular_tint=0.4,
    )
    assert res.max_rel < 1e-10
    # Anisotropic principled with the frame supplied by the analysis.
    assert A.reciprocity_error(principled, 512, base_color=RGB, roughness=0.4, anisotropic=0.8).max_rel < 1e-10

    def lopsided(l, v, n, x=None, y=None):
        return (1 + l[..., 2:3]).expand(*l.shape[:-1], 3) / math.pi

    assert A.reciprocity_error(lopsided, 256).max_rel > 0.1


# --------------------------------------------------------------------------------------
# Views
# --------------------------------------------------------------------------------------


def test_image_slice_and_curves():
    params = dict(base_color=RGB, roughness=0.4)
    img = A.image_slice(principled, 16, **params)
    assert img.shape == (3, 16, 16) and img.dtype == F64
    ref = slices.image_slice(principled, 16, **params)
    assert torch.equal(img, ref)
    # Grey BRDFs come out RGB.
    assert A.image_slice(microfacet, 8, alpha=0.3, fresnel="none").shape == (3, 8, 8)

    th, f = A.retro_reflection_curve(principled, **params)
    assert f.shape == (th.numel(), 3)
    # θd = 0: l = v = h at angle θh from the normal.
    k = 40
    d = torch.stack((torch.sin(th[k]), torch.zeros(()), torch.cos(th[k]))).to(F64)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    assert torch.allclose(f[k], principled(d, d, n, **params), rtol=1e-10)

    th, f = A.specular_peak_curve(principled, **params)
    assert f[0, 0] > f[-1, 0]  # peak at θh = 0


def test_polar_lobe_peaks_at_mirror():
    ti = math.radians(40.0)
    to, val = A.polar_lobe(microfacet, ti, alpha=0.05, fresnel="schlick")
    assert val.shape == (to.numel(), 3)
    assert abs(math.degrees(float(to[val[:, 0].argmax()])) - 40.0) < 1.0
    assert (val[to < 0] < val.max() * 1e-2).all()


def test_render_sphere_lambert():
    img, mask = A.render_sphere(lambert, 33, base_color=0.8, return_mask=True)
    assert img.shape == (3, 33, 33) and mask.shape == (33, 33)
    assert (img[:, ~mask] == 0).all()
    # Centre pixel: normal toward the camera, radiance = (0.8 / π) · π · n·l.
    ld = torch.nn.functional.normalize(torch.tensor(A.DEFAULT_SPHERE_LIGHT, dtype=F64), dim=0)
    assert abs(float(img[0, 16, 16]) - 0.8 * float(ld[2])) < 0.02
    # The local fallback (used only without the shader modules) agrees at the centre.
    fb, fb_mask = A._render_sphere_fallback(A.bind_brdf(lambert, base_color=0.8), 33, ld, math.pi)
    assert fb_mask[16, 16] and abs(float(fb[0, 16, 16]) - 0.8 * float(ld[2])) < 0.02
    # String parameters reach the BRDF (bound), numbers go through the g-buffer.
    spec = A.render_sphere(microfacet, 17, alpha=0.2, fresnel="dielectric")
    assert spec.shape == (3, 17, 17) and spec.max() > 0


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------


def test_explore_refuses_a_parameter_the_model_does_not_take(capsys):
    """A misspelt key is one line naming the spec, the key and the model's parameters, not a traceback
    when the report is half drawn (and lambert, which swallows unknown keywords, no longer ignores it)."""
    from torchbrdf.analysis import explore

    with pytest.raises(ValueError, match=r"principled has no parameter 'rough'; it takes base_color.*roughness"):
        explore.parse_spec("principled:rough=0.2")
    with pytest.raises(ValueError, match=r"lambert has no parameter 'roughness'; it takes base_color \(and label\)"):
        explore.parse_spec("lambert:roughness=0.2")
    assert explore.parse_spec("microfacet:alpha=0.1,diffuse=0.5/0.5/0.5,label=x").label == "x"
    with pytest.raises(SystemExit) as e:
        explore.main(["--out", "unused", "--brdf", "principled:rough=0.2"])
    assert e.value.code == 2 and "no parameter 'rough'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        explore.main(["--help"])
    shown = capsys.readouterr().out  # the spec syntax and each model's keys are in --help
    assert "r/g/b" in shown and "microfacet: alpha," in shown and "lambert: base_color;" in shown


@pytest.mark.parametrize("spec, named", [
    ("merl:missing.binary", r"--brdf 'merl:missing.binary': MERL file 'missing.binary' not found"),
    ("fit:missing.json", r"--brdf 'fit:missing.json': .*missing.json"),
    ("fit:{tmp}/other.json", r"--brdf 'fit:.*other.json': .*other.json.* 'params'"),
    ("principled:roughness=rough", r"--brdf 'principled:roughness=rough': roughness: expected a torch.Tensor or float"),
])
def test_explore_refuses_a_spec_that_does_not_load_before_writing(tmp_path, monkeypatch, capsys, spec, named):
    """A missing MERL or params file, or a value the model refuses, is one line naming the spec, with
    the output folder untouched (it was a traceback after --out was created)."""
    from torchbrdf.analysis import explore

    monkeypatch.chdir(tmp_path)
    (tmp_path / "other.json").write_text('{"loss": 1}')
    with pytest.raises(SystemExit) as e:
        explore.main(["--out", "report", "--quick", "--brdf", spec.format(tmp=tmp_path)])
    assert e.value.code == 2 and re.search(named, capsys.readouterr().err)
    assert not (tmp_path / "report").exists()


def test_explore_refuses_an_out_that_is_a_file(tmp_path, capsys):
    from torchbrdf.analysis import explore

    (tmp_path / "report").write_text("mine")
    with pytest.raises(SystemExit) as e:
        explore.main(["--out", str(tmp_path / "report"), "--quick", "--brdf", "lambert"])
    assert e.value.code == 2 and "is a file, not a folder" in capsys.readouterr().err
    assert (tmp_path / "report").read_text() == "mine"


def test_explore_lobes_key_selects_principled_lobes():
    """``lobes`` is one of the keys --help lists for principled: its value names lobes (not a
    word for principled to iterate letter by letter)."""
    from torchbrdf.analysis import explore
    from torchbrdf.brdf.principled import principled

    spec = explore.parse_spec("principled:lobes=diffuse/specular,roughness=0.3")
    assert spec.params["lobes"] == ("diffuse", "specular")
    assert spec.label == "principled lobes=diffuse/specular roughness=0.3 base_color=0.8/0.8/0.8"
    g = torch.Generator().manual_seed(0)
    l, v = (torch.nn.functional.normalize(torch.rand(8, 3, generator=g, dtype=torch.float64) + 0.5, dim=-1)
            for _ in range(2))
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(8, 3)
    want = principled(l, v, n, base_color=0.8, roughness=0.3, lobes=("diffuse", "specular"), clearcoat=1.0)
    got = explore.parse_spec("principled:lobes=diffuse/specular,roughness=0.3,clearcoat=1").brdf()(l, v, n)
    torch.testing.assert_close(got, want)
    assert not torch.allclose(got, principled(l, v, n, base_color=0.8, roughness=0.3, clearcoat=1.0))
    only = explore.parse_spec("principled:lobes=diffuse").brdf()(l, v, n)
    torch.testing.assert_close(only, principled(l, v, n, base_color=0.8, lobes=("diffuse",)))


def test_explore_writes_report(tmp_path):
    from torchbrdf.analysis import explore

    spec = explore.parse_spec("microfacet:alpha=0.09,fresnel=dielectric,diffuse=0.5/0.5/0.5,label=ggx")
    assert spec.label == "ggx" and spec.params["fresnel"] == "dielectric"
    assert torch.equal(spec.params["diffuse"], torch.tensor([0.5, 0.5, 0.5], dtype=F64))
    with pytest.raises(ValueError, match="unknown model"):
        explore.parse_spec("phong:n=10")
    for texts in explore.PRESETS.values():  # every preset parses and builds
        for text in texts:
            assert callable(explore.parse_spec(text).brdf())

    out = tmp_path / "report"
    rc = explore.main(
        ["--out", str(out), "--quick", "--brdf", "principled:roughness=0.3,base_color=0.8/0.2/0.1",
         "--brdf", "microfacet:alpha=0.09,fresnel=dielectric"]
    )
    assert rc == 0
    page = (out / "index.html").read_text()
    for name in ("slices.png", "spheres.png", "albedo.png", "retro.png", "peak.png", "polar.png"):
        assert f'src="{name}"' in page
        assert (out / name).stat().st_size > 1000
    assert "principled roughness=0.3" in page
