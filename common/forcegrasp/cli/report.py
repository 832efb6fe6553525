"""``forcegrasp report``: the paper's experiments on the shipped policies, as docs/results.md and PNGs.

Needs nothing but ``assets/policies/`` (no run folder): every policy there is tested on the
held-out ``"test"`` placements (success with 95 % intervals, the adaptation map), at 1x and 0.5x
mass with the 0.03 m tolerance, under joint-torque noise from 0 to 1 N·m, and on the paper's
three Fig. 3 placements (palm and object x against time), and the scripted approach told and
blind on the same held-out and lighter placements per object; the policies of Table I's arm and the
scripted approach told the offset also under each condition of the robustness bar (`BAR`); one
successful grasp per object is rendered as a GIF. The results table, the bar and Figs. 6-8 report
the policies trained with randomisation (the default recipe), beside those trained at the paper's
fixed conditions; the observation-arm ablation (Figs. 3-4) compares the fixed-condition family,
where every arm trained alike. A policy of several objects is tested on each of its objects and zero-shot on
the paper's others (the generalist section, beside the one-object policies of Table I's arm).
``--reuse`` carries over OUT/results.json's episodes of every policy whose file is unchanged
(same protocol), so adding a policy costs its own episodes only. ``--quick`` runs reduced trial
counts (CI); the default is the full protocol.
Writes ``OUT/results.md``, ``OUT/results.json``, ``OUT/results/*.png`` (`report_figures`) and
``OUT/results/grasp-*.gif``. The probes of what each arm sees (a record beside OUT's parent, the
repository) join the page where present.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from forcegrasp import docs_dir
from forcegrasp.cli.report_figures import (_scripted_cell as scripted_cell, fig_adaptation, fig_force_feedback,
                                           fig_generalists, fig_lighter, fig_noise, fig_trajectories)
from forcegrasp.cli.report_bar import CONDITION_HEADS, robustness_section
from forcegrasp.markdown import replace_between
from forcegrasp.report import (ARMS, PAPER, PAPER_OBJECTS, POLICIES_DIR, PROTOCOLS, SCRIPTED_MODES,
                               SCRIPTED_SKIPS, TABLE_I, ablation_rows, arm_rows, carried_over, file_digest,
                               pooled, robust_and_reference, run_experiments, shipped_policies, wilson)
from forcegrasp.report_summary import summarise, summarise_generalists, summarise_scripted


def report_objects(policies) -> list[str]:
    """The objects of the shipped policies: the paper's four in its order, then the others by name."""
    have = {o for s in policies for o in s.objects}
    return [o for o in PAPER_OBJECTS if o in have] + sorted(have - set(PAPER_OBJECTS))
#: A record the page reads relative to OUT's parent (docs/.. is the repository); left out when absent.
PROBE_RECORD = Path("experiments/probes/ff_information.json")


def grasp_video(shipped, out: Path, tries: int = 10) -> Path | None:
    """The first successful held-out episode of `shipped` among the first `tries` test placements
    (seed 0) as a GIF (`forcegrasp.video`: the object's camera, a quarter speed): what
    ``forcegrasp eval POLICY --video out.gif`` writes when the first placement succeeds."""
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.evaluation import placements
    from forcegrasp.policy import Policy
    from forcegrasp.video import SPEED, output_size, record_episode, step_fps, write_video

    policy = Policy.load(shipped.path)
    env = FunctionalGraspEnv.for_policy(policy.metadata)
    width, height, stride = output_size(".gif", None, None, None)
    for p in placements(0, tries, env.jitter, "test", clear=env.is_clear):
        frames, result = record_episode(env, policy, p, width, height, stride)
        if result.success:
            write_video(out, frames, step_fps(env) * SPEED / stride)
            return out
    return None


# ---------------------------------------------------------------------------------- the page
def _cell(summary: dict, obj: str, arm: tuple[bool, str], kind: str, value: str = "") -> str:
    counts = pooled(arm_rows(summary, obj, arm), kind, value)
    if counts is None:
        return "not trained yet"
    k, n = counts
    lo, hi = wilson(k, n)
    return f"**{k / n:.0%}** ({lo:.0%}–{hi:.0%}, n={n})"


def _scripted_cell(scripted: dict, obj: str) -> str:
    """The scripted approach's held-out success, told / blind."""
    if obj not in scripted:
        return "not run"
    return " / ".join(f"{scripted[obj][mode]['held_out']['']['rate']:.0%}" for mode in SCRIPTED_MODES)


TABLE_CONDITIONS = ("1x_3cm", "0.5x_3cm", "noise_0.5", "jitter_3cm")  # the bar's, in the summary table


def _told(scripted: dict, obj: str, kind: str, value: str = "") -> str:
    cell = scripted_cell(scripted, obj, "told", kind, value)
    return "–" if cell is None else f"{cell['rate']:.0%}"


def results_table(summary: dict, objects: list[str], scripted: dict) -> list[str]:
    """The summary table (the page's first, and the README's between its ``results-table``
    markers): Table I's arm under the trained conditions and the bar's others, seeds pooled, for
    the policies trained with randomisation where there are any (`robust_and_reference`), beside
    the scripted approach told the offset on the same placements and the paper."""
    rows, _ = robust_and_reference(summary)
    lines = ["| object | trained conditions | " + " | ".join(CONDITION_HEADS[c] for c in TABLE_CONDITIONS)
             + " | scripted, told the offset | paper |", "|---|" + "---|" * (len(TABLE_CONDITIONS) + 3)]
    for o in (o for o in objects if arm_rows(rows, o, TABLE_I)):
        paper_light = PAPER["mass_1"].get(o)
        paper = f"~90 %{f'; 1x: {paper_light:.0%}' if paper_light else ''}" if o in PAPER_OBJECTS else "–"
        told = " / ".join([_told(scripted, o, "held_out")] + [
            "=" if c in SCRIPTED_SKIPS else _told(scripted, o, "condition", c) for c in TABLE_CONDITIONS])
        lines.append(f"| {o} | {_cell(rows, o, TABLE_I, 'held_out')} | "
                     + " | ".join(_cell(rows, o, TABLE_I, "condition", c) for c in TABLE_CONDITIONS)
                     + f" | {told} | {paper} |")
    return lines


def arms_section(probe: Path) -> list[str]:
    """What each observation arm carries of the torques, contact and object offset: the held-out R^2
    of `bench/ff_information.py`'s probes, from its JSON record (empty when there is none)."""
    if not probe.is_file():
        return []
    rows = json.loads(probe.read_text())
    first = rows[0]
    lines = ["## What each arm sees", "",
             f"Held-out R² of a linear (ridge) probe from what each observation arm sees, on {first['episodes']} "
             f"episodes per object driven by {first['actions']} actions (`python bench/ff_information.py --json "
             f"experiments/probes/{probe.name}`; 1 = fully recoverable, ≤ 0 = nothing beyond the mean). The `timing` row knows only the "
             "step and the commanded h.", "",
             "| object | arm | observed | torques | hand contact | fingertip contacts | object offset |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['object']} | {r['arm']} | {r['obs_dim']} | {r['torques']:.2f} | {r['hand_contact']:.2f} | "
                     f"{r['fingertip_contacts']:.2f} | {r['object_offset']:.2f} |")
    blind = [r for r in rows if r["arm"] == "commanded only"]
    if blind:  # why its contact R² is not zero while it sees nothing of the object
        lo, hi = ({k: f(r[k] for r in blind) for k in ("object_offset", "hand_contact", "fingertip_contacts")}
                  for f in (min, max))
        offset = "nothing of" if hi["object_offset"] <= 0.05 else "some of"
        lines += ["", f"Commanded only recovers {offset} the object offset (R² {lo['object_offset']:.2f} to "
                  f"{hi['object_offset']:.2f}). Its contact R² ({lo['hand_contact']:.2f} to {hi['hand_contact']:.2f} "
                  f"for the hand, {lo['fingertip_contacts']:.2f} to {hi['fingertip_contacts']:.2f} for the fingertips) "
                  "is what the hand's own commanded motion predicts: the actions decide when the fingers close on "
                  "wherever the object is, and the observations are the same for every offset under the same actions "
                  "(`tests/test_proprioception.py`), so this arm can know when it is likely touching, never where "
                  "the object is."]
    return lines + [""]


def _pooled_rate(summary: dict, obj: str, arm: tuple[bool, str]) -> str | None:
    counts = pooled(arm_rows(summary, obj, arm), "held_out")
    if counts is None:
        return None
    (k, n), (lo, hi) = counts, wilson(*counts)
    return f"{k / n:.0%} [{lo:.0%}–{hi:.0%}]"


def ablation_section(summary: dict, objects: list[str], scripted: dict) -> list[str]:
    """The four observation arms per object on the same held-out placements (`ablation_rows`: every
    arm trained at the same fixed conditions), beside the scripted approach told and blind, and what
    they show, worded from these numbers and the env's design."""
    summary = ablation_rows(summary)
    lines = ["## The four arms", "",
             "Held-out success (95 % Wilson interval, seeds pooled) of every observation arm shipped, all trained at "
             "the paper's fixed conditions (5x mass, no noise; each file's recipe is in the table of shipped "
             "policies), beside the scripted straight approach told the true offset and blind, on the same placements.",
             "", "| object | " + " | ".join(ARMS.values()) + " | scripted told / blind |",
             "|---|" + "---:|" * (len(ARMS) + 1)]
    for o in objects:
        lines.append(f"| {o} | " + " | ".join(_pooled_rate(summary, o, arm) or "–" for arm in ARMS)
                     + f" | {_scripted_cell(scripted, o)} |")
    torques_only = {o: r for o in objects if (r := _pooled_rate(summary, o, (True, "commanded")))}
    blind_arm = {o: r for o in objects if (r := _pooled_rate(summary, o, (False, "commanded")))}
    said = []
    if torques_only:
        said.append("With commanded proprioception and the torques, force reaches the policy through the torque sensors "
                    "alone, and it grasps " + ", ".join(f"the {o} {r}" for o, r in torques_only.items())
                    + ": the torques carry what the grasp needs.")
    if blind_arm:
        said.append("Commanded only sees nothing that depends on the object: under deterministic actions its "
                    "observations are the same for every placement, so it plays one open-loop trajectory, and its "
                    "success (" + ", ".join(f"the {o} {r}" for o, r in blind_arm.items()) + ") is the share of the "
                    "jitter square that trajectory happens to grasp. Compare it with the blind scripted approach "
                    "(a straight approach to the nominal pose), not with the arms that feel the object.")
        rates = {o: [pooled(arm_rows(summary, o, arm), "held_out") for arm in (TABLE_I, (False, "commanded"))]
                 for o in blind_arm}
        gaps = {o: full[0] / full[1] - blind[0] / blind[1] for o, (full, blind) in rates.items() if full}
        if gaps:
            said.append("What force information is worth within the paper's ±2 cm is the gap between Table I's arm "
                        "and commanded only: " + ", ".join(f"the {o} {100 * g:.0f} points" for o, g in gaps.items())
                        + ".")
    measured_only = {o: r for o in objects if (r := _pooled_rate(summary, o, (False, "measured")))}
    if measured_only:
        said.append("Measured only is the paper's ablation but not an arm without force here: every joint is a position "
                    "servo, so the measured joint angles beside the commanded targets carry most of the torque signal "
                    "(the probe above), and it grasps " + ", ".join(f"the {o} {r}" for o, r in measured_only.items())
                    + ".")
    return lines + ["", " ".join(said), ""]


def _trained_under(env: dict) -> str:
    """A sidecar's training conditions in words: its randomisation ranges, or the fixed mass."""
    ranges = []
    if mass := env.get("mass_scale_range"):
        ranges.append(f"mass {mass[0]:g}-{mass[1]:g}x")
    if noise := env.get("torque_noise_range"):
        ranges.append(f"torque noise {noise[0]:g}-{noise[1]:g} N·m")
    if jitter := env.get("jitter_range"):
        ranges.append(f"jitter ±{jitter[0] * 100:g}-{jitter[1] * 100:g} cm")
    return ", ".join(ranges) if ranges else f"{env.get('mass_scale', 5.0):g}x mass"


def _rate_cell(cell: dict | None, note: str = "") -> str:
    if cell is None:
        return "–"
    lo, hi = wilson(cell["successes"], cell["episodes"])
    return f"{note}{cell['rate']:.0%} [{lo:.0%}–{hi:.0%}]"


def generalists_section(generalists: dict, summary: dict, figure: Path | None, rel) -> list[str]:
    """The policies of several objects: held-out success on each object they trained on, zero-shot
    on each they never saw (with what went wrong), beside the one-object policies (Table I's arm)."""
    if not generalists:
        return []
    objects = [o for o in PAPER_OBJECTS if any(o in r["objects"] or o in r["unseen"] for r in generalists.values())]
    objects += sorted({o for r in generalists.values() for o in r["objects"]} - set(objects))
    lines = ["## One policy for several objects", "",
             "Each policy trained on several objects (`env.objects`) is tested on the same held-out placements "
             "as the one-object policies, on every object it trained on, and *zero-shot* (in italics) on each of "
             "the paper's objects it never saw. Success with 95 % Wilson intervals; `worst` is the minimum over "
             "the objects it trained on, which the evaluator ranks by.", "",
             "| policy | seed | wall-clock (min) | " + " | ".join(objects) + " | worst |",
             "|---|---:|---:|" + "---:|" * (len(objects) + 1)]
    for name, r in generalists.items():
        cells = [_rate_cell(r["object"].get(o)) if o in r["object"] else
                 f"*{_rate_cell(r['unseen'].get(o))}*" if o in r["unseen"] else "–" for o in objects]
        worst = min(r["object"].values(), key=lambda c: c["rate"]) if r["object"] else None
        lines.append(f"| `{name}` | {r['seed']} | {r['wall_clock_min'] or 0:g} | " + " | ".join(cells)
                     + f" | {_rate_cell(worst)} |")
    specialists = [_cell(robust_and_reference(summary)[0], o, TABLE_I, "held_out") for o in objects]
    lines.append("| one policy per object (Table I's arm, seeds pooled) | | | " + " | ".join(specialists) + " | |")
    failures = [f"{o}: " + ", ".join(f"{n} {k}" for k, n in sorted(r["unseen"][o]["failures"].items(), key=lambda kv: -kv[1]))
                for r in generalists.values() for o in r["unseen"] if r["unseen"][o]["failures"]]
    if failures:
        lines += ["", "What the zero-shot failures were (`info[\"failure\"]`, per unseen object and policy): "
                  + "; ".join(failures) + "."]
    if figure is not None:
        lines += ["", "**One policy per object, one for several, and zero-shot on an unseen object, per object.**",
                  "", f"![generalists]({rel(figure)})"]
    return lines + [""]


def write_page(policies, summary: dict, figures: dict, protocol_name: str, seconds: float, out: Path,
               scripted: dict | None = None, generalists: dict | None = None, reused: int = 0) -> Path:
    objects = report_objects([s for s in policies if not s.multi])
    rel = lambda p: p.relative_to(out).as_posix()  # noqa: E731
    lines = [
        "# Results: the paper's experiments on the shipped policies",
        "",
        f"Regenerated by `forcegrasp report{' --quick' if protocol_name == 'quick' else ''}` from `assets/policies/` "
        f"alone ({protocol_name} protocol: {PROTOCOLS[protocol_name]['held_out']} held-out placements per policy, "
        f"{PROTOCOLS[protocol_name]['mass']} per mass, {PROTOCOLS[protocol_name]['noise']} per noise level, "
        f"{PROTOCOLS[protocol_name]['condition']} per condition of the robustness bar; "
        f"{seconds / 60:.1f} min on this machine"
        f"{f', carrying over the episodes of {reused} unchanged policies from the previous report' if reused else ''}"
        "). Placements are the `test` stream (seed 0), never used to pick a "
        "checkpoint; actions deterministic; 95 % Wilson intervals, seeds pooled. The table shows the policies of the "
        "paper's arm (joint torques and measured proprioception) trained with the default recipe, under randomised "
        "mass, torque noise and (where the policies table says so) placement width; the scripted approach told the "
        "offset runs on the same placements (trained / 1x / 0.5x / noise, which cannot change it / ±3 cm).",
        "",
        *results_table(summary, objects, scripted or {}),
    ]
    lines += ["", f"The paper (1 M steps, 4 h on a GPU per policy, trained at 5x mass): {PAPER['held_out_ff']} with force feedback, "
              f"{PAPER['held_out_noff']} without; lighter objects at 1x mass drill 73 %, mug 80 %, camera 99 % (spray "
              f"lower), at 0.5x {PAPER['mass_0.5']}; torque noise: {PAPER['noise']}. The scripted straight "
              "approach (`forcegrasp.scripted`) on the same placements: told the true offset, what a well-aimed "
              "straight grasp achieves; blind (offset 0), the best an arm without object information can do.", "",
              "## The policies", "",
              "| policy | object | observation arm | trained under | seed | env steps to the pick | wall-clock (min) | recipe |",
              "|---|---|---|---|---:|---:|---:|---|"]
    for s in policies:
        r = s.meta.get("recipe", {})
        extra = ", ".join(f"{k}={v}" for k, v in {**r.get("overrides", {}), **{k: v for k, v in r.get("actor", {}).items()
                                                                                if k == "demo_episodes" and v}}.items())
        lines.append(f"| `{s.path.name}` | {', '.join(s.objects)} | {ARMS[s.arm]} | "
                     f"{_trained_under(s.meta.get('env', {}))} | {s.meta.get('seed')} | "
                     f"{s.meta.get('env_steps', 0):,} | {s.meta.get('wall_clock_min', 0):g} | "
                     f"{r.get('name', '?')}{' + ' + extra if extra else ''} |")
    captions = {
        "fig4": "Held-out success per observation arm, all trained at the paper's fixed conditions, with the "
                "scripted approach told (dashed) and blind (dotted) across each object's bars (the paper's Fig. 4)",
        "fig6": "Adaptation maps of the table's policies: held-out placements in the ±2 cm square, success (green "
                "circle) and failure (red triangle) (Fig. 6)",
        "fig7": "Lighter objects: 1x and 0.5x mass with the 0.03 m movement tolerance (Fig. 7), the table's policies; "
                "hatched, where shown: the same arm trained at 5x mass only; diamonds: the scripted approach told "
                "the offset",
        "fig8": "Robustness against joint-torque noise, 0 to 1 N·m (Fig. 8), the table's policies; dashed, where "
                "shown: the same arm trained at 5x mass only",
        "fig3": "Palm (solid) and object (dashed) x against time for the paper's three placements, each arm's first "
                "seed, all trained at the paper's fixed conditions (Fig. 3)",
    }
    lines += ["", *robustness_section(summary, objects, scripted or {}),
              *arms_section(out.parent / PROBE_RECORD), *ablation_section(summary, objects, scripted or {}),
              *generalists_section(generalists or {}, summary, figures.get("generalists"), rel), "## Figures", ""]
    for key, caption in captions.items():
        if key in figures:
            lines += [f"**{caption}.**", "", f"![{key}]({rel(figures[key])})", ""]
    videos = [p for k, p in figures.items() if k.startswith("grasp-")]
    if videos:
        lines += ["**One successful held-out grasp per object** (its first policy with torques and measured "
                  "proprioception, Table I), pre-grasp to goal at a quarter speed, seen by the object's camera "
                  "(`forcegrasp eval POLICY --video out.gif` renders one):", ""]
        lines += [f"![{p.stem}]({rel(p)})" for p in videos] + [""]
    page = out / "results.md" if out.is_dir() else out
    page.write_text("\n".join(lines))
    return page


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp report", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced trial counts (CI)")
    parser.add_argument("--policies", type=Path, default=POLICIES_DIR, help=f"folder of shipped policies ({POLICIES_DIR})")
    parser.add_argument("--out", type=Path, default=docs_dir(), help="folder for results.md (default: docs/)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes (default: all cores)")
    parser.add_argument("--no-videos", "--no-strips", dest="no_videos", action="store_true",
                        help="skip the rendered grasp GIFs")
    parser.add_argument("--reuse", action="store_true",
                        help="carry over OUT/results.json's episodes of the policies whose file is unchanged")
    args = parser.parse_args(argv)
    try:
        policies = shipped_policies(args.policies)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not policies:
        print(f"error: no shipped policies in {args.policies}", file=sys.stderr)
        return 2
    name = "quick" if args.quick else "full"
    print(f"{len(policies)} policies, {name} protocol, {args.workers} workers", flush=True)
    t0 = time.perf_counter()
    previous_file = args.out / "results.json"
    previous = json.loads(previous_file.read_text()) if args.reuse and previous_file.is_file() else None
    done, scripted_done = carried_over(previous, policies, name)
    singles = [s for s in policies if not s.multi]
    objects = report_objects(singles)
    scripted_done = {o: cells for o, cells in scripted_done.items() if o in objects}
    if args.reuse:
        print(f"carrying over the episodes of {len(done)} unchanged policies and the scripted rows of "
              f"{len(scripted_done)} objects from {previous_file}", flush=True)
    results, scripted_eps = run_experiments(policies, PROTOCOLS[name], args.workers, log=lambda s: print(s, flush=True),
                                            done=done, scripted_done=scripted_done)
    summary = summarise(policies, results)
    scripted = summarise_scripted(scripted_eps, scripted_done)
    generalists = summarise_generalists(policies, results)
    robust, reference = robust_and_reference(summary)
    table_arm = [s for s in singles if s.name in robust and s.arm == TABLE_I]
    table_objects = [o for o in objects if any(s.obj == o for s in table_arm)]
    ablation = ablation_rows(summary)
    figs_dir = args.out / "results"
    figs_dir.mkdir(parents=True, exist_ok=True)
    figures = {
        "fig4": fig_force_feedback(ablation, report_objects([s for s in singles if s.name in ablation]),
                                   figs_dir / "force-feedback.png", scripted),
        "fig6": fig_adaptation(table_arm, results, figs_dir / "adaptation.png"),
        "fig7": fig_lighter(robust, table_objects, figs_dir / "lighter.png", scripted, reference),
        "fig8": fig_noise(robust, table_objects, figs_dir / "torque-noise.png", reference),
        "fig3": fig_trajectories([s for s in singles if s.name in ablation], results, objects,
                                 figs_dir / "trajectories.png"),
    }
    if generalists:
        figures["generalists"] = fig_generalists(summary, generalists, figs_dir / "generalists.png")
    if not args.no_videos:
        for o in objects:
            first = next((s for s in singles if s.obj == o and s.arm == TABLE_I), None)
            if first is not None and (p := grasp_video(first, figs_dir / f"grasp-{o}.gif")) is not None:
                figures[f"grasp-{o}"] = p
    seconds = time.perf_counter() - t0
    (args.out / "results.json").write_text(json.dumps(
        {"protocol": name, "counts": PROTOCOLS[name], "seconds": round(seconds, 1), "reused": sorted(done),
         "digests": {s.name: file_digest(s.path) for s in policies}, "policies": summary,
         "scripted": scripted, "generalists": generalists,
         "episodes": {n: {k: v for k, v in r.items() if k != "trajectory"} for n, r in results.items()}}, indent=1))
    page = write_page(policies, summary, figures, name, seconds, args.out, scripted, generalists, len(done))
    table = results_table(summary, objects, scripted)
    print("\n".join(table))
    if replace_between(args.out.parent / "README.md", "results-table", table):
        print(f"updated the results table of {args.out.parent / 'README.md'}")
    print(f"wrote {page}, {args.out / 'results.json'} and {len(figures)} figures in {figs_dir} ({seconds:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
