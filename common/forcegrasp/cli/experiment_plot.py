"""``forcegrasp experiment --plot``: several experiment records overlaid, against minutes and steps."""

from __future__ import annotations

from pathlib import Path


def object_set(record: dict) -> str:
    """``mug``, or ``mug+camera`` for a run of several objects."""
    return "+".join(record.get("objects") or [record["object"]])


def curves(records: list[dict]) -> list[dict]:
    """Every curve of the plot: ``group`` (its colour: the label, with the object set when the
    records differ in it, and the object for a run of several objects, which draws one per object),
    ``seed``, ``kind`` (``best``: the evaluator's pick, ``latest``) and ``points`` (minute, the
    latest snapshot's environment steps, held-out success) per tested mark."""
    differ = len({object_set(r) for r in records}) > 1
    out = []
    for r in records:
        base = f"{r['label']} {object_set(r)}" if differ else r["label"]
        parts = [(f"{base}: {o}", o) for o in r["objects"]] if len(r.get("objects") or []) > 1 else [(base, None)]
        for group, obj in parts:
            for kind in ("best", "latest"):
                points = [(m["minute"], m["steps"].get("latest"),
                           (m["test"][kind]["objects"][obj] if obj else m["test"][kind])["success_rate"])
                          for m in r["marks"] if kind in m["test"]]
                if points:
                    out.append({"group": group, "seed": r["seed"], "kind": kind, "points": points})
    return out


def plot_records(records: list[dict], out: Path) -> Path:
    """Held-out success of the evaluator's pick (solid) and the latest snapshot (dotted) against
    wall-clock minutes and environment steps (`curves`); one colour per group, one marker per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = curves(records)
    groups = list(dict.fromkeys(c["group"] for c in series))
    colours = {g: plt.cm.tab10(i % 10) for i, g in enumerate(groups)}
    markers = "osD^vP*X"
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for c in series:
        seeds = sorted({x["seed"] for x in series if x["group"] == c["group"]})
        style = dict(color=colours[c["group"]], marker=markers[seeds.index(c["seed"]) % len(markers)], ms=4)
        ls, lw = ("-", 1.8) if c["kind"] == "best" else (":", 1.0)
        name = f"{c['group']} s{c['seed']}" if c["kind"] == "best" else None
        pts = c["points"]
        axes[0].plot([p[0] for p in pts], [100 * p[2] for p in pts], ls=ls, lw=lw, label=name, **style)
        axes[1].plot([p[1] or 0 for p in pts], [100 * p[2] for p in pts], ls=ls, lw=lw, **style)
    axes[0].set_xlabel("wall-clock minutes (2-core machine, evaluator beside training)")
    axes[1].set_xlabel("environment steps trained by the mark")
    axes[0].set_ylabel("held-out success %")
    for ax in axes:
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ax.axhline(90, color="grey", lw=0.8, ls="--")
    objects = sorted({object_set(r) for r in records})
    fig.suptitle(f"{', '.join(objects)}: evaluator's pick (solid) and latest snapshot (dotted) on "
                 f"{records[0]['episodes']} held-out placements")
    axes[0].legend(fontsize=8, loc="lower right")  # curves rise to the top left
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
