"""Figure for docs/recovery.md: the recovery's confidence map vs where captured highlights reach.

``python docs/recovery_confidence.py CAPTURE_DIR RECOVERY_OUT_DIR [docs/recovery_confidence.png]``

Panels: the true base colour; the *highlight reach* — for each pixel, the smallest angle over
the captured lights between its true normal and the half vector (a GGX lobe of roughness r
is ~ r² rad wide, so a glossy pixel whose smallest angle is large never shows a highlight);
the true roughness; the recovery's ``confidence.exr``; and the roughness error.
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from torchbrdf.capture.format import load_capture, pixel_points
from torchbrdf.io import read_exr


def main(cap_dir: str, out_dir: str, png: str = "docs/recovery_confidence.png") -> None:
    cap = load_capture(cap_dir)
    gt = {k: read_exr(Path(cap_dir) / "gt" / f"{k}.exr") for k in ("base_color", "roughness", "normal")}
    conf = read_exr(Path(out_dir) / "confidence.exr")[0]
    rough = read_exr(Path(out_dir) / "roughness.exr")[0]
    h, w = conf.shape
    p = pixel_points(w, h).reshape(-1, 3)
    n = gt["normal"].reshape(3, -1).T
    v = torch.nn.functional.normalize(cap.camera_position - p, dim=-1)
    ang = []
    for pos in cap.light_positions:
        l = torch.nn.functional.normalize(pos - p, dim=-1)
        hv = torch.nn.functional.normalize(l + v, dim=-1)
        ang.append(torch.rad2deg(torch.acos((hv * n).sum(-1).clamp(-1, 1))))
    reach = torch.stack(ang).min(0).values.reshape(h, w)
    # In lobe widths: a GGX lobe of roughness r is ~ atan(r²) wide; > 3 widths: no highlight.
    width = torch.rad2deg(torch.atan(gt["roughness"][0] ** 2)).clamp(min=0.5)
    ratio = reach / width
    err = (rough - gt["roughness"][0]).abs()
    fig, ax = plt.subplots(1, 6, figsize=(21, 3.8))
    panels = [(gt["base_color"].permute(1, 2, 0).clamp(0, 1) ** (1 / 2.2), "true base colour", None, None),
              (ratio, "highlight miss: smallest normal–half-vector\nangle over captured lights / lobe width", "magma_r", (0, 6)),
              (gt["roughness"][0], "true roughness", "viridis", (0, 1)),
              (conf, "recovered confidence.exr", "viridis", (0, 1)),
              (err, "|roughness error|", "magma", (0, 0.2))]
    a = ax[5]
    edges = torch.tensor([0, 0.5, 1, 1.5, 2, 3, 4, 6, 10, 1e9])
    for sel, lab, col in ((gt["roughness"][0] < 0.5, "glossy pixels (true r < 0.5)", "C0"),
                          (gt["roughness"][0] >= 0.5, "rough pixels", "C1")):
        xs, ys, es = [], [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = sel & (ratio >= lo) & (ratio < hi)
            if int(m.sum()) >= 10:
                xs.append(float(ratio[m].median()))
                ys.append(float(conf[m].mean()))
                es.append(float(err[m].pow(2).mean().sqrt()))
        a.plot(xs, ys, "-o", color=col, label=f"{lab}: mean confidence")
        a.plot(xs, es, "--x", color=col, label=f"{lab}: roughness RMSE")
    a.set_xlabel("highlight miss (lobe widths)")
    a.set_ylim(0, 1)
    a.legend(fontsize=6)
    a.set_title("confidence and error vs highlight miss", fontsize=9)
    for a, (img, title, cmap, lim) in zip(ax, panels):
        im = a.imshow(img.numpy(), cmap=cmap, vmin=None if lim is None else lim[0], vmax=None if lim is None else lim[1])
        a.set_title(title, fontsize=9)
        a.set_xticks([])
        a.set_yticks([])
        if cmap is not None:
            fig.colorbar(im, ax=a, fraction=0.046, pad=0.04)
    fig.suptitle(f"{Path(cap_dir).name}: recovered confidence vs where the captured highlights reach", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    print(f"wrote {png}")


if __name__ == "__main__":
    main(*sys.argv[1:])
