import tempfile, time, torch
from torchbrdf.capture.synthetic import generate_capture
from torchbrdf.capture.format import load_capture
from torchbrdf.recovery.solver import LevelData, encode, soft_metal_candidates, soft_metal_fit, RecoveryConfig
from torchbrdf.recovery.svbrdf import recover
d = tempfile.mkdtemp()
generate_capture(d, recipe="aa_inlay", seed=5, size=32, lights=8, noise=0.01)
cap = load_capture(d).to(device="cuda", dtype=torch.float32)
data = LevelData(cap, 32, list(range(len(cap))), float(0.01 * cap.images.clamp(min=0).mean()))
P = 32 * 32
ones = torch.ones(P, 1, device="cuda")
n = torch.zeros(P, 3, device="cuda"); n[:, 2] = 1
theta = encode({"base_color": 0.5 * ones.expand(P, 3), "specular": 0.5 * ones, "roughness": 0.4 * ones, "normal": n})
metal = (torch.arange(P, device="cuda") % 32 < 16).float()[:, None]
r = data.residual(theta, metal, data.train_idx); cost = (r * r).sum(-1, keepdim=True)
rows = soft_metal_candidates(cost, metal, 32, 8.0, 0.2, 2)
t, m, acc = soft_metal_fit(data, theta, metal, rows, data.train_idx, "principled", 1e-3, 1e-3, 5)
print("cuda soft_metal_fit ok:", t.device, m.device, rows.numel(), "fractional", int(((m > 0) & (m < 1)).sum()))
try:
    t0 = time.time()
    res = recover(d, RecoveryConfig(device="cuda", iters=8), None, gt=d + "/gt", progress=False)
    print("cuda recover ok", time.time() - t0, res.report["fractional_metallic_fraction"], res.report["soft_metal"], res.report["errors"])
except Exception as e:
    import traceback; traceback.print_exc()
    print("cuda recover FAILED:", type(e).__name__, e)
