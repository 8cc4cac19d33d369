"""Figure for docs/recovery.md: the schedules' time per capture against held-out PSNR.

``python docs/recovery_schedules.py ROWS.json [docs/recovery_schedules.png]``

``ROWS.json``: ``python -m torchbrdf.bench.recovery --part schedules --json ROWS.json``. One line
per capture through its schedules (fast, default, thorough): the median CPU time per capture
(bars: min to max; the process's CPU seconds, steadier than wall time on a shared machine, wall
time where a row has none) against the held-out mean PSNR (filled) and worst-light PSNR (hollow).
"""

import json
import statistics
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def main(rows_json: str, png: str = "docs/recovery_schedules.png") -> None:
    with open(rows_json, encoding="utf-8") as fh:
        run = json.load(fh)
    rows = run["rows"]
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    for k, case in enumerate(dict.fromkeys(r["case"] for r in rows)):
        mine = [r for r in rows if r["case"] == case]
        secs = [r.get("cpu_seconds") or r["seconds"] for r in mine]
        t = [statistics.median(x) for x in secs]
        err = [[ti - min(x) for ti, x in zip(t, secs)], [max(x) - ti for ti, x in zip(t, secs)]]
        colour = f"C{k}"
        ax.errorbar(t, [r["heldout_mean_db"] for r in mine], xerr=err, color=colour, marker="o", capsize=3,
                    label=f"{case}: held-out mean")
        ax.plot(t, [r["heldout_worst_db"] for r in mine], color=colour, marker="o", markerfacecolor="white",
                linestyle="--", label=f"{case}: worst light")
        for ti, r in zip(t, mine):
            ax.annotate(r["schedule"], (ti, r["heldout_mean_db"]), textcoords="offset points", xytext=(4, 5),
                        fontsize=8, color=colour)
    kind = "CPU" if all(r.get("cpu_seconds") for r in rows) else "wall"
    ax.set_xlabel(f"{kind} time per capture (s; {run['size']}² pixels, {run['threads']} thread(s))")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("Recovery schedules: time against held-out accuracy")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    print(f"wrote {png}")


if __name__ == "__main__":
    main(*sys.argv[1:])
