"""MERL round trip of a known principled material, rendering it, and fitting it back.

One MERL file is written from a principled material with a partial metallic (so base
colour, roughness and metallic all matter: the diffuse colour is ``base (1 - metallic)``,
the specular colour ``lerp(0.08 specular, base, metallic)``), then read, evaluated,
rendered through the shader and fitted with ``training.fit_measured``.
"""

import json

import pytest
import torch

from torchbrdf import analysis as A
from torchbrdf.brdf.measured import MERLBRDF, read_merl, write_merl
from torchbrdf.brdf.principled import principled
from torchbrdf.recovery import fit_measured as FM

F64 = torch.float64
TRUTH = {"base_color": [0.7, 0.35, 0.15], "roughness": 0.3, "metallic": 0.4}


def truth_params():
    return {
        "base_color": torch.tensor(TRUTH["base_color"], dtype=F64),
        "roughness": TRUTH["roughness"],
        "metallic": TRUTH["metallic"],
    }


@pytest.fixture(scope="module")
def merl_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("merl") / "known.binary"
    write_merl(path, principled, **truth_params())
    return path


def _hemisphere(gen, count):
    d = torch.nn.functional.normalize(torch.randn(count, 3, generator=gen, dtype=F64), dim=-1)
    return torch.cat((d[:, :2], d[:, 2:].abs()), -1)


def test_round_trip_and_evaluation(merl_file, tmp_path):
    brdf = MERLBRDF.from_file(merl_file)
    # Written bytes read back exactly, and writing the module again reproduces the file.
    copy = tmp_path / "copy.binary"
    write_merl(copy, brdf)
    assert copy.read_bytes() == merl_file.read_bytes()
    assert torch.equal(read_merl(copy), brdf.table)

    gen = torch.Generator().manual_seed(1)
    l, v = _hemisphere(gen, 20000), _hemisphere(gen, 20000)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(l)
    got, want = brdf(l, v, n), principled(l, v, n, **truth_params())
    # Trilinear interpolation error, measured for this material: cosine-weighted relative
    # RMS 0.4-1 % per channel, at most 1 % away from grazing (n·l, n·v > 0.2). The bounds
    # below leave 2-3x headroom; a coordinate or scale bug gives errors of order 1.
    c = l[:, 2:3] * v[:, 2:3]
    rel_rms = ((c * (got - want)) ** 2).sum(0).sqrt() / ((c * want) ** 2).sum(0).sqrt()
    assert (rel_rms < 0.02).all(), rel_rms
    inner = (l[:, 2] > 0.2) & (v[:, 2] > 0.2)
    assert ((got - want).abs() / want)[inner].max() < 0.03


def test_measured_renders_and_analyses_like_its_source(merl_file):
    brdf = MERLBRDF.from_file(merl_file)
    img, mask = A.render_sphere(brdf, 40, return_mask=True)
    ref = A.render_sphere(principled, 40, **truth_params())
    assert img.shape == (3, 40, 40) and mask.any()
    assert float((img - ref).abs().sum() / ref.abs().sum()) < 0.01
    th = torch.tensor([0.3, 1.2], dtype=F64)
    a = A.directional_albedo(brdf, th).value
    b = A.directional_albedo(principled, th, **truth_params()).value
    assert ((a - b).abs() / b).max() < 0.005
    # The analysis views accept the measured module directly.
    assert A.image_slice(brdf, 16).shape == (3, 16, 16)
    assert A.reciprocity_error(brdf, 256).max_rel < 0.05  # symmetric up to interpolation


def test_fit_recovers_known_parameters(merl_file, tmp_path):
    # The samples are grid nodes, where the table holds the model's exact values, so the loss
    # is exactly 0 at the true parameters and the recovery error is the optimiser's alone
    # (about 1e-5 at this budget; 1e-2 after 60 Adam steps without L-BFGS). The tolerances
    # are those of a useful fit — 0.02 in base colour (~1/50 of the range, below a visible
    # colour shift), 0.02 in roughness (α within 0.012 at 0.3), 0.03 in metallic — and
    # still fail for any wrong local minimum (e.g. the metallic = 0 basin).
    out = tmp_path / "fit"
    rc = FM.main(["--merl", str(merl_file), "--out", str(out), "--samples", "3000", "--iters", "30", "--lbfgs", "60"])
    assert rc == 0
    report = json.loads((out / "params.json").read_text())
    p = report["params"]
    assert max(abs(a - b) for a, b in zip(p["base_color"], TRUTH["base_color"])) < 0.02, p
    assert abs(p["roughness"] - TRUTH["roughness"]) < 0.02, p
    assert abs(p["metallic"] - TRUTH["metallic"]) < 0.03, p
    assert len(report["errors"]["rel_rmse"]) == 3 and max(report["errors"]["rel_rmse"]) < 0.01
    assert (out / "slices.png").stat().st_size > 1000
    assert (out / "spheres.png").stat().st_size > 1000

    # The report command puts the fitted model beside the measured data.
    from torchbrdf.analysis import explore

    report_dir = tmp_path / "report"
    assert explore.main(["--out", str(report_dir), "--quick", "--brdf", f"merl:{merl_file}", "--brdf", f"fit:{out / 'params.json'}"]) == 0
    page = (report_dir / "index.html").read_text()
    assert "known" in page and "fit fit" in page
    summary = json.loads((report_dir / "summary.json").read_text())
    measured, fitted = (s["albedo_luminance_0_60_85"] for s in summary)
    assert all(abs(a - b) < 0.01 for a, b in zip(measured[:2], fitted[:2]))


def test_two_lobe_model_and_loss():
    # The second lobe starts (nearly) off and adds to the principled value.
    model = FM.PrincipledFit(two_lobes=True, init={"base_color": 0.5, "spec2_f0": 0.001, "spec2_f90": 0.001})
    assert set(model.values()) >= {"roughness2", "spec2_f0", "spec2_f90"}
    gen = torch.Generator().manual_seed(0)
    l, v = _hemisphere(gen, 64), _hemisphere(gen, 64)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(l)
    single = FM.PrincipledFit(init={"base_color": 0.5})
    assert torch.allclose(model(l, v, n), single(l, v, n), rtol=0.05)
    # Gradients reach every fitted variable.
    s = FM.MeasuredSamples(l, v, single(l, v, n).detach() * 1.3)
    FM._loss_terms(model, s, 1e-3).mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    with pytest.raises(ValueError, match="cannot fit"):
        FM.PrincipledFit(names=("base_color", "shininess"))


def test_demo_fits_a_tabulated_known_material(tmp_path, capsys):
    # --demo needs no data: it writes a MERL file of DEMO_MATERIAL into --out and fits it; the
    # fit's error against that truth is reported (tolerances as in the test above).
    out = tmp_path / "demo"
    assert FM.main(["--demo", "--out", str(out), "--samples", "3000", "--iters", "30", "--lbfgs", "60",
                    "--no-figures"]) == 0
    assert (out / FM.DEMO_FILE).is_file() and MERLBRDF.from_file(out / FM.DEMO_FILE).table.shape[0] == 3
    report = json.loads((out / "params.json").read_text())
    assert report["truth"]["roughness"] == FM.DEMO_MATERIAL["roughness"]
    err = report["truth_error"]
    assert err["base_color"] < 0.02 and err["roughness"] < 0.02 and err["metallic"] < 0.03, err
    # --help says where measured data come from; a source is required.
    with pytest.raises(SystemExit):
        FM.main(["--help"])
    assert "MERL BRDF database" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        FM.main(["--out", str(out)])
    assert "one of the arguments --merl --demo is required" in capsys.readouterr().err


@pytest.mark.parametrize("args, says", [
    (["--merl", "{tmp}/missing.binary"], "--merl: MERL file '{tmp}/missing.binary' not found"),
    (["--merl", "{tmp}"], "is a directory, not a file"),
    (["--merl", "{tmp}/short.binary"], "too short for the 12-byte header"),
    (["--demo", "--extra", "shininess"], "--extra 'shininess': expected distinct names among clearcoat,"),
    (["--demo", "--samples", "0"], "--samples must be at least 1, got 0"),
    (["--demo", "--iters", "-1"], "--iters must be at least 0, got -1"),
])
def test_bad_input_is_one_line_naming_the_option(tmp_path, capsys, args, says):
    """A missing or broken MERL file or an impossible option: exit status 2 and one line, no traceback,
    and nothing written (the options are checked before --demo writes its file)."""
    (tmp_path / "short.binary").write_bytes(b"garbage\n")
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        FM.main([a.format(tmp=tmp_path) for a in args] + ["--out", str(out)])
    assert e.value.code == 2
    assert says.format(tmp=tmp_path) in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("inside", ["", "sub"])
def test_an_out_that_is_a_file_is_one_line_and_left_alone(tmp_path, capsys, inside):
    # this was mkdir's FileExistsError/NotADirectoryError traceback, after --demo had fitted
    taken = tmp_path / "taken"
    taken.write_text("mine")
    with pytest.raises(SystemExit) as e:
        FM.main(["--demo", "--samples", "200", "--iters", "0", "--lbfgs", "0", "--no-figures",
                 "--out", str(taken / inside if inside else taken)])
    assert e.value.code == 2 and f"--out {taken / inside if inside else taken}: {taken} is a file, not a folder" in (
        capsys.readouterr().err)
    assert taken.read_text() == "mine"


@pytest.mark.parametrize("name", ["roughness2", "spec2_f0"])
def test_extra_refuses_the_second_lobes_parameters(tmp_path, capsys, name):
    """--two-lobes adds them; fitted through --extra alone they would not enter the model and
    params.json would report a value the data never constrained."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        FM.main(["--demo", "--extra", name, "--samples", "200", "--iters", "0", "--lbfgs", "0",
                 "--no-figures", "--out", str(out)])
    assert e.value.code == 2
    assert f"--extra {name!r}: expected distinct names among clearcoat," in capsys.readouterr().err
    assert not out.exists()
