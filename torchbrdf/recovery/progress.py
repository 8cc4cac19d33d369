"""Following a recovery as it runs: stage messages, the progress bar, and where time and loss went.

:class:`StageProgress` writes the stage messages and the tqdm bar; :func:`fit_losses` is the
loss they (and ``loss.png``) show; :func:`stage_seconds` sums a run's history per stage.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import torch

from torchbrdf.recovery.engine import Recovery

__all__ = ["StageProgress", "fit_losses", "stage_seconds", "last_fit_loss"]


_STAGE_TEXT = {
    "dual": "both hypotheses side by side (dielectric: metallic 0; metal: metallic 1), LM on base colour, "
            "specular, roughness and normal; each pixel's class is chosen at the end",
    "polish": "each pixel's chosen class only, LM plus neighbour propagation",
    "all": "every light, the held-out validation light included",
}


class StageProgress:
    """Stage messages and a bar whose ETA comes from per-stage costs.

    One iteration of a stage costs about (pixels × hypotheses) work units; the bar advances
    in those units, so its average rate (tqdm ``smoothing=0``) predicts the later, larger
    stages instead of jumping when a level four times the size starts.
    """

    def __init__(self, plan: list[tuple[int, str, int]], stage: int, it: int, enabled: bool,
                 write: Callable[[str], None]):
        self.plan = plan
        self.units = [s * s * (2 if kind == "dual" else 1) for s, kind, _ in plan]
        self.total_iters = sum(p[2] for p in plan)
        # Where a resumed run starts: by stage and iteration, not by iterations run (a converged
        # stage skipped its rest).
        done = sum(u * p[2] for u, p in zip(self.units[:stage], plan[:stage]))
        done += it * self.units[stage] if stage < len(plan) else 0
        self.done = done  # work units
        self.enabled = enabled
        self.bar = None
        self.write = write
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=sum(u * p[2] for u, p in zip(self.units, plan)), initial=done, smoothing=0,
                            file=sys.stderr, desc="recover", dynamic_ncols=True,
                            bar_format="{desc} {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")
            bar = self.bar
            self.write = lambda msg: bar.write(msg, file=sys.stderr)  # tqdm.write defaults to stdout
            self.write("fit loss (bar and loss.png) = mean squared log residual per pixel, training light "
                       "and channel; in the dual stages, of each pixel's better hypothesis")
        self.stage: int | None = None

    def stage_start(self, stage: int, rec: Recovery) -> None:
        """Announce ``stage`` once, when its first iteration is about to run."""
        if not self.enabled or stage == self.stage:
            return
        self.stage = stage
        size, kind, n = self.plan[stage]
        extra = ""
        if kind != "dual" and _state(rec).get("metal") is not None:
            extra = f" ({100 * float(_state(rec)['metal'].mean()):.0f}% of pixels metal)"
        start = ("" if kind == "all" else "; its first iteration also propagates neighbours' parameters and "
                 "searches normals, so it takes longer")
        upto = "up to " if size == self.plan[-1][0] and rec.cfg.converge_tol > 0 else ""
        if self.bar is not None:  # the last stage's final iteration first, then this stage's header
            self.bar.refresh()
            self.bar.set_description_str(f"stage {stage + 1}/{len(self.plan)} ({kind} {size}²) starting",
                                         refresh=False)
        self.write(f"stage {stage + 1}/{len(self.plan)}: {size}×{size} px, {upto}{n} iterations — "
                   f"{kind}: {_STAGE_TEXT.get(kind, kind)}{extra}{start}")

    def iteration_done(self, rec: Recovery) -> None:
        """Advance the bar by the iteration ``rec`` just ran (a converged stage's rest at once)."""
        if self.bar is None:
            return
        st = _state(rec)
        h = st["history"][-1]
        stage = min(st["stage"], len(self.plan)) - (1 if st["it"] == 0 else 0)
        stage = max(0, min(stage, len(self.plan) - 1))
        fit = h.get("fit", {})
        loss = fit.get("best", fit.get("chosen", h["loss"]))
        self.bar.set_description_str(f"iteration {st['global_it']}/{self.total_iters} "
                                     f"({h['stage']} {h['size']}², fit loss {loss:.3g})", refresh=False)
        self.bar.update(self.units[stage] * (1 + h.get("skipped", 0)))  # a converged stage's rest at once

    def close(self) -> None:
        """End the bar."""
        if self.bar is not None:
            self.bar.close()


def _state(rec: Recovery) -> dict[str, Any]:
    """The solver's state dict (set by ``init_state`` or ``load_checkpoint``)."""
    return rec.state


def fit_losses(rec: Recovery) -> dict:
    """Data-only fit loss of the current state on the training lights.

    The quantity the bar and ``loss.png`` show: per hypothesis and per pixel's better one in a dual stage, the
    chosen class otherwise. Mean over pixels of the squared log residual per light and channel.
    It is the last LM step's (``rec.fit_cost``, no extra render); a state without one is rendered.
    """
    st = _state(rec)
    fc = rec.fit_cost
    if len(fc) == len(st["theta"]) and all(v.shape[0] == st["theta"][0].shape[0] for v in fc.values()):
        return rec.fit_summary()
    size, kind, _ = rec.plan[min(st["stage"], len(rec.plan) - 1)]
    data = rec.data(size)
    n = max(1, len(data.train_idx) * 3)

    def cost(theta, metal):
        r = data.residual(theta, metal, data.train_idx, rec.cfg.model)
        return torch.nan_to_num((r * r).sum(-1), nan=float("inf")) / n

    if len(st["theta"]) == 2:
        ones = torch.ones_like(st["lam"][0])
        cd, cm = cost(st["theta"][0], 0 * ones), cost(st["theta"][1], ones)
        best = float(torch.minimum(cd, cm).mean())  # each pixel's better hypothesis
        return {"dielectric": float(cd.mean()), "metal": float(cm.mean()), "best": best}
    return {"chosen": float(cost(st["theta"][0], st["metal"]).mean())}


def stage_seconds(history: list) -> list[dict]:
    """Where a run's time went: one entry per stage run, in order.

    ``history``: the solver's per-iteration records (``size``, ``stage`` and, from runs that
    time their iterations, ``seconds``: the iteration with its stage's end work and the next
    stage's setup). Consecutive records of one (size, stage) form an entry. Returns
    ``[{"size", "stage", "iterations", "seconds"}]``; a stage with any iteration without a time
    (one run before a resume from a checkpoint of an older version) has ``seconds`` None.
    """
    out: list[dict] = []
    for h in history:
        if not out or (out[-1]["size"], out[-1]["stage"]) != (h["size"], h["stage"]):
            out.append({"size": h["size"], "stage": h["stage"], "iterations": 0, "seconds": 0.0})
        e = out[-1]
        e["iterations"] += 1
        t = h.get("seconds")
        e["seconds"] = None if t is None or e["seconds"] is None else e["seconds"] + t
    return out


def last_fit_loss(history: list) -> float | None:
    """The last iteration's fit loss (each pixel's better hypothesis, or its chosen class), or None."""
    if not history or "fit" not in history[-1]:
        return None
    f = history[-1]["fit"]
    return float(f.get("best", f.get("chosen", float("nan"))))
