"""The robustness bar of ``forcegrasp report``: which settings a policy must hold and how well
(`BAR`), which it misses (`misses`), and the page's section that judges every policy tested under
the bar's conditions, beside the scripted approach told the offset (`robustness_section`)."""

from __future__ import annotations

from forcegrasp.report import BAR_CONDITIONS, PROTOCOLS, SCRIPTED_SKIPS, TABLE_I, arm_of, wilson

#: The robustness bar: the least success a policy must show per setting (``""``: the trained
#: conditions, the held-out experiment); the 1 cm conditions are reported without a bar.
BAR = {"": 0.95, "1x_3cm": 0.90, "0.5x_3cm": 0.90, "noise_0.5": 0.90, "jitter_3cm": 0.90}
CONDITION_HEADS = {"1x_3cm": "1x mass, 3 cm", "0.5x_3cm": "0.5x mass, 3 cm", "1x_1cm": "1x mass, 1 cm",
                   "0.5x_1cm": "0.5x mass, 1 cm", "noise_0.5": "torque noise 0.5 N·m", "jitter_3cm": "±3 cm jitter"}


def _bar_cell(cell: dict | None, bar: float | None) -> str:
    """A success rate with its interval; in italics where it misses its bar."""
    if cell is None:
        return "–"
    lo, hi = wilson(cell["successes"], cell["episodes"])
    text = f"{cell['rate']:.0%} [{lo:.0%}–{hi:.0%}]"
    return f"*{text}*" if bar is not None and cell["rate"] < bar else text


def misses(row: dict) -> list[str]:
    """The settings of the bar (`BAR`) where a `summarise` row falls short, as words; [] if it meets it."""
    cells = {"": row["held_out"].get("")} | {c: row.get("condition", {}).get(c) for c in BAR if c}
    return [f"{CONDITION_HEADS.get(c, 'trained conditions')}: {cell['rate']:.0%}" if cell else
            f"{CONDITION_HEADS.get(c, 'trained conditions')}: not measured"
            for c, cell in cells.items() if cell is None or cell["rate"] < BAR[c]]


def robustness_section(summary: dict, objects: list[str], scripted: dict) -> list[str]:
    """The bar, policy by policy: every policy tested under the bar's conditions (`bar_policies`:
    Table I's arm, randomised first) under the trained conditions and each of `BAR_CONDITIONS` (95 %
    Wilson intervals, misses in italics), the scripted approach told the offset per object, and
    which policies meet the bar."""
    rows = {n: r for n, r in summary.items() if arm_of(r) == TABLE_I and r.get("condition")}
    if not rows:
        return []
    heads = ["trained conditions"] + [CONDITION_HEADS[c] for c in BAR_CONDITIONS]
    n = PROTOCOLS["full"]["condition"]
    lines = ["## Robustness, policy by policy", "",
             f"Every policy of Table I's arm on the held-out placements (trained conditions: {PROTOCOLS['full']['held_out']}; "
             f"each other condition: {n} in the full protocol) under each test condition of `forcegrasp.conditions`, "
             "deterministic actions, 95 % Wilson intervals. The bar: at least 95 % under the trained conditions and "
             "90 % at 1x and 0.5x mass with the paper's 3 cm tolerance, under 0.5 N·m of torque noise and at ±3 cm "
             "(the 1 cm figures have none); *italics* miss it. `trained under` says whether the policy trained "
             "under randomised conditions (the default recipe; the policies table above names the ranges) or only "
             "at the paper's 5x mass; Figs. 7 and 8 set the two families side by side.", "",
             "| policy | trained under | minutes | " + " | ".join(heads) + " |", "|---|---|---:|" + "---:|" * len(heads)]
    ordered = sorted(rows.items(), key=lambda kv: (not kv[1].get("randomised"), objects.index(kv[1]["object"])
                                                   if kv[1]["object"] in objects else len(objects), kv[0]))
    for name, r in ordered:
        cells = [_bar_cell(r["held_out"].get(""), BAR[""])] + [
            _bar_cell(r.get("condition", {}).get(c), BAR.get(c)) for c in BAR_CONDITIONS]
        lines.append(f"| `{name}` | {'randomised' if r.get('randomised') else '5x only'} | "
                     f"{r.get('wall_clock_min') or 0:g} | " + " | ".join(cells) + " |")
    for o in (o for o in objects if any(r["object"] == o for r in rows.values())):
        if o in scripted and "told" in scripted[o]:
            told = scripted[o]["told"]
            cells = [_bar_cell(told.get("held_out", {}).get(""), None)] + [
                "= trained" if c in SCRIPTED_SKIPS else _bar_cell(told.get("condition", {}).get(c), None)
                for c in BAR_CONDITIONS]
            lines.append(f"| scripted, told the offset: {o} | – | – | " + " | ".join(cells) + " |")
    robust = {name: misses(r) for name, r in ordered if r.get("randomised")}
    if robust:
        met = [name for name, m in robust.items() if not m]
        said = f"{len(met)} of the {len(robust)} policies trained with randomisation meet every bar"
        short = [f"`{name}` ({'; '.join(m)})" for name, m in robust.items() if m]
        lines += ["", said + (f"; short of it: {', '.join(short)}." if short else ".")]
    return lines + [""]
