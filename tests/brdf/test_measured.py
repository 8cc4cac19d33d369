"""torchbrdf.measured: MERL file format, coordinates, interpolation, gradients."""

import math

import numpy as np
import pytest
import torch

from torchbrdf.brdf.measured import (
    MERL_RES,
    MERL_SCALE,
    MERLBRDF,
    merl_coordinates,
    merl_directions,
    merl_grid,
    read_merl,
    write_merl,
)

F64 = torch.float64


# --------------------------------------------------------------------------------------
# Test BRDFs and an independent float64 reference for the MERL coordinates
# --------------------------------------------------------------------------------------


def lambert(l, v, n, x=None, y=None, albedo=0.5):
    """Lambert: albedo / π wherever called (the tabulator zeroes the hidden hemisphere)."""
    return torch.ones_like(l[..., :1]) * torch.as_tensor(albedo, dtype=l.dtype) / math.pi


def ggx_lobe(l, v, n, x=None, y=None, alpha=0.3, f0=0.04, kd=(0.1, 0.2, 0.3)):
    """Smooth isotropic GGX lobe (separable Smith, Schlick Fresnel) plus a coloured diffuse term."""
    def d(a, b):
        return (a * b).sum(-1, keepdim=True)

    h = torch.nn.functional.normalize(l + v, dim=-1)
    nh, lh = d(n, h), d(l, h).clamp(0, 1)
    nl, nv = d(n, l).clamp(min=1e-6), d(n, v).clamp(min=1e-6)
    a2 = alpha * alpha
    ndf = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + torch.sqrt(a2 + (1 - a2) * c * c))

    fresnel = f0 + (1 - f0) * (1 - lh) ** 5
    diffuse = torch.as_tensor(kd, dtype=l.dtype) / math.pi
    return ndf * g1(nl) * g1(nv) * fresnel / (4 * nl * nv) + diffuse


def _rodrigues(vec, axis, angle):
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    axis = np.broadcast_to(axis, vec.shape)
    return vec * c + np.cross(axis, vec) * s + axis * (axis * vec).sum(-1, keepdims=True) * (1 - c)


def reference_coordinates(l, v):
    """MERL's half/diff conversion with explicit angle rotations, numpy float64, local frame."""
    h = l + v
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    theta_h = np.arccos(np.clip(h[:, 2], -1, 1))
    phi_h = np.arctan2(h[:, 1], h[:, 0])
    d = _rodrigues(l, np.array([0.0, 0.0, 1.0]), -phi_h)
    d = _rodrigues(d, np.array([0.0, 1.0, 0.0]), -theta_h)
    theta_d = np.arccos(np.clip(d[:, 2], -1, 1))
    phi_d = np.arctan2(d[:, 1], d[:, 0])
    phi_d = np.where(phi_d < 0, phi_d + np.pi, phi_d)
    return theta_h, theta_d, phi_d


def upper_hemisphere(rng, count, min_cos=0.0):
    out = np.empty((0, 3))
    while len(out) < count:
        w = rng.normal(size=(4 * count, 3))
        w /= np.linalg.norm(w, axis=-1, keepdims=True)
        w[:, 2] = np.abs(w[:, 2])
        out = np.concatenate([out, w[w[:, 2] > min_cos]])
    return out[:count]


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def to_world(rot, w):
    return torch.from_numpy(w @ rot.T)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # Tabulation is ~20 small elementwise passes over 1.46M samples; on the shared 2-core
    # machine, two intra-op threads competing with other jobs make it 10x slower, not faster.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# Tabulations are the slow part (~0.3 s each): share them across tests.
@pytest.fixture(scope="module")
def lambert_brdf():
    return MERLBRDF.from_brdf(lambert, albedo=torch.tensor([0.2, 0.5, 0.8], dtype=F64))


@pytest.fixture(scope="module")
def ggx_brdf():
    return MERLBRDF.from_brdf(ggx_lobe, alpha=0.3)


@pytest.fixture(scope="module")
def random_brdf():
    g = torch.Generator().manual_seed(3)
    return MERLBRDF(torch.rand(3, *MERL_RES, generator=g, dtype=F64) * 1000.0)


# --------------------------------------------------------------------------------------
# File format
# --------------------------------------------------------------------------------------


def test_file_layout_header_order_and_scale(tmp_path):
    # A table whose every value encodes its own index, written byte by byte as MERL does.
    c, i, j, k = np.meshgrid(*(np.arange(s) for s in (3, *MERL_RES)), indexing="ij")
    stored = (c * 1e7 + i * 1e5 + j * 1e3 + k).astype("<f8")
    p = tmp_path / "handmade.binary"
    p.write_bytes(np.array([90, 90, 180], dtype="<i4").tobytes() + stored.tobytes())

    raw = read_merl(p, raw=True)
    assert raw.dtype == F64 and raw.shape == (3, 90, 90, 180)
    assert raw[1, 2, 3, 4] == 1e7 + 2e5 + 3e3 + 4  # [channel, θh, θd, φd], φd fastest
    table = read_merl(p)
    for ch, scale in enumerate((1 / 1500, 1.15 / 1500, 1.66 / 1500)):
        assert torch.equal(table[ch], raw[ch] * scale)

    brdf = MERLBRDF.from_file(p)
    assert brdf.name == "handmade" and torch.equal(brdf.stored, raw)
    out = tmp_path / "out.binary"
    write_merl(out, brdf)
    assert out.read_bytes() == p.read_bytes()  # byte-for-byte round trip


def test_round_trip_from_brdf_is_bit_exact(tmp_path, lambert_brdf):
    p = tmp_path / "lambert.binary"
    write_merl(p, lambert_brdf)
    assert p.stat().st_size == 12 + 3 * 90 * 90 * 180 * 8
    assert np.frombuffer(p.read_bytes()[:12], dtype="<i4").tolist() == [90, 90, 180]
    back = MERLBRDF.from_file(p)
    assert torch.equal(back.stored, lambert_brdf.stored)
    assert torch.equal(back.table, lambert_brdf.table)
    p2 = tmp_path / "again.binary"
    write_merl(p2, back)
    assert p2.read_bytes() == p.read_bytes()
    assert sorted(f.name for f in tmp_path.iterdir()) == ["again.binary", "lambert.binary"]  # no temp files


def test_write_table_and_callable(tmp_path, lambert_brdf):
    values = torch.full((3, *MERL_RES), 0.25, dtype=F64)
    write_merl(tmp_path / "t.binary", values)
    torch.testing.assert_close(read_merl(tmp_path / "t.binary"), values, rtol=1e-15, atol=0)
    write_merl(tmp_path / "c.binary", lambert, albedo=torch.tensor([0.2, 0.5, 0.8], dtype=F64))
    assert torch.equal(MERLBRDF.from_file(tmp_path / "c.binary").stored, lambert_brdf.stored)


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.binary"):
        MERLBRDF.from_file(tmp_path / "nothing.binary")
    bad = tmp_path / "dims.binary"
    bad.write_bytes(np.array([90, 90, 360], dtype="<i4").tobytes() + b"\0" * 64)
    with pytest.raises(ValueError, match=r"dims.binary.*\(90, 90, 360\)"):
        read_merl(bad)
    short = tmp_path / "short.binary"
    short.write_bytes(np.array([90, 90, 180], dtype="<i4").tobytes() + b"\0" * 800)
    with pytest.raises(ValueError, match="short.binary.*812 bytes"):
        MERLBRDF.from_file(short)
    tiny = tmp_path / "tiny.binary"
    tiny.write_bytes(b"\1\2")
    with pytest.raises(ValueError, match="tiny.binary"):
        read_merl(tiny)
    with pytest.raises(ValueError, match=r"w.binary.*\(3, 90, 90\)"):
        write_merl(tmp_path / "w.binary", torch.zeros(3, 90, 90))
    with pytest.raises(TypeError, match="w.binary"):
        write_merl(tmp_path / "w.binary", "not a brdf")
    with pytest.raises(ValueError, match="non-finite"):
        write_merl(tmp_path / "w.binary", torch.full((3, *MERL_RES), float("nan")))
    with pytest.raises(ValueError, match="shape"):
        MERLBRDF.from_brdf(lambda l, v, n, x, y: l[..., :2])
    with pytest.raises(ValueError, match="non-finite"):
        MERLBRDF.from_brdf(lambda l, v, n, x, y: l / 0.0)
    assert not (tmp_path / "w.binary").exists()


def test_from_table_refuses_nonfinite_values_unless_allowed():
    table = torch.full((3, *MERL_RES), 0.2, dtype=F64)
    table[1, 4, 5, 6] = float("nan")
    with pytest.raises(ValueError, match=r"values: contains 1 non-finite value.*\(1, 4, 5, 6\)"):
        MERLBRDF.from_table(table)
    kept = MERLBRDF.from_table(table, allow_nonfinite=True)
    assert torch.isnan(kept.table[1, 4, 5, 6]) and float(kept.table[0, 4, 5, 6]) == pytest.approx(0.2)


# --------------------------------------------------------------------------------------
# Coordinates
# --------------------------------------------------------------------------------------


def test_coordinates_match_numpy_reference():
    rng = np.random.default_rng(0)
    l_loc, v_loc = upper_hemisphere(rng, 4000), upper_hemisphere(rng, 4000)
    ref_h, ref_d, ref_p = reference_coordinates(l_loc, v_loc)
    rot = random_rotation(rng)
    x, y, n = (torch.from_numpy(rot[:, i].copy()) for i in range(3))
    l, v = to_world(rot, l_loc), to_world(rot, v_loc)
    for frame in ((x, y), (None, None)):  # away from h = n the frame does not matter
        th, td, pd = (t.squeeze(-1).numpy() for t in merl_coordinates(l, v, n, *frame))
        np.testing.assert_allclose(th, ref_h, atol=1e-9, rtol=0)
        np.testing.assert_allclose(td, ref_d, atol=1e-9, rtol=0)
        defined = (ref_h > 1e-3) & (ref_d > 1e-3)
        diff = np.mod(pd - ref_p + np.pi / 2, np.pi) - np.pi / 2  # φd is defined modulo π
        assert np.abs(diff[defined]).max() < 1e-9
        assert pd.min() >= 0 and pd.max() <= np.pi


def test_coordinates_at_h_equal_n_use_phi_h_zero():
    # l and v mirrored about n: θh = 0, d = l, and φd is l's azimuth in (x, y), folded.
    theta, phi = 0.7, 2.5
    st = math.sin(theta)
    l = torch.tensor([st * math.cos(phi), st * math.sin(phi), math.cos(theta)], dtype=F64)
    v = l * torch.tensor([-1.0, -1.0, 1.0], dtype=F64)
    n, x, y = torch.eye(3, dtype=F64)[[2, 0, 1]]
    th, td, pd = merl_coordinates(l, v, n, x, y)
    assert float(th) == 0.0
    assert float(td) == pytest.approx(theta, abs=1e-12)
    assert float(pd) == pytest.approx(phi, abs=1e-12)
    _, _, pd_swapped = merl_coordinates(v, l, n, x, y)  # v's azimuth is φ + π: folds back to φ
    assert float(pd_swapped) == pytest.approx(phi, abs=1e-12)


def test_directions_invert_coordinates():
    g = torch.Generator().manual_seed(1)
    th = torch.rand(500, generator=g, dtype=F64) * 1.5 + 0.01
    td = torch.rand(500, generator=g, dtype=F64) * 1.5 + 0.01
    pd = torch.rand(500, generator=g, dtype=F64) * 3.1 + 0.01
    l, v = merl_directions(th, td, pd)
    torch.testing.assert_close(l.norm(dim=-1), torch.ones(500, dtype=F64))
    torch.testing.assert_close(v.norm(dim=-1), torch.ones(500, dtype=F64))
    n, x, y = torch.eye(3, dtype=F64)[[2, 0, 1]]
    back = merl_coordinates(l, v, n, x, y)
    for got, want in zip(back, (th, td, pd)):
        torch.testing.assert_close(got.squeeze(-1), want, atol=1e-9, rtol=0)


def test_grid_positions():
    th, td, pd = merl_grid()
    assert th[0] == 0 and td[0] == 0 and pd[0] == 0
    torch.testing.assert_close(th[45], torch.tensor((45 / 90) ** 2 * math.pi / 2, dtype=F64))
    torch.testing.assert_close(td[1], torch.tensor(math.pi / 180, dtype=F64))
    torch.testing.assert_close(pd[179], torch.tensor(179 * math.pi / 180, dtype=F64))


# --------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------


def test_interpolation_is_trilinear_in_warped_indices():
    # Trilinear interpolation of an affine function of the indices is exact, so this pins the
    # index mapping (square-root warp in θh, linear θd and φd) and the table layout together.
    i, j, k = torch.meshgrid(*(torch.arange(s, dtype=F64) for s in MERL_RES), indexing="ij")
    coef = torch.tensor([[1.0, 0.01, 0.0001], [0.02, 1.0, 0.0003], [0.03, 0.002, 1.0]], dtype=F64)
    values = torch.stack([c[0] * i + c[1] * j + c[2] * k for c in coef]) + 1.0
    brdf = MERLBRDF.from_table(values)
    rng = np.random.default_rng(2)
    l_loc, v_loc = upper_hemisphere(rng, 3000, 0.02), upper_hemisphere(rng, 3000, 0.02)
    th, td, pd = reference_coordinates(l_loc, v_loc)
    u = np.stack(
        [
            np.minimum(np.sqrt(th / (np.pi / 2)) * 90, 89),
            np.minimum(td / (np.pi / 2) * 90, 89),
            pd / np.pi * 180,
        ],
        axis=-1,
    )
    keep = u[:, 2] < 179  # between sample 179 and 0 φd wraps: not affine there
    expected = torch.from_numpy(u[keep]) @ coef.T + 1.0
    rot = random_rotation(rng)
    n = torch.from_numpy(rot[:, 2].copy())
    got = brdf(to_world(rot, l_loc[keep]), to_world(rot, v_loc[keep]), n)
    torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-9)


def test_grid_samples_are_reproduced(random_brdf):
    g = torch.Generator().manual_seed(4)
    idx = [torch.randint(1, s, (400,), generator=g) for s in MERL_RES]
    th, td, pd = merl_grid()
    l, v = merl_directions(th[idx[0]], td[idx[1]], pd[idx[2]])
    vis = (l[:, 2] > 1e-3) & (v[:, 2] > 1e-3)
    n, x, y = torch.eye(3, dtype=F64)[[2, 0, 1]]
    got = random_brdf(l[vis], v[vis], n, x, y)
    want = random_brdf.table[:, idx[0][vis], idx[1][vis], idx[2][vis]].t()
    torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-10)


def test_lambert_is_reproduced(lambert_brdf):
    rng = np.random.default_rng(5)
    rot = random_rotation(rng)
    n = torch.from_numpy(rot[:, 2].copy())
    l_loc, v_loc = upper_hemisphere(rng, 5000, 0.05), upper_hemisphere(rng, 5000, 0.05)
    got = lambert_brdf(to_world(rot, l_loc), to_world(rot, v_loc), n)
    want = torch.tensor([0.2, 0.5, 0.8], dtype=F64) / math.pi
    torch.testing.assert_close(got, want.expand_as(got), rtol=1e-12, atol=0)


def test_ggx_lobe_is_reproduced_to_interpolation_error(ggx_brdf):
    rng = np.random.default_rng(6)
    rot = random_rotation(rng)
    x, y, n = (torch.from_numpy(rot[:, i].copy()) for i in range(3))
    l_loc, v_loc = upper_hemisphere(rng, 20000, 0.1), upper_hemisphere(rng, 20000, 0.1)
    l, v = to_world(rot, l_loc), to_world(rot, v_loc)
    want = ggx_lobe(l, v, n)
    for frame in ((x, y), (None, None)):
        got = ggx_brdf(l, v, n, *frame)
        rel = ((got - want).abs() / want).max(dim=-1).values
        assert rel.max() < 1.5e-2  # measured 0.55 % on the 1° grid with this seed
        assert rel.median() < 5e-4  # measured 1.1e-4


def test_principled_file_round_trip(tmp_path):
    # A MERL file written from a known principled material evaluates back to it.
    torchbrdf = pytest.importorskip("torchbrdf")
    params = {"base_color": torch.tensor([0.6, 0.3, 0.1], dtype=F64), "roughness": 0.5, "metallic": 0.0}
    path = tmp_path / "principled.binary"
    write_merl(path, torchbrdf.principled, **params)
    brdf = MERLBRDF.from_file(path)
    rng = np.random.default_rng(10)
    l = torch.from_numpy(upper_hemisphere(rng, 5000, 0.1))
    v = torch.from_numpy(upper_hemisphere(rng, 5000, 0.1))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    want = torchbrdf.principled(l, v, n, **params)
    rel = ((brdf(l, v, n) - want).abs() / want).max(dim=-1).values
    assert rel.max() < 2e-2 and rel.median() < 1e-3  # measured 0.6 % and 2e-4


def test_below_horizon_is_zero(ggx_brdf):
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    s = math.sqrt(0.5)
    l = torch.tensor([[s, 0, s], [s, 0, -s], [1, 0, 0], [0, 0, 1]], dtype=F64)
    v = torch.tensor([[0, s, -s], [0, s, s], [0, 0, 1], [1, 0, 0]], dtype=F64)
    assert (ggx_brdf(l, v, n) == 0).all()


def test_missing_samples_evaluate_as_zero():
    stored = torch.full((3, *MERL_RES), -1.0, dtype=F64)
    stored[1] = 1500.0 / 1.15  # green measured everywhere, = 1.0
    brdf = MERLBRDF(stored)
    l = torch.tensor([[0.3, 0.1, 0.9], [0.0, 0.0, 1.0]], dtype=F64)
    l = l / l.norm(dim=-1, keepdim=True)
    got = brdf(l, l.flip(0), torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    torch.testing.assert_close(got, torch.tensor([[0.0, 1.0, 0.0]] * 2, dtype=F64))
    assert (brdf.table[0] < 0).all()  # the stored marker itself is kept for writing back


def test_reciprocity(random_brdf, ggx_brdf):
    rng = np.random.default_rng(7)
    rot = random_rotation(rng)
    n = torch.from_numpy(rot[:, 2].copy())
    l = to_world(rot, upper_hemisphere(rng, 5000, 0.01))
    v = to_world(rot, upper_hemisphere(rng, 5000, 0.01))
    for brdf in (random_brdf, ggx_brdf):
        torch.testing.assert_close(brdf(l, v, n), brdf(v, l, n), rtol=1e-9, atol=1e-12)


def test_broadcasting_dtypes_and_module_cast(ggx_brdf, device):
    brdf = MERLBRDF(ggx_brdf.stored).to(device)
    rng = np.random.default_rng(8)
    l = torch.from_numpy(upper_hemisphere(rng, 4, 0.2)).view(4, 1, 3).to(device)
    v = torch.from_numpy(upper_hemisphere(rng, 5, 0.2)).view(1, 5, 3).to(device)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64, device=device)
    ref = brdf(l, v, n)
    assert ref.shape == (4, 5, 3) and ref.dtype == F64 and ref.device.type == device.type
    for dtype, tol in ((torch.float32, 1e-4), (torch.float16, 1e-2), (torch.bfloat16, 3e-2)):
        got = brdf(l.to(dtype), v.to(dtype), n.to(dtype))
        assert got.dtype == dtype
        torch.testing.assert_close(got.double(), ref, rtol=tol, atol=tol * ref.max().item())
    small = brdf.float()
    assert small.stored.dtype == torch.float32
    torch.testing.assert_close(small(l.float(), v.float(), n.float()).double(), ref, rtol=1e-4, atol=1e-6)


def test_gradients_are_finite_at_singular_configurations(random_brdf):
    s = math.sqrt(0.5)
    cases = [
        ([0, 0, 1], [0, 0, 1]),  # l = v = n: θh = θd = 0, φ undefined
        ([s, 0, s], [s, 0, s]),  # l = v
        ([s, 0, s], [-s, 0, s]),  # h = n
        ([1e-7, 0, 1], [0, 1e-7, 1]),  # h within 1e-7 of n
        ([1, 0, 0], [0, 0, 1]),  # grazing light
        ([s, 0, s], [-s, 0, -s]),  # l = -v: zero half vector
        ([0, 0, -1], [0, 0, 1]),  # light below the horizon
    ]
    for dtype in (F64, torch.float32):
        for lv in cases:
            l, v = (
                torch.nn.functional.normalize(torch.tensor(w, dtype=F64), dim=-1).to(dtype).requires_grad_()
                for w in lv
            )
            n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, requires_grad=True)
            f = random_brdf(l, v, n)
            f.sum().backward()
            for t in (f, l.grad, v.grad, n.grad):
                assert torch.isfinite(t).all(), (dtype, lv)


def test_gradient_matches_finite_differences(ggx_brdf):
    rng = np.random.default_rng(9)
    l = torch.from_numpy(upper_hemisphere(rng, 20, 0.3)).requires_grad_()
    v = torch.from_numpy(upper_hemisphere(rng, 20, 0.3))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    weights = torch.tensor([0.3, 1.0, 0.5], dtype=F64)
    (ggx_brdf(l, v, n) * weights).sum().backward()
    assert torch.isfinite(l.grad).all() and (l.grad.abs().sum(-1) > 0).all()
    direction = torch.from_numpy(rng.normal(size=(20, 3)))
    eps = 1e-7  # well inside one grid cell (~1e-2 rad) so the piecewise-linear map is smooth
    with torch.no_grad():
        up = (ggx_brdf(l + eps * direction, v, n) * weights).sum(-1)
        down = (ggx_brdf(l - eps * direction, v, n) * weights).sum(-1)
    numeric = (up - down) / (2 * eps)
    analytic = (l.grad * direction).sum(-1)
    torch.testing.assert_close(analytic, numeric, rtol=1e-4, atol=1e-6)


def test_scale_constants():
    assert MERL_RES == (90, 90, 180)
    assert MERL_SCALE == (1 / 1500, 1.15 / 1500, 1.66 / 1500)


def test_directory_and_missing_file_messages(tmp_path):
    folder = tmp_path / "gold.binary"
    folder.mkdir()
    for load in (read_merl, MERLBRDF.from_file):
        with pytest.raises(IsADirectoryError, match=r"gold\.binary' is a directory, not a file"):
            load(folder)
        with pytest.raises(FileNotFoundError, match=r"nothing\.binary' not found"):
            load(tmp_path / "nothing.binary")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_samples_refused_unless_allowed(tmp_path, lambert_brdf, bad):
    p = tmp_path / "nan.binary"
    write_merl(p, lambert_brdf)
    data = bytearray(p.read_bytes())
    # Sample (channel G, θh 2, θd 3, φd 4) of the stored float64 table, after the 12-byte header.
    index = ((1 * 90 + 2) * 90 + 3) * 180 + 4
    data[12 + 8 * index : 12 + 8 * index + 8] = np.float64(bad).tobytes()
    p.write_bytes(bytes(data))
    match = r"nan\.binary': 1 non-finite sample.*channel G at \(θh, θd, φd\) index \(2, 3, 4\).*allow_nonfinite=True"
    with pytest.raises(ValueError, match=match):
        read_merl(p)
    with pytest.raises(ValueError, match=match):
        MERLBRDF.from_file(p)
    table = read_merl(p, allow_nonfinite=True)
    assert int((~torch.isfinite(table)).sum()) == 1
    brdf = MERLBRDF.from_file(p, allow_nonfinite=True)
    assert int((~torch.isfinite(brdf.stored)).sum()) == 1
    with pytest.raises(ValueError, match="non-finite"):  # and it is not written back
        write_merl(tmp_path / "again.binary", brdf)


def test_from_brdf_takes_float32_parameters():
    """A float32 parameter (torch's default) is cast to the tabulation dtype.

    The principled BRDF wants one dtype and named the mismatch with the internal directions before.
    """
    from torchbrdf import principled

    f32 = MERLBRDF.from_brdf(principled, base_color=torch.tensor([0.7, 0.2, 0.1]), roughness=0.35)
    f64 = MERLBRDF.from_brdf(principled, base_color=torch.tensor([0.7, 0.2, 0.1]).double(), roughness=0.35)
    assert torch.equal(f32.stored, f64.stored)


def test_from_table_refuses_a_wrong_shape_naming_the_argument():
    # Channel-last (90, 90, 180, 3), the natural guess: named here, not a broadcast error inside.
    with pytest.raises(ValueError, match=r"values: expected a \(3, 90, 90, 180\) table, got \(90, 90, 180, 3\)"):
        MERLBRDF.from_table(torch.rand(90, 90, 180, 3))
