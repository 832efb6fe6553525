"""The figures of ``forcegrasp report``: the paper's Figs. 3, 4, 6, 7 and 8 from the summary.

Each figure that compares series has a ``draw_*`` function that draws on one matplotlib Axes (what
the tests inspect) and a ``fig_*`` function that writes it as a PNG. Fig. 4 has a bar per observation
arm (`forcegrasp.report.ARMS`, always the same colours) and the scripted approach told and blind
as lines; Figs. 7 and 8 show the paper's arm (`TABLE_I`) of the policies trained with randomisation
beside the same arm trained at 5x mass only (a `reference` summary, when the report has both
families) and, in Fig. 7, the scripted approach told the offset. The generalist figure sets policies of several objects beside
the one-object policies, per object, and zero-shot where a policy never saw the object.
"""

from __future__ import annotations

from pathlib import Path

from forcegrasp.report import (ARMS, FIG3_OFFSETS, MASSES, NOISE_LEVELS, TABLE_I, arm_of, arm_rows, pooled,
                               wilson)

ARM_COLOURS = {TABLE_I: "tab:blue", (False, "measured"): "tab:orange", (True, "commanded"): "tab:green",
               (False, "commanded"): "tab:purple"}
ARM_TAGS = {TABLE_I: "FF", (False, "measured"): "no FF", (True, "commanded"): "FF, cmd",
            (False, "commanded"): "no FF, cmd"}  # Fig. 3's crowded legends
SCRIPTED_STYLES = {"told": {"color": "k", "ls": "--", "lw": 1.2, "label": "scripted, told the offset"},
                   "blind": {"color": "grey", "ls": ":", "lw": 1.6, "label": "scripted, blind (offset 0)"}}
REFERENCE_LABEL = "trained at 5x only"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out: Path, dpi: int) -> Path:
    """Lay out, write and close one figure."""
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    _plt().close(fig)
    return out


def _once(label: str, seen: set) -> str:
    """`label` the first time, then matplotlib's hidden label: one legend entry per series."""
    if label in seen:
        return "_nolegend_"
    seen.add(label)
    return label


def _reference_rows(reference: dict, obj: str) -> list[dict]:
    """The reference family's rows of Table I's arm for one object (a `summarise` dict)."""
    return arm_rows(reference, obj, TABLE_I)


def _scripted_cell(scripted: dict, obj: str, mode: str, kind: str, value: str = "") -> dict | None:
    return scripted.get(obj, {}).get(mode, {}).get(kind, {}).get(value)


def draw_force_feedback(ax, summary: dict, objects: list[str], scripted: dict) -> None:
    """Fig. 4: per object a bar per arm that has policies (95 % Wilson intervals, seeds as dots; an
    arm without policies for that object says so), and the scripted approach told and blind as
    lines across the object's bars: what aim alone achieves, and what no object information does."""
    arms = [a for a in ARMS if any(arm_of(r) == a for r in summary.values())]
    width, seen = 0.8 / max(1, len(arms)), set()
    for i, obj in enumerate(objects):
        for j, arm in enumerate(arms):
            x, colour = i + (j - (len(arms) - 1) / 2) * width, ARM_COLOURS[arm]
            rows = arm_rows(summary, obj, arm)
            if not rows:
                ax.text(x, 3, "not\ntrained", ha="center", fontsize=6, color=colour)
                continue
            k, n = pooled(rows, "held_out")
            lo, hi = wilson(k, n)
            ax.bar(x, 100 * k / n, 0.94 * width, color=colour, label=_once(ARMS[arm], seen))
            ax.errorbar(x, 100 * k / n, yerr=[[max(0.0, 100 * (k / n - lo))], [max(0.0, 100 * (hi - k / n))]],
                        color="k", capsize=3, lw=1)
            ax.plot([x] * len(rows), [100 * r["held_out"][""]["rate"] for r in rows], "k.", ms=4)
        for mode, style in SCRIPTED_STYLES.items():
            if (cell := _scripted_cell(scripted, obj, mode, "held_out")) is not None:
                ax.plot([i - 0.45, i + 0.45], [100 * cell["rate"]] * 2, zorder=3,
                        **{**style, "label": _once(style["label"], seen)})
    ax.axhline(90, color="0.75", lw=0.8, zorder=0, label="the paper with force feedback: about 90 %")
    ax.set(xticks=range(len(objects)), xticklabels=objects, ylabel="held-out success (%)", ylim=(0, 105),
           title="Held-out success per observation arm (95 % intervals; dots: seeds)")
    handles, labels = ax.get_legend_handles_labels()
    arms_first = sorted(range(len(labels)), key=lambda i: labels[i] not in ARMS.values())
    ax.legend([handles[i] for i in arms_first], [labels[i] for i in arms_first], fontsize=7, loc="upper center",
              bbox_to_anchor=(0.5, -0.12), ncol=3)


def fig_force_feedback(summary: dict, objects: list[str], out: Path, scripted: dict) -> Path:
    fig, ax = _plt().subplots(figsize=(8, 4.2))
    draw_force_feedback(ax, summary, objects, scripted)
    return _save(fig, out, dpi=110)


def fig_adaptation(policies, results: dict, out: Path) -> Path:
    plt = _plt()
    cols = min(4, len(policies))
    rows = -(-len(policies) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.9 * rows), squeeze=False)
    for ax in axes.flat[len(policies):]:
        ax.axis("off")
    for ax, s in zip(axes.flat, policies):
        eps = results[s.name]["held_out"][""]
        for e in eps:
            x, y = 100 * e["offset"][0], 100 * e["offset"][1]
            ax.plot(x, y, "o" if e["success"] else "^", ms=4, mfc="none" if e["success"] else "tab:red",
                    mec="tab:green" if e["success"] else "tab:red")
        rate = sum(e["success"] for e in eps) / len(eps)
        ax.set(xlim=(-2.2, 2.2), ylim=(-2.2, 2.2), aspect="equal", xlabel="dx (cm)",
               title=f"{s.obj}, seed {s.meta.get('seed')}: {rate:.0%}\n{ARMS[s.arm]}")
        ax.title.set_fontsize(7)
    for row in axes:
        row[0].set_ylabel("dy (cm)")
    return _save(fig, out, dpi=100)


def draw_lighter(ax, summary: dict, objects: list[str], scripted: dict, reference: dict | None) -> None:
    """Fig. 7: the paper's arm at 1x and 0.5x mass (filled bars), beside the policies trained at 5x
    only (hatched, where `reference` is given), with the scripted approach told the offset (a marker)."""
    per_mass = 2 if reference else 1
    width, seen = 0.8 / (len(MASSES) * per_mass), set()
    for j, m in enumerate(MASSES):
        value, colour = f"{m:g}", f"C{j}"
        for i, obj in enumerate(objects):
            centre = i + (j - (len(MASSES) - 1) / 2) * width * per_mass
            x = centre - (per_mass - 1) * width / 2
            k, n = pooled(arm_rows(summary, obj, TABLE_I), "mass", value) or (0, 0)
            ax.bar(x, 100 * k / n if n else 0, 0.94 * width, color=colour, label=_once(f"{value}x mass", seen))
            if reference:
                k, n = pooled(_reference_rows(reference, obj), "mass", value) or (0, 0)
                ax.bar(x + width, 100 * k / n if n else 0, 0.94 * width, facecolor="none", edgecolor=colour,
                       hatch="///", label=_once(f"{value}x mass, {REFERENCE_LABEL}", seen))
            if (cell := _scripted_cell(scripted, obj, "told", "mass", value)) is not None:
                ax.plot(centre, 100 * cell["rate"], "kD", ms=5, label=_once(SCRIPTED_STYLES["told"]["label"], seen))
    ax.set(xticks=range(len(objects)), xticklabels=objects, ylabel="success (%)", ylim=(0, 105),
           title=f"Lighter objects, 0.03 m movement tolerance: {ARMS[TABLE_I]}")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3)


def fig_lighter(summary: dict, objects: list[str], out: Path, scripted: dict, reference: dict | None) -> Path:
    fig, ax = _plt().subplots(figsize=(7, 4))
    draw_lighter(ax, summary, objects, scripted, reference)
    return _save(fig, out, dpi=110)


def _noise_curve(rows: list[dict]) -> list[tuple[float, float]]:
    """(noise std, pooled success in %) where the rows ran that level."""
    pts = [(v, pooled(rows, "noise", f"{v:g}")) for v in NOISE_LEVELS]
    return [(v, 100 * p[0] / p[1]) for v, p in pts if p]


def draw_noise(ax, summary: dict, objects: list[str], reference: dict | None) -> None:
    """Fig. 8: the paper's arm per object against torque noise, and the policies trained at 5x only
    (dashed, same colour, where `reference` is given)."""
    for i, o in enumerate(objects):
        if pts := _noise_curve(arm_rows(summary, o, TABLE_I)):  # shrinking markers: overlaps stay visible
            ax.plot(*zip(*pts), marker="osD^v<>p"[i % 8], ms=max(3, 9 - 1.5 * i), color=f"C{i}", label=o)
        if reference and (pts := _noise_curve(_reference_rows(reference, o))):
            ax.plot(*zip(*pts), marker=".", ls="--", color=f"C{i}", label=f"{o}, {REFERENCE_LABEL}")
    ax.set(xlabel="joint-torque noise std (N·m)", ylabel="success (%)", ylim=(-3, 103),
           title=f"Robustness against joint-torque noise: {ARMS[TABLE_I]}")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    ax.grid(alpha=0.3)


def fig_noise(summary: dict, objects: list[str], out: Path, reference: dict | None) -> Path:
    fig, ax = _plt().subplots(figsize=(6.5, 4.6))
    draw_noise(ax, summary, objects, reference)
    return _save(fig, out, dpi=110)


def fig_trajectories(policies, results: dict, objects: list[str], out: Path) -> Path:
    """Fig. 3: palm and object x against time on the three scenes, each arm's first seed."""
    plt = _plt()
    fig, axes = plt.subplots(len(objects), len(FIG3_OFFSETS), figsize=(9, 2.3 * len(objects)), squeeze=False)
    for row, obj in zip(axes, objects):
        firsts: dict = {}
        for s in policies:  # sorted by object, arm, seed
            if s.obj == obj:
                firsts.setdefault(s.arm, s)
        for col, ax in enumerate(row):
            for arm, s in firsts.items():
                t = results[s.name]["trajectory"][""][col]
                tag = f"{ARM_TAGS[arm]} ({'ok' if t['success'] else t['failure']})"
                ax.plot([100 * v for v in t["palm_x"]], color=ARM_COLOURS[arm], label=f"palm, {tag}")
                ax.plot([100 * v for v in t["object_x"]], color=ARM_COLOURS[arm], ls="--", label="object")
            dx, dy = FIG3_OFFSETS[col]
            ax.set_title(f"{obj}, scene {'abc'[col]}: offset ({dx:+.3f}, {dy:+.3f}) m", fontsize=8)
            ax.tick_params(labelsize=7)
            if col == 0:
                ax.set_ylabel("x (cm)", fontsize=8)
            ax.legend(fontsize=6)
    for ax in axes[-1]:
        ax.set_xlabel("step", fontsize=8)
    return _save(fig, out, dpi=100)


GENERALIST_SERIES = (("one policy per object (Table I's arm)", "tab:blue"),
                     ("one policy for several objects", "tab:cyan"),
                     ("zero-shot: a policy that never saw it", "tab:red"))


def generalist_cells(summary: dict, generalists: dict, obj: str) -> list[tuple[int, int] | None]:
    """Successes and episodes on ``obj`` of the three `GENERALIST_SERIES`, seeds pooled (None: none)."""
    def pool(cells):
        return (sum(c["successes"] for c in cells), sum(c["episodes"] for c in cells)) if cells else None

    return [pooled(arm_rows(summary, obj, TABLE_I), "held_out"),
            pool([r["object"][obj] for r in generalists.values() if obj in r["object"]]),
            pool([r["unseen"][obj] for r in generalists.values() if obj in r["unseen"]])]


def draw_generalists(ax, summary: dict, generalists: dict) -> list[str]:
    """Per object, held-out success of the specialists, of the generalists trained on it and of those
    that never saw it (zero-shot), with 95 % Wilson intervals; the objects drawn."""
    objects = list(dict.fromkeys(o for r in generalists.values() for o in [*r["object"], *r["unseen"]]))
    width, seen = 0.8 / len(GENERALIST_SERIES), set()
    for i, obj in enumerate(objects):
        for j, ((label, colour), cell) in enumerate(zip(GENERALIST_SERIES, generalist_cells(summary, generalists, obj))):
            if cell is None:
                continue
            (k, n), x = cell, i + (j - 1) * width
            lo, hi = wilson(k, n)
            ax.bar(x, 100 * k / n, 0.94 * width, color=colour, label=_once(label, seen))
            ax.errorbar(x, 100 * k / n, yerr=[[max(0.0, 100 * (k / n - lo))], [max(0.0, 100 * (hi - k / n))]],
                        color="k", capsize=3, lw=1)
    ax.axhline(90, color="0.75", lw=0.8, zorder=0)
    ax.set(xticks=range(len(objects)), xticklabels=objects, ylabel="held-out success (%)", ylim=(0, 105),
           title="One policy per object, one for several, and zero-shot (95 % intervals)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3)
    return objects


def fig_generalists(summary: dict, generalists: dict, out: Path) -> Path:
    fig, ax = _plt().subplots(figsize=(8, 4.2))
    draw_generalists(ax, summary, generalists)
    return _save(fig, out, dpi=110)
