"""``python -m training.train_estimator``: train the map estimator behind :class:`torchbrdf.recovery.prior.Prior`.

A compact U-Net (:class:`~torchbrdf.recovery.prior.MapEstimator`) learns flash image(s) ->
principled maps from :class:`torchbrdf.data.MaterialStream` samples, with the rendering loss
plus a map loss (:mod:`torchbrdf.losses`), for a bounded wall time. It writes
``OUT/estimator.pt`` (loadable with ``Prior.from_file``) and ``OUT/model_card.json`` /
``OUT/model_card.md`` (data, time, accuracy on held-out samples). ``--benchmark`` instead
measures the data loader's samples/s against the training step (docs/neural.md).

Runs as ``python -m training.train_estimator`` and as ``python training/train_estimator.py``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

import torchbrdf
from torchbrdf.data import FamilySource, MaterialDataset, MaterialStream, RecipeSource
from torchbrdf.losses import map_loss, rendering_loss
from torchbrdf.recovery.prior import MapEstimator, Prior

# Held-out samples come from a dataset seed that training never uses.
HELDOUT_SEED = 7_777


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m training.train_estimator", description=__doc__.split("\n")[0].replace("``", ""))
    p.add_argument("--out", type=Path, default=Path("out/estimator"), help="output folder (created)")
    p.add_argument("--minutes", type=float, default=5.0, help="training wall time")
    p.add_argument("--size", type=int, default=64, help="training crop size S")
    p.add_argument("--batch", type=int, default=8, help="samples per training step")
    p.add_argument("--lights", type=int, default=1, help="images per sample: the flash, then random lights")
    p.add_argument("--ring", action="store_true",
                   help="the extra lights are light_layout's ring (the capture layout), not random lights")
    p.add_argument("--source", choices=("recipes", "families"), default="recipes",
                   help="materials: the synthetic recipes or torchbrdf.capture.families")
    p.add_argument("--width", type=int, default=16, help="U-Net channels of the first level")
    p.add_argument("--depth", type=int, default=3, help="U-Net downsamplings")
    p.add_argument("--lr", type=float, default=2e-3, help="Adam learning rate")
    p.add_argument("--map-weight", type=float, default=1.0, help="weight of the map loss beside the rendering loss")
    p.add_argument("--workers", type=int, default=2, help="DataLoader workers")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the training process")
    p.add_argument("--device", default="cpu", help="training device (cpu, cuda, cuda:1, ...)")
    p.add_argument("--seed", type=int, default=0, help="seed of the training stream and the weights' initialisation")
    p.add_argument("--init", type=Path, default=None, help="continue from these weights (same architecture)")
    p.add_argument("--heldout", type=int, default=64, help="held-out samples for the card's accuracy")
    p.add_argument("--benchmark", action="store_true", help="measure loader samples/s vs the training step, then exit")
    return p


def _source(args) -> FamilySource | RecipeSource:
    return FamilySource() if args.source == "families" else RecipeSource()


def _loader(args, seed: int, length: int | None = None, start: int = 0) -> DataLoader:
    stream = MaterialStream(length=length, start=start, size=args.size, seed=seed, extra_lights=args.lights - 1,
                            ring_lights=args.ring, source=_source(args))
    return DataLoader(stream, batch_size=args.batch, num_workers=args.workers,
                      persistent_workers=args.workers > 0 and length is None)


def _step(model, opt, batch, args, gen: torch.Generator) -> dict:
    dev = torch.device(args.device)
    images, target = batch["images"].to(dev), batch["maps"].to(dev)
    pred = model(images, batch["light_positions"].to(dev), batch["light_intensities"].to(dev))
    rl = rendering_loss(pred, target, generator=gen) if dev.type == "cpu" else rendering_loss(pred, target)
    ml = map_loss(pred, target)
    loss = rl + args.map_weight * ml
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return {"loss": float(loss.detach()), "rendering": float(rl.detach()), "map": float(ml.detach())}


def widen_lights(state: dict, lights: int, new_lights: int) -> dict:
    """A state dict of a ``lights``-image estimator for ``new_lights`` images: the first conv's
    weights of the images the two share are kept (the flash first), those of new images start
    at zero (the network starts as the old one and learns what the new images add), the pixel
    coordinates' channels move behind them."""
    if new_lights == lights:
        return dict(state)
    key = "down.0.0.weight"  # the first conv: (out, 3 L + 2, 3, 3)
    w = state[key]
    keep = 3 * min(lights, new_lights)
    new = torch.zeros(w.shape[0], 3 * new_lights + 2, *w.shape[2:], dtype=w.dtype)
    new[:, :keep] = w[:, :keep]
    new[:, -2:] = w[:, -2:]
    return {**state, key: new}


@torch.no_grad()
def evaluate(model: torch.nn.Module, samples: list[dict], device: str = "cpu") -> dict:
    """Held-out accuracy: per-map RMSE, normal angular error, rendering loss (fixed seed), and
    the same RMSEs of the best constant maps (the held-out means) for scale."""
    model.eval()
    preds, gts = [], []
    for s in samples:
        preds.append(model(s["images"][None].to(device), s["light_positions"][None].to(device),
                           s["light_intensities"][None].to(device)).cpu())
        gts.append(s["maps"][None])
    pred, gt = torch.cat(preds), torch.cat(gts)
    model.train()
    const = gt.mean(dim=(0, 2, 3), keepdim=True).expand_as(gt)
    out: dict = {}
    for name, sl in (("base_color", slice(0, 3)), ("roughness", slice(3, 4)), ("metallic", slice(4, 5)),
                     ("specular", slice(5, 6))):
        out[f"{name}_rmse"] = float((pred[:, sl] - gt[:, sl]).square().mean().sqrt())
        out[f"{name}_rmse_constant"] = float((const[:, sl] - gt[:, sl]).square().mean().sqrt())
    cos = (pred[:, 6:9] * gt[:, 6:9]).sum(1).clamp(-1, 1)
    out["normal_mean_deg"] = float(torch.rad2deg(torch.acos(cos)).mean())
    out["normal_mean_deg_flat"] = float(torch.rad2deg(torch.acos(gt[:, 8].clamp(-1, 1))).mean())
    out["rendering_loss"] = float(rendering_loss(pred, gt, generator=torch.Generator().manual_seed(0)))
    return out


def benchmark(args) -> dict:
    """Loader samples/s (``--workers``) and the training step's samples/s, alternated three times."""
    torch.set_num_threads(args.threads)
    model = MapEstimator(args.lights, args.width, args.depth).to(args.device)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    gen = torch.Generator().manual_seed(0)
    batch = next(iter(_loader(args, args.seed, length=args.batch)))
    loader_rates, step_rates = [], []
    for rep in range(3):
        batches = iter(_loader(args, args.seed + 1 + rep, length=args.batch * 13))
        next(batches)  # the workers' start-up is not throughput
        t = time.perf_counter()
        n = sum(b["images"].shape[0] for b in batches)
        loader_rates.append(n / (time.perf_counter() - t))
        _step(model, opt, batch, args, gen)  # warm
        t = time.perf_counter()
        for _ in range(5):
            _step(model, opt, batch, args, gen)
        step_rates.append(5 * args.batch / (time.perf_counter() - t))
    res = {"workers": args.workers, "threads": args.threads, "size": args.size, "batch": args.batch,
           "loader_samples_per_s": sorted(loader_rates), "step_samples_per_s": sorted(step_rates)}
    print(json.dumps(res, indent=1))
    return res


def train(args) -> dict:
    """Train for ``args.minutes``, then evaluate and write the weights and the card."""
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    model = MapEstimator(args.lights, args.width, args.depth).to(args.device)
    previous = None
    if args.init is not None:
        init = Prior.from_file(args.init)
        if {k: v for k, v in init.model.config.items() if k != "lights"} != \
                {k: v for k, v in model.config.items() if k != "lights"}:
            raise SystemExit(f"train_estimator: --init {args.init} is a {init.model.config} estimator, "
                             f"not {model.config}")
        model.load_state_dict(widen_lights(init.model.state_dict(), init.lights, args.lights))
        previous = init.card.get("training")
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    gen = torch.Generator().manual_seed(args.seed)
    heldout_ds = MaterialDataset(length=args.heldout, size=args.size, seed=HELDOUT_SEED, variants=1,
                                 extra_lights=args.lights - 1, ring_lights=args.ring, source=_source(args))
    heldout = [heldout_ds[k] for k in range(args.heldout)]
    budget = 60.0 * args.minutes
    start = time.perf_counter()
    steps, seen, wait, log = 0, 0, 0.0, []
    t_fetch = time.perf_counter()
    for batch in _loader(args, args.seed):
        wait += time.perf_counter() - t_fetch
        frac = (time.perf_counter() - start) / budget
        if frac >= 1.0:
            break
        for group in opt.param_groups:  # cosine decay over the time budget
            group["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))
        losses = _step(model, opt, batch, args, gen)
        steps += 1
        seen += batch["images"].shape[0]
        if steps % 50 == 0:
            log.append({"step": steps, "seconds": round(time.perf_counter() - start, 1), **losses})
            print(json.dumps(log[-1]), flush=True)
        t_fetch = time.perf_counter()
    seconds = time.perf_counter() - start
    accuracy = evaluate(model, heldout, args.device)
    card = {
        "model": {"class": "torchbrdf.recovery.prior.MapEstimator", **model.config,
                  "parameters": sum(p.numel() for p in model.parameters()), "storage": "float16"},
        "data": {"dataset": "torchbrdf.data.MaterialStream", "source": repr(_source(args)),
                 "size": args.size, "lights": args.lights, "layout": "ring" if args.ring else "random",
                 "noise": [0.0, 0.02], "seed": args.seed,
                 "samples_seen": seen},
        "training": {"steps": steps, "batch": args.batch, "seconds": round(seconds, 1), "device": args.device,
                     "threads": args.threads, "workers": args.workers, "loader_wait_fraction": round(wait / seconds, 3),
                     "loss": f"rendering_loss + {args.map_weight} * map_loss", "lr": args.lr,
                     "torch": torch.__version__, "torchbrdf": torchbrdf.__version__,
                     "continued_from": previous},
        "heldout": {"seed": HELDOUT_SEED, "samples": args.heldout, **accuracy},
        "command": "python -m training.train_estimator " + " ".join(sys.argv[1:]),
        "log": log[-20:],
    }
    Prior(model, card).save(args.out / "estimator.pt")
    (args.out / "model_card.json").write_text(json.dumps(card, indent=1) + "\n")
    (args.out / "model_card.md").write_text(model_card_markdown(card))
    print(json.dumps(card["heldout"], indent=1))
    return card


def model_card_markdown(card: dict) -> str:
    """The card as a short Markdown page."""
    h, t, d = card["heldout"], card["training"], card["data"]
    rows = "\n".join(f"| {m} | {h[f'{m}_rmse']:.3f} | {h[f'{m}_rmse_constant']:.3f} |"
                     for m in ("base_color", "roughness", "metallic", "specular"))
    return (
        "# Map estimator: model card\n\n"
        f"U-Net ({card['model']['parameters']} parameters, width {card['model']['width']}, depth "
        f"{card['model']['depth']}), {d['lights']} image(s) -> principled maps.\n\n"
        f"Data: {d['dataset']} ({d['source']}), {d['size']}x{d['size']} samples, seed {d['seed']}, "
        f"{d['samples_seen']} samples seen.\n\n"
        f"Training: {t['steps']} steps of {t['batch']} in {t['seconds']} s on {t['device']} "
        f"({t['threads']} thread(s), {t['workers']} loader workers), loss {t['loss']}"
        + (f", continuing {prev['steps']} steps of {prev['seconds']} s" if (prev := t.get("continued_from")) else "")
        + ".\n\n"
        f"Held-out accuracy ({h['samples']} samples, dataset seed {h['seed']}):\n\n"
        "| map | RMSE | RMSE of the best constant |\n|---|---|---|\n" + rows + "\n"
        f"| normal (mean angle, deg) | {h['normal_mean_deg']:.2f} | {h['normal_mean_deg_flat']:.2f} (flat) |\n\n"
        f"Rendering loss on the held-out samples: {h['rendering_loss']:.4f}.\n\n"
        f"Command: `{card['command']}`\n"
        + (_panel_markdown(card["panel"], d["source"]) if "panel" in card else "")
    )


def _panel_markdown(panel: dict, source: str = "") -> str:
    """The card's error on recovery-panel materials (``python -m torchbrdf.bench.prior_error``)."""
    rows = "\n".join(f"| {m} | {panel[f'{m}_rmse']:.3f} | {panel[f'{m}_bias_share']:.2f} |"
                      for m in ("base_color", "roughness", "metallic", "specular"))
    seen = ("its training families, panel seeds it never saw" if "FamilySource" in source
            else "torchbrdf.capture.families, not the recipes it was trained on")
    return (
        f"\nAccuracy on the recovery panel's {panel['split']} materials ({panel['materials']} captures of "
        f"{panel['size']}x{panel['size']} px, {panel['lights']} lights; materials of {seen}):\n\n"
        "| map | RMSE | share that is each capture's mean error |\n|---|---|---|\n" + rows + "\n"
        f"| normal (mean angle, deg) | {panel['normal_mean_deg']:.2f} | |\n\n"
        f"Command: `{panel['command']}`\n"
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    args = _parser().parse_args(argv)
    if args.lights < 1 or args.minutes <= 0 or args.batch < 1:
        raise SystemExit("train_estimator: --lights and --batch must be >= 1 and --minutes > 0")
    benchmark(args) if args.benchmark else train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
