"""The decode's tangents in closed form, and the Jacobians built on them without ``torch.func``.

:func:`~torchbrdf.recovery.params.decode_jvp` and :func:`~torchbrdf.recovery.params.decode_directions`
against ``torch.func`` (``jacfwd`` in float64; ``vmap`` of ``jvp``, the fit's former way, bit
for bit), and the light step's and the normal equations' Jacobians, which no longer go
through ``torch.func.vmap`` (the residual's tangents along the lights: tests/capture/test_synthetic.py).
"""

from __future__ import annotations

import pytest
import torch

from torchbrdf.recovery import calibration
from torchbrdf.recovery.levels import log_residual, vmapped_jvp
from torchbrdf.recovery.params import N_PARAMS, decode, decode_directions, decode_jvp, decode_slots

from tests.recovery.recovery_fixtures import flat_level

#: The decoded parameters in the order of the Jacobian's rows below (9 rows with metallic).
ROWS = ("base_color", "specular", "roughness", "normal", "metallic")


def _unknowns(dtype: torch.dtype, n_x: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``x (P, n_x)`` and ``metal (P, 1)``: metal and dielectric pixels, a fractional metallic
    (8 columns), extreme logits (the sigmoid saturated) and slopes (flat, steep, ``−0``)."""
    gen = torch.Generator().manual_seed(5)
    x = (2.0 * torch.randn(40, n_x, generator=gen)).to(dtype)
    x[:4, 0:5], x[4:8, 0:5] = 30.0, -30.0  # σ' = e^-30 (float64) or its float32 rounding
    x[8:12, 5:7], x[12:16, 5:7] = 0.0, torch.tensor([[40.0, -25.0]], dtype=dtype)
    x[16:20, 5:7], x[20:22, 5], x[22:24, 6] = -0.0, -0.0, -0.0  # signed zeros: the tangents keep their signs
    metal = (torch.arange(40) % 2).to(dtype)[:, None]
    if n_x == 8:
        x[:, 7] = torch.rand(40, generator=gen).to(dtype)  # fractional metallic
    return x, metal


def _reference(x: torch.Tensor, metal: torch.Tensor) -> dict:
    """The decode's per-pixel Jacobian ``{name: (P, C, n_x)}`` by ``jacfwd``, one pixel at a time."""
    def one(v: torch.Tensor, m: torch.Tensor) -> dict:
        return decode(v[None, :7], v[None, 7:8] if v.shape[0] == 8 else m[None])

    jac = torch.func.vmap(torch.func.jacfwd(one))(x, metal)
    return {k: v[:, 0] for k, v in jac.items()}


@pytest.mark.parametrize("n_x", [7, 8])
def test_decode_jvp_is_the_jacobian_of_decode(n_x):
    """Along the unit directions the closed-form tangents are ``jacfwd(decode)`` to 1e-12 (float64):
    per-channel sigmoid derivatives, the roughness's span, the normal's 3×2 block, metallic's 1
    (8 columns; none with 7), zeros elsewhere. The normal's block with its slopes swapped, or
    a base colour's channels crossed, is told apart."""
    x, metal = _unknowns(torch.float64, n_x)
    p, dp = decode_jvp(x, metal, torch.eye(n_x, dtype=x.dtype)[:, None, :].expand(n_x, *x.shape))
    want = _reference(x, metal)
    assert set(dp) == ({"base_color", "specular", "roughness", "normal"} | ({"metallic"} if n_x == 8 else set()))
    for k, v in decode(x[:, :7], x[:, 7:8] if n_x == 8 else metal).items():
        assert torch.equal(p[k], v)
    got = torch.cat([dp[k].permute(1, 2, 0) for k in ROWS if k in dp], 1)  # (P, C, n_x)
    ref = torch.cat([want[k] for k in ROWS if k in dp], 1)
    assert got.shape == (40, 9 if n_x == 8 else 8, n_x)
    torch.testing.assert_close(got, ref, rtol=0.0, atol=1e-12)
    assert float(got[:, 5:8, 5:7].abs().min(-1).values.max()) > 0.1  # the normal block is not trivial
    for wrong in (got[:, :, [0, 1, 2, 3, 4, 6, 5, *range(7, n_x)]], got[:, [1, 0, *range(2, got.shape[1])]]):
        assert float((wrong - ref).abs().max()) > 1e-3


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n_x", [7, 8])
def test_decode_tangents_are_those_of_vmap_of_jvp_bit_for_bit(dtype, n_x):
    """:func:`decode_jvp` (random tangents) and :func:`decode_directions` (the normal equations'
    slots, the light step's unit directions with zero ones after, two slopes in one direction)
    give ``vmap`` of ``jvp`` of :func:`decode` exactly, signed zeros included; the directions
    in their order (reversed rows differ)."""
    x, metal = _unknowns(dtype, n_x)
    f = vmapped_jvp(lambda v: decode(*((v[:, :7], v[:, 7:8]) if v.shape[1] == 8 else (v, metal))))
    gen = torch.Generator().manual_seed(1)
    tangents = torch.randn(4, *x.shape, generator=gen).to(dtype)
    _, want = f(x, tangents)
    _, got = decode_jvp(x, metal, tangents)
    for k in got:
        assert torch.equal(got[k], want[k]), k
    for rows in (decode_slots(n_x), [[j] for j in range(N_PARAMS)] + [[]] * 4, [[5, 6], [0, 4], [3]]):
        unit = torch.zeros(len(rows), *x.shape, dtype=dtype)
        for k, cols in enumerate(rows):
            unit[k, :, list(cols)] = 1.0
        _, want = f(x, unit)
        _, got = decode_directions(x, metal, rows)
        assert set(got) == set(want) - ({"metallic"} if n_x == 7 else set())
        for k in got:
            assert got[k].is_contiguous() and torch.equal(got[k], want[k]), (rows, k)
            assert torch.equal(got[k].signbit(), want[k].signbit()), (rows, k)
        _, flipped = decode_directions(x, metal, list(rows)[::-1])
        assert not all(torch.equal(flipped[k], want[k]) for k in got)


def test_decode_directions_refuses_an_unknown_it_does_not_have():
    x, metal = _unknowns(torch.float32, 7)
    with pytest.raises(ValueError, match=r"rows\[1\] lists unknown 7; x has 7 columns"):
        decode_directions(x, metal, [[0], [7]])


def test_decode_directions_refuses_an_unknown_listed_twice():
    """A row is a sum of unit vectors: an unknown listed twice would be a direction of length 2
    along it, which the copies of each unknown's derivative cannot give (refused, not halved)."""
    x, metal = _unknowns(torch.float64, 7)
    for row in ([5, 5], [0, 0], [6, 5, 6]):
        with pytest.raises(ValueError, match=r"rows\[1\] lists unknown \d twice"):
            decode_directions(x, metal, [[0], row])


def _light_jacobians_by_vmap(data, t0, m, pts, log_obs, inten0, pos0, s0, model, position=True):
    """The light step's Jacobians as ``torch.func.vmap`` of ``jvp`` of the residual (the reference)."""
    def res(t, pos, s):
        r = log_residual(decode(t, m), pts, data.camera, pos, inten0 * torch.exp(s)[:, None], log_obs, data.eps,
                         model)
        return r.reshape(t.shape[0], -1)

    n, n_g = t0.shape[0], 4 if position else 1
    tt = torch.zeros(N_PARAMS + n_g, n, N_PARAMS, dtype=t0.dtype)
    tt[:N_PARAMS] = torch.eye(N_PARAMS, dtype=t0.dtype)[:, None, :]
    tp = torch.zeros(N_PARAMS + n_g, *pos0.shape, dtype=t0.dtype)
    ts = torch.zeros(N_PARAMS + n_g, s0.shape[0], dtype=t0.dtype)
    for k in range(n_g - 1):
        tp[N_PARAMS + k, :, k] = 1.0
    ts[-1] = 1.0
    return torch.func.vmap(lambda a, b, c: torch.func.jvp(res, (t0, pos0, s0), (a, b, c)),
                           out_dims=(None, 0))(tt, tp, ts)


def _no_vmap(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("torch.func.vmap called")

    monkeypatch.setattr(torch.func, "vmap", refuse)


def _light_step_args(dtype, seed, model="principled"):
    """A flat 8×8 level with 6 lights and the joint light step's arguments at a perturbed state."""
    data, theta, metal = flat_level(size=8, lights=6, normal_tilt_deg=10.0)
    gen = torch.Generator().manual_seed(seed)
    n_l = data.pos_stated.shape[0]
    data.camera = data.camera.to(dtype)
    return (data, (theta + 0.3 * torch.randn(theta.shape, generator=gen)).to(dtype), metal.to(dtype),
            data.points.to(dtype), data.log_obs.permute(1, 0, 2).to(dtype), data.inten_stated.to(dtype),
            (data.pos_stated + 0.01 * torch.randn(n_l, 3, generator=gen)).to(dtype),
            (0.1 * torch.randn(n_l, generator=gen)).to(dtype), model)


@pytest.mark.parametrize("model", ["principled", "svbrdf_ggx"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("position", [True, False])
def test_light_step_jacobians_are_vmap_of_jvp_without_it(monkeypatch, dtype, position, model):
    """The joint light step's residuals and ``7 + G`` derivative columns (offsets, log scales
    away from 0 and from each other) equal ``vmap`` of ``jvp`` of the residual bit for bit,
    computed without ``torch.func.vmap``, under either model."""
    args = _light_step_args(dtype, 3, model)
    n_l = args[0].pos_stated.shape[0]
    want_r, want = _light_jacobians_by_vmap(*args, position=position)
    _no_vmap(monkeypatch)
    r, cols = calibration._pixel_and_light_jacobians(*args, position=position)
    assert cols.shape == (N_PARAMS + (4 if position else 1), 64, 3 * n_l)
    assert torch.equal(r, want_r) and torch.equal(cols, want)
    assert float(cols[-1].median()) > 0.5  # the log scale's column: pred / (pred + ε)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_light_step_jacobians_run_in_one_pass_with_the_bits_of_several(monkeypatch, dtype):
    """The joint light step's 7 + 4 directions run in one pass of the JVP kernel (one primal,
    not two) and give the bits of passes of 4, 4 and 3 directions."""
    from torchbrdf.kernels import c_runner

    args = _light_step_args(dtype, 4)
    passes = []
    load = c_runner.load

    def counted(spec, backward=False):
        if backward == "jvp":
            passes.append(spec.ntan)
        return load(spec, backward=backward)

    monkeypatch.setattr(c_runner, "load", counted)
    r, cols = calibration._pixel_and_light_jacobians(*args)
    assert passes == [N_PARAMS + 4]
    monkeypatch.setattr(c_runner, "TANGENTS_PER_PASS", 4)
    passes.clear()
    r4, cols4 = calibration._pixel_and_light_jacobians(*args)
    assert passes == [4, 4, 3]
    assert torch.equal(r, r4) and torch.equal(cols, cols4)


@pytest.mark.parametrize("model", ["principled", "svbrdf_ggx"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("position", [True, False])
def test_light_step_jacobians_take_the_base_colour_in_one_direction_with_the_bits_of_three(dtype, position, model):
    """``base_one``: the base colour's three logits in one direction (``5 + G`` rows) give each
    logit's column on its own channel with the bits of one direction per logit, and the light
    step's reduced system from them is the same, bit for bit, with the C elimination and without."""
    args = _light_step_args(dtype, 3, model)
    r, cols = calibration._pixel_and_light_jacobians(*args, position=position)
    r1, cols1 = calibration._pixel_and_light_jacobians(*args, position=position, base_one=True)
    assert cols1.shape == (cols.shape[0] - 2, *cols.shape[1:])
    assert torch.equal(r1, r) and torch.equal(cols1[1:], cols[3:])
    channel = torch.arange(cols.shape[-1]) % 3
    for c in range(3):
        assert torch.equal(cols1[0][:, channel == c], cols[c][:, channel == c])
        assert bool((cols[c][:, channel != c] == 0).all())  # (what the one row stands for there)
    g = torch.Generator().manual_seed(5)
    prior = (1e-2 * torch.randn(r.shape[0], 7, generator=g, dtype=dtype), torch.rand(r.shape[0], 7, generator=g,
                                                                                     dtype=dtype))
    for fused in (True, False):
        want = calibration._reduced_light_system(r, cols, prior, 1e-3, chunk=24, fused=fused)
        got = calibration._reduced_light_system(r1, cols1, prior, 1e-3, chunk=24, fused=fused, base_one=True)
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1]) and got[2] == want[2]
    with pytest.raises(ValueError, match="family: expected one of"):
        calibration._pixel_and_light_jacobians(*args[:-1], "exact_fresnel", position, True)


@pytest.mark.parametrize("n_t", [7, 8])
def test_normal_equations_without_vmap_are_those_of_the_vmapped_decode(monkeypatch, n_t):
    """``LevelData.normal_equations`` (8 columns: the continuous-metallic stage, metallic
    differentiated or held) gives the fused kernel's terms on the decode's tangents of ``vmap`` of
    ``jvp`` bit for bit, without ``torch.func.vmap``."""
    from torchbrdf.brdf import capture_residual
    from torchbrdf.recovery.params import decode_pattern

    data, theta, metal = flat_level(size=8, lights=6, normal_tilt_deg=10.0)
    gen = torch.Generator().manual_seed(2)
    x = torch.cat((theta + 0.3 * torch.randn(theta.shape, generator=gen), torch.rand(64, 1, generator=gen)), -1)
    idx = data.train_idx
    slots = decode_slots(n_t)
    dirs = torch.zeros(len(slots), 8)
    for s, cols in enumerate(slots):
        dirs[s, list(cols)] = 1.0
    p, dp = vmapped_jvp(lambda v: decode(v[:, :7], v[:, 7:8]))(x, dirs[:, None].expand(-1, *x.shape))
    pattern = decode_pattern(n_t)
    want = capture_residual.normal_equations(p["normal"], data.points, data.camera, data.pos[idx], data.inten[idx],
                                             p, data.log_obs[idx].permute(1, 0, 2).contiguous(), data.eps,
                                             {k: dp[k] for k in pattern}, pattern, n_t)
    _no_vmap(monkeypatch)
    got = data.normal_equations(x, x[:, 7:8], idx, "principled", n_t)
    assert want is not None and got is not None
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    assert float(got[2][:, n_t - 1, n_t - 1].abs().max()) > 0  # the last unknown moves the residuals
