"""``forcegrasp experiment --plot``: several experiment records overlaid, against minutes and steps."""

from __future__ import annotations

from pathlib import Path


def plot_records(records: list[dict], out: Path) -> Path:
    """Held-out success of the evaluator's pick (solid) and the latest snapshot (dotted) against
    wall-clock minutes and environment steps; one colour per label, one marker per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    several_objects = len({r["object"] for r in records}) > 1

    def group(r: dict) -> str:  # one colour per configuration (and object, when they differ)
        return f"{r['label']} {r['object']}" if several_objects else r["label"]

    labels = list(dict.fromkeys(group(r) for r in records))
    colours = {lab: plt.cm.tab10(i % 10) for i, lab in enumerate(labels)}
    markers = "osD^vP*X"
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for r in records:
        seeds = sorted({x["seed"] for x in records if group(x) == group(r)})
        style = dict(color=colours[group(r)], marker=markers[seeds.index(r["seed"]) % len(markers)], ms=4)
        for kind, ls, lw in (("best", "-", 1.8), ("latest", ":", 1.0)):
            # x: the environment steps trained by the mark (the latest snapshot's), for both curves
            pts = [(m["minute"], m["steps"].get("latest"), m["test"][kind]["success_rate"]) for m in r["marks"]
                   if kind in m["test"]]
            if not pts:
                continue
            name = f"{group(r)} s{r['seed']}" if kind == "best" else None
            axes[0].plot([p[0] for p in pts], [100 * p[2] for p in pts], ls=ls, lw=lw, label=name, **style)
            axes[1].plot([p[1] or 0 for p in pts], [100 * p[2] for p in pts], ls=ls, lw=lw, **style)
    axes[0].set_xlabel("wall-clock minutes (2-core machine, evaluator beside training)")
    axes[1].set_xlabel("environment steps trained by the mark")
    axes[0].set_ylabel("held-out success %")
    for ax in axes:
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ax.axhline(90, color="grey", lw=0.8, ls="--")
    objects = sorted({r["object"] for r in records})
    fig.suptitle(f"{', '.join(objects)}: evaluator's pick (solid) and latest snapshot (dotted) on "
                 f"{records[0]['episodes']} held-out placements")
    axes[0].legend(fontsize=8, loc="lower right")  # curves rise to the top left
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
