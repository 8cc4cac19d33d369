"""torchbrdf.losses: the rendering loss against an independent float64 reference of the published
definition (Deschaintre et al. 2018), its configuration sampler, compile/Triton paths, and map_loss."""

import importlib
import math

import numpy as np
import pytest
import torch

import torchbrdf
from torchbrdf import losses as L

from tests.reference import principled_ref


def _maps(layout, b=2, size=8, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    parts = []
    for name, c in L.LAYOUTS[layout].items():
        if name == "normal":
            xy = 0.4 * (torch.rand(b, 2, size, size, generator=g) - 0.5)
            parts.append(torch.cat((xy, torch.ones(b, 1, size, size)), 1))
        else:
            parts.append(0.05 + 0.9 * torch.rand(b, c, size, size, generator=g))
    return torch.cat(parts, 1).to(dtype)


# ---- the independent float64 reference -------------------------------------------------------

def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _ggx_ref(l, v, n, diffuse, specular, roughness):
    """Deschaintre et al.'s renderer: GGX, Smith-Schlick G (k = alpha / 2), spherical-Gaussian Fresnel."""
    h = _unit(l + v)
    nl, nv, nh, vh = (np.sum(a * b, -1, keepdims=True) for a, b in ((n, l), (n, v), (n, h), (v, h)))
    alpha = np.maximum(roughness, 1e-3) ** 2
    d = alpha ** 2 / (np.pi * (nh ** 2 * (alpha ** 2 - 1) + 1) ** 2)
    k = alpha / 2
    g = 1.0 / ((nl * (1 - k) + k) * (nv * (1 - k) + k))
    f = specular + (1 - specular) * 2.0 ** ((-5.55473 * vh - 6.98316) * vh)
    val = diffuse * (1 - specular) / np.pi + d * g * f / 4
    return np.where((nl > 0) & (nv > 0), val, 0.0)


def _reference_renderings(maps, light, view, positional, layout):
    """``(B, N, H, W, 3)`` renderings: pi * f * max(n.l, 0) / d^2 with per-pixel geometry."""
    maps = maps.double().numpy()
    light, view, positional = light.double().numpy(), view.double().numpy(), positional.double().numpy()
    b, _, h, w = maps.shape
    named, at = {}, 0
    for name, c in L.LAYOUTS[layout].items():
        named[name] = np.moveaxis(maps[:, at:at + c], 1, -1)  # (B, H, W, c)
        at += c
    xs = -1 + (np.arange(w) + 0.5) * 2 / w
    ys = 1 - (np.arange(h) + 0.5) * 2 / h
    p = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], 0.0 * xs[None, :]), -1)  # (H, W, 3)
    out = np.zeros((b, light.shape[1], h, w, 3))
    for i in range(b):
        n = _unit(named["normal"][i]).reshape(-1, 3)
        for k in range(light.shape[1]):
            to_l = light[i, k] - positional[k] * p.reshape(-1, 3)
            to_v = view[i, k] - positional[k] * p.reshape(-1, 3)
            d2 = np.sum(to_l ** 2, -1, keepdims=True)
            l, v = _unit(to_l), _unit(to_v)
            if layout == "principled":
                x = _unit(np.cross(n, [0.3, 0.9, 0.1]))
                f = principled_ref(l, v, n, x, np.cross(n, x),
                                   **{m: named[m][i].reshape(-1, named[m].shape[-1])
                                      for m in ("base_color", "roughness", "metallic", "specular")})
            else:
                f = _ggx_ref(l, v, n, *(named[m][i].reshape(-1, named[m].shape[-1])
                                        for m in ("diffuse", "specular", "roughness")))
            nl = np.maximum(np.sum(n * l, -1, keepdims=True), 0.0)
            out[i, k] = (np.pi * f * nl / d2).reshape(h, w, 3)
    return out


def _reference_loss(pred, target, configs, layout):
    rp = _reference_renderings(pred, *configs, layout)
    rt = _reference_renderings(target, *configs, layout)
    return np.mean(np.abs(np.log(rp + 0.01) - np.log(rt + 0.01)))


@pytest.mark.parametrize("layout", ["principled", "svbrdf_ggx"])
def test_rendering_loss_matches_the_float64_reference(layout):
    pred, target = _maps(layout, seed=1), _maps(layout, seed=2)
    configs = L.random_configurations(2, generator=torch.Generator().manual_seed(3))
    ref = _reference_renderings(target, *configs, layout)
    got = L.render_configurations(target, configs, layout).permute(0, 1, 3, 4, 2).double().numpy()
    assert np.abs(got - ref).max() <= 2e-5 * np.abs(ref).max()
    loss = L.rendering_loss(pred, target, layout=layout, configs=configs)
    assert loss.dtype == torch.float32
    assert float(loss) == pytest.approx(_reference_loss(pred, target, configs, layout), rel=2e-5)
    # The generator path draws the same configurations as random_configurations with that seed.
    seeded = L.rendering_loss(pred, target, layout=layout, generator=torch.Generator().manual_seed(3))
    assert float(seeded) == float(loss)


def test_rendering_loss_float64_inputs_match_tightly():
    pred, target = _maps("principled", seed=4, dtype=torch.float64), _maps("principled", seed=5, dtype=torch.float64)
    configs = L.random_configurations(2, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    loss = L.rendering_loss(pred, target, configs=configs)
    assert loss.dtype == torch.float64
    assert float(loss) == pytest.approx(_reference_loss(pred, target, configs, "principled"), rel=1e-10)


def test_configurations_follow_the_published_scheme():
    c = L.random_configurations(4000, n_diffuse=3, n_specular=6, generator=torch.Generator().manual_seed(0),
                                dtype=torch.float64)
    assert c.light.shape == c.view.shape == (4000, 9, 3)
    assert c.positional.tolist() == [0.0] * 3 + [1.0] * 6
    d_light, d_view = c.light[:, :3], c.view[:, :3]
    for d in (d_light, d_view):
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(4000, 3, dtype=torch.float64))
        sin2 = 1 - d[..., 2] ** 2  # cosine-weighted: sin^2(theta) is uniform on [0.001, 0.9]
        assert sin2.min() >= 0.001 - 1e-12 and sin2.max() <= 0.9 + 1e-12
        assert float(sin2.mean()) == pytest.approx(0.4505, abs=0.01)
        assert float(sin2.std()) == pytest.approx(0.899 / math.sqrt(12), abs=0.01)
        azimuth = torch.atan2(d[..., 1], d[..., 0])
        assert float(azimuth.cos().mean()) == pytest.approx(0.0, abs=0.03)
    # Light and view directions of the diffuse-lit configurations are independent.
    corr = torch.corrcoef(torch.stack((d_light[..., 0].flatten(), d_view[..., 0].flatten())))[0, 1]
    assert abs(float(corr)) < 0.03
    # Specular-lit: recover the shift s (z = 1e-4) from the mirror condition, then check every part.
    lp, vp = c.light[:, 3:], c.view[:, 3:]
    ratio = (lp[..., 2] - 1e-4) / (vp[..., 2] - 1e-4)
    shift = (lp[..., :2] + ratio[..., None] * vp[..., :2]) / (1 + ratio[..., None])
    assert shift.min() >= -1 and shift.max() <= 1 and float(shift.std()) == pytest.approx(1 / math.sqrt(3), abs=0.01)
    s3 = torch.cat((shift, torch.full_like(shift[..., :1], 1e-4)), -1)
    to_l, to_v = lp - s3, vp - s3
    mirrored = to_v / to_v.norm(dim=-1, keepdim=True) * torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(to_l / to_l.norm(dim=-1, keepdim=True), mirrored)
    for dist in (to_l.norm(dim=-1), to_v.norm(dim=-1)):
        assert float(dist.log().mean()) == pytest.approx(0.5, abs=0.02)
        assert float(dist.log().std()) == pytest.approx(0.75, abs=0.02)
    sin2 = 1 - mirrored[..., 2] ** 2
    assert sin2.min() >= 0.001 - 1e-9 and sin2.max() <= 0.9 + 1e-9


def test_seeding_and_zero_at_equality():
    pred, target = _maps("principled", seed=7), _maps("principled", seed=8)
    a = L.rendering_loss(pred, target, generator=torch.Generator().manual_seed(1))
    b = L.rendering_loss(pred, target, generator=torch.Generator().manual_seed(1))
    c = L.rendering_loss(pred, target, generator=torch.Generator().manual_seed(2))
    assert float(a) == float(b) and float(a) != float(c)
    assert float(L.rendering_loss(target, target, generator=torch.Generator().manual_seed(1))) == 0.0
    module = L.RenderingLoss(seed=1)
    assert float(module(pred, target)) == float(a)  # the module's own generator, same seed
    assert float(module(pred, target)) != float(a)  # ... which then moves on


def test_gradients_reach_every_map():
    pred = _maps("principled", seed=9).requires_grad_()
    loss = L.rendering_loss(pred, _maps("principled", seed=10), generator=torch.Generator().manual_seed(0))
    (grad,) = torch.autograd.grad(loss, pred)
    assert torch.isfinite(grad).all()
    assert (grad.abs().sum(dim=(0, 2, 3)) > 0).all()  # each of the 9 channels gets a gradient


def test_backward_kernel_runs_over_the_prediction_only(monkeypatch):
    """The target needs no gradient: the backward kernel covers pred's lanes, not both renderings'."""
    from torchbrdf.kernels import c_runner

    seen = []
    for name in ("run_fwd", "run_bwd"):
        real = getattr(c_runner, name)
        monkeypatch.setattr(c_runner, name, lambda plan, *a, _real=real, _name=name, **k: (
            seen.append((_name, plan.N)), _real(plan, *a, **k))[1])
    pred = _maps("principled", b=2, size=16, seed=13).requires_grad_()
    target = _maps("principled", b=2, size=16, seed=14)
    configs = L.random_configurations(2, generator=torch.Generator().manual_seed(0))
    loss = L.rendering_loss(pred, target, configs=configs)
    (grad,) = torch.autograd.grad(loss, pred)
    half = 2 * 9 * 16 * 16  # 4608 lanes per rendering: fused, as the 9216 of both together
    assert seen == [("run_fwd", half), ("run_fwd", half), ("run_bwd", half)]
    # the same values as the one rendering of both (what a call without gradients runs)
    seen.clear()
    with torch.no_grad():
        both = L.rendering_loss(pred, target, configs=configs)
    assert seen == [("run_fwd", 2 * half)]
    torch.testing.assert_close(loss.detach(), both, rtol=1e-6, atol=0)


def test_compile_fullgraph_has_no_graph_breaks_and_runs_the_fused_operator():
    from torch._dynamo.utils import counters

    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    pred = _maps("principled", seed=11).requires_grad_()
    target = _maps("principled", seed=12)
    configs = L.random_configurations(2, generator=torch.Generator().manual_seed(0))
    counters.clear()
    fn = torch.compile(lambda p, t, c: L.rendering_loss(p, t, configs=c), fullgraph=True, backend="aot_eager")
    out = fn(pred, target, configs)
    torch._dynamo.reset()
    torch.compile(lambda p, t, c: L.rendering_loss(p, t, configs=c), fullgraph=True, backend=backend)(
        pred, target, configs)
    assert not counters["graph_break"]
    assert any("principled_fwd" in str(node.target) for gm in graphs for node in gm.graph.nodes)
    eager = L.rendering_loss(pred, target, configs=configs)
    torch.testing.assert_close(out, eager)
    g_out, = torch.autograd.grad(out, pred)
    g_eager, = torch.autograd.grad(eager, pred)
    torch.testing.assert_close(g_out, g_eager, rtol=1e-4, atol=1e-7)
    # Drawing the configurations inside the compiled function (torch's global RNG) also traces.
    torch._dynamo.reset()
    drawn = torch.compile(lambda p, t: L.rendering_loss(p, t), fullgraph=True, backend="aot_eager")(pred, target)
    assert torch.isfinite(drawn)


def test_triton_kernels_through_the_interpreter(monkeypatch, tmp_path):
    pytest.importorskip("triton")
    ct = importlib.import_module("torchbrdf.kernels.codegen_triton")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    monkeypatch.setenv("TORCHBRDF_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("TORCHBRDF_BACKEND", raising=False)
    monkeypatch.delenv("TORCHBRDF_EAGER", raising=False)
    kinds = []  # the kinds of Triton kernels launched: proves the Triton path ran
    monkeypatch.setattr(ct, "launch", lambda kernel, kind, *rest, real=ct.launch: (
        kinds.append(kind), real(kernel, kind, *rest))[1])
    pred = _maps("principled", b=1, size=6, seed=13).requires_grad_()
    target = _maps("principled", b=1, size=6, seed=14)
    configs = L.random_configurations(1, 1, 2, generator=torch.Generator().manual_seed(0))
    torchbrdf.set_backend("triton")
    try:
        loss = L.rendering_loss(pred, target, configs=configs)
        (grad,) = torch.autograd.grad(loss, pred)
    finally:
        torchbrdf.set_backend(None)
    assert kinds, "the Triton kernels did not run"
    assert float(loss.detach()) == pytest.approx(_reference_loss(pred.detach(), target, configs, "principled"), rel=2e-5)
    assert torch.isfinite(grad).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    pred, target = _maps("principled", seed=15), _maps("principled", seed=16)
    configs = L.random_configurations(2, generator=torch.Generator().manual_seed(0))
    cpu = L.rendering_loss(pred, target, configs=configs)
    gpu = L.rendering_loss(pred.cuda(), target.cuda(), configs=L.Configurations(*(t.cuda() for t in configs)))
    assert float(gpu) == pytest.approx(float(cpu), rel=1e-4)
    seeded = L.rendering_loss(pred.cuda(), target.cuda(), generator=torch.Generator().manual_seed(0))
    assert float(seeded) == pytest.approx(float(cpu), rel=1e-4)  # a CPU generator seeds a CUDA loss


def test_map_loss_is_the_weighted_sum_of_per_map_l1():
    pred, target = _maps("principled", seed=17), _maps("principled", seed=18)
    d = (pred - target).abs()
    per_map = [d[:, 0:3].mean(), d[:, 3:4].mean(), d[:, 4:5].mean(), d[:, 5:6].mean(), d[:, 6:9].mean()]
    torch.testing.assert_close(L.map_loss(pred, target), sum(per_map))
    weighted = L.map_loss(pred, target, weights={"metallic": 3.0, "normal": 0.0})
    torch.testing.assert_close(weighted, per_map[0] + per_map[1] + 3 * per_map[2] + per_map[3])
    torch.testing.assert_close(L.MapLoss(weights={"metallic": 3.0, "normal": 0.0})(pred, target), weighted)
    with pytest.raises(ValueError, match="sheen"):
        L.map_loss(pred, target, weights={"sheen": 1.0})


def test_bad_input_names_the_layout_and_shape():
    with pytest.raises(ValueError, match=r"\(B, 10, H, W\).*svbrdf_ggx"):
        L.rendering_loss(_maps("principled"), _maps("principled"), layout="svbrdf_ggx")
    with pytest.raises(ValueError, match="one shape"):
        L.rendering_loss(_maps("principled", b=1), _maps("principled", b=2))
    with pytest.raises(ValueError, match="layout"):
        L.RenderingLoss(layout="disney")
    with pytest.raises(ValueError, match="n_diffuse"):
        L.random_configurations(1, 0, 0)
    channel_last = _maps("principled").permute(0, 2, 3, 1)
    with pytest.raises(ValueError, match=r"rendering_loss: pred must be \(B, 9, H, W\)"):
        L.rendering_loss(channel_last, channel_last)
    with pytest.raises(ValueError, match="map_loss: pred must be"):
        L.map_loss(channel_last, channel_last)
    with pytest.raises(ValueError, match="dtype and device.*float32.*float64"):
        L.rendering_loss(_maps("principled"), _maps("principled").double())
