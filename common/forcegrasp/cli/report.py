"""``forcegrasp report``: the paper's experiments on the shipped policies, as docs/results.md and PNGs.

Needs nothing but ``assets/policies/`` (no run folder): every policy there is tested on the
held-out ``"test"`` placements (success with 95 % intervals, the adaptation map), at 1x and 0.5x
mass with the 0.03 m tolerance, under joint-torque noise from 0 to 1 N·m, and on the paper's
three Fig. 3 placements (palm and object x against time); one successful grasp per object is
rendered as a GIF. ``--quick`` runs reduced trial counts (CI); the default is the full protocol.
Writes ``OUT/results.md``, ``OUT/results.json``, ``OUT/results/*.png`` and ``OUT/results/grasp-*.gif``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from forcegrasp import docs_dir
from forcegrasp.markdown import replace_between
from forcegrasp.report import (FIG3_OFFSETS, MASSES, NOISE_LEVELS, PAPER, POLICIES_DIR, PROTOCOLS, run_experiments,
                               shipped_policies, summarise)

OBJECT_ORDER = ("spray_bottle", "power_drill", "mug", "camera")


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


def _pooled(summary: dict, obj: str, ff: bool, kind: str, value: str = "") -> tuple[int, int] | None:
    """Successes and episodes over every seed of one object and arm."""
    rows = [r for r in summary.values() if r["object"] == obj and r["force_feedback"] == ff and value in r[kind]]
    if not rows:
        return None
    return sum(r[kind][value]["successes"] for r in rows), sum(r[kind][value]["episodes"] for r in rows)


def fig_force_feedback(summary: dict, objects: list[str], out: Path) -> Path:
    from forcegrasp.report import wilson

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for j, (ff, colour) in enumerate(((True, "tab:blue"), (False, "tab:orange"))):
        for i, obj in enumerate(objects):
            pooled = _pooled(summary, obj, ff, "held_out")
            if pooled is None:
                ax.text(i + (j - 0.5) * 0.36, 3, "not\ntrained", ha="center", fontsize=7, color=colour)
                continue
            k, n = pooled
            lo, hi = wilson(k, n)
            ax.bar(i + (j - 0.5) * 0.36, 100 * k / n, 0.34, color=colour, label=None if i else
                   ("with force feedback" if ff else "without force feedback"))
            ax.errorbar(i + (j - 0.5) * 0.36, 100 * k / n, yerr=[[max(0.0, 100 * (k / n - lo))], [max(0.0, 100 * (hi - k / n))]],
                        color="k", capsize=3, lw=1)
            for r in summary.values():  # each seed as a dot
                if r["object"] == obj and r["force_feedback"] == ff:
                    ax.plot(i + (j - 0.5) * 0.36, 100 * r["held_out"][""]["rate"], "k.", ms=4)
    ax.axhline(90, color="grey", ls=":", lw=1)
    ax.set(xticks=range(len(objects)), xticklabels=objects, ylabel="held-out success (%)", ylim=(0, 105),
           title="Success with and without force feedback (95 % intervals; dots: seeds)")
    ax.legend(fontsize=8, loc="lower right")
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
               title=f"{s.obj}\n{'with' if s.force_feedback else 'without'} FF, seed {s.meta.get('seed')}: {rate:.0%}")
        ax.title.set_fontsize(8)
    for row in axes:
        row[0].set_ylabel("dy (cm)")
    return _save(fig, out, dpi=100)


def fig_lighter(summary: dict, objects: list[str], out: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.4))
    for j, m in enumerate(MASSES):
        rates = [(_pooled(summary, o, True, "mass", f"{m:g}") or (0, 0)) for o in objects]
        ax.bar([i + (j - 0.5) * 0.36 for i in range(len(objects))], [100 * k / n if n else 0 for k, n in rates], 0.34,
               label=f"{m:g}x mass")
    ax.set(xticks=range(len(objects)), xticklabels=objects, ylabel="success (%)", ylim=(0, 105),
           title="Lighter objects, 0.03 m movement tolerance (with force feedback)")
    ax.legend(fontsize=8)
    return _save(fig, out, dpi=110)


def fig_noise(summary: dict, objects: list[str], out: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.4))
    for o in objects:
        pts = [(v, _pooled(summary, o, True, "noise", f"{v:g}")) for v in NOISE_LEVELS]
        pts = [(v, 100 * k / n) for v, p in pts if p for k, n in [p]]
        if pts:
            ax.plot(*zip(*pts), marker="o", label=o)
    ax.set(xlabel="joint-torque noise std (N·m)", ylabel="success (%)", ylim=(-3, 103),
           title="Robustness against joint-torque noise (with force feedback)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _save(fig, out, dpi=110)


def fig_trajectories(policies, results: dict, objects: list[str], out: Path) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(len(objects), len(FIG3_OFFSETS), figsize=(9, 2.3 * len(objects)), squeeze=False)
    for row, obj in zip(axes, objects):
        for col, ax in enumerate(row):
            for s in policies:
                if s.obj != obj or s.meta.get("seed") != min(p.meta.get("seed") for p in policies if p.obj == obj):
                    continue
                t = results[s.name]["trajectory"][""][col]
                colour = "tab:blue" if s.force_feedback else "tab:orange"
                tag = f"{'FF' if s.force_feedback else 'no FF'} ({'ok' if t['success'] else t['failure']})"
                ax.plot([100 * v for v in t["palm_x"]], color=colour, label=f"palm, {tag}")
                ax.plot([100 * v for v in t["object_x"]], color=colour, ls="--", label="object")
            dx, dy = FIG3_OFFSETS[col]
            ax.set_title(f"{obj}, scene {'abc'[col]}: offset ({dx:+.3f}, {dy:+.3f}) m", fontsize=8)
            ax.tick_params(labelsize=7)
            if col == 0:
                ax.set_ylabel("x (cm)", fontsize=8)
            ax.legend(fontsize=6)
    for ax in axes[-1]:
        ax.set_xlabel("step", fontsize=8)
    return _save(fig, out, dpi=100)


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
def _cell(summary: dict, obj: str, ff: bool, kind: str, value: str = "") -> str:
    from forcegrasp.report import wilson

    pooled = _pooled(summary, obj, ff, kind, value)
    if pooled is None:
        return "not trained yet"
    k, n = pooled
    lo, hi = wilson(k, n)
    return f"**{k / n:.0%}** ({lo:.0%}–{hi:.0%}, n={n})"


def results_table(summary: dict, objects: list[str]) -> list[str]:
    """The summary table: success with and without force feedback, lighter objects and torque noise
    (the page's first table, and the README's between its ``results-table`` markers)."""
    lines = ["| object | with force feedback | without | paper (with / without) | 1x mass, 0.03 m | 0.5x mass, 0.03 m | "
             "torque noise 0.5 N·m |", "|---|---|---|---|---|---|---|"]
    for o in objects:
        paper_light = PAPER["mass_1"].get(o)
        lines.append(f"| {o} | {_cell(summary, o, True, 'held_out')} | {_cell(summary, o, False, 'held_out')} | "
                     f"~90 % / < 35 %{f'; 1x: {paper_light:.0%}' if paper_light else ''} | "
                     f"{_cell(summary, o, True, 'mass', '1')} | {_cell(summary, o, True, 'mass', '0.5')} | "
                     f"{_cell(summary, o, True, 'noise', '0.5')} |")
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
    return lines + [""]


def write_page(policies, summary: dict, figures: dict, protocol_name: str, seconds: float, out: Path) -> Path:
    objects = [o for o in OBJECT_ORDER if any(s.obj == o for s in policies)]
    rel = lambda p: p.relative_to(out).as_posix()  # noqa: E731
    lines = [
        "# Results: the paper's experiments on the shipped policies",
        "",
        f"Regenerated by `forcegrasp report{' --quick' if protocol_name == 'quick' else ''}` from `assets/policies/` "
        f"alone ({protocol_name} protocol: {PROTOCOLS[protocol_name]['held_out']} held-out placements per policy, "
        f"{PROTOCOLS[protocol_name]['mass']} per mass, {PROTOCOLS[protocol_name]['noise']} per noise level; "
        f"{seconds / 60:.1f} min on this machine). Placements are the `test` stream (seed 0), never used to pick a "
        "checkpoint; actions deterministic; 95 % Wilson intervals, seeds pooled.",
        "",
        *results_table(summary, objects),
    ]
    lines += ["", f"The paper (1 M steps, 4 h on a GPU per policy): {PAPER['held_out_ff']} with force feedback, "
              f"{PAPER['held_out_noff']} without; lighter objects at 1x mass drill 73 %, mug 80 %, camera 99 % (spray "
              f"lower), at 0.5x {PAPER['mass_0.5']}; torque noise: {PAPER['noise']}.", "",
              "## The policies", "",
              "| policy | object | force feedback | seed | env steps to the pick | wall-clock (min) | recipe |",
              "|---|---|---|---:|---:|---:|---|"]
    for s in policies:
        r = s.meta.get("recipe", {})
        extra = ", ".join(f"{k}={v}" for k, v in {**r.get("overrides", {}), **{k: v for k, v in r.get("actor", {}).items()
                                                                                if k == "demo_episodes" and v}}.items())
        lines.append(f"| `{s.path.name}` | {s.obj} | {'yes' if s.force_feedback else 'no'} | {s.meta.get('seed')} | "
                     f"{s.meta.get('env_steps', 0):,} | {s.meta.get('wall_clock_min', 0):g} | "
                     f"{r.get('name', '?')}{' + ' + extra if extra else ''} |")
    captions = {
        "fig4": "Success with and without force feedback (the paper's Fig. 4)",
        "fig6": "Adaptation maps: held-out placements in the ±2 cm square, success (green circle) and failure (red triangle) (Fig. 6)",
        "fig7": "Lighter objects: 1x and 0.5x mass with the 0.03 m movement tolerance (Fig. 7)",
        "fig8": "Robustness against joint-torque noise, 0 to 1 N·m (Fig. 8)",
        "fig3": "Palm (solid) and object (dashed) x against time for the paper's three placements, with and without force feedback (Fig. 3)",
    }
    lines += ["", *arms_section(out.parent / "experiments" / "probes" / "ff_information.json"), "## Figures", ""]
    for key, caption in captions.items():
        if key in figures:
            lines += [f"**{caption}.**", "", f"![{key}]({rel(figures[key])})", ""]
    videos = [p for k, p in figures.items() if k.startswith("grasp-")]
    if videos:
        lines += ["**One successful held-out grasp per object** (its first force-feedback policy), pre-grasp to "
                  "goal at a quarter speed, seen by the object's camera (`forcegrasp eval POLICY --video out.gif` "
                  "renders one):", ""]
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
    args = parser.parse_args(argv)
    policies = shipped_policies(args.policies)
    if not policies:
        print(f"error: no shipped policies in {args.policies}", file=sys.stderr)
        return 2
    name = "quick" if args.quick else "full"
    print(f"{len(policies)} policies, {name} protocol, {args.workers} workers", flush=True)
    t0 = time.perf_counter()
    results = run_experiments(policies, PROTOCOLS[name], args.workers, log=lambda s: print(s, flush=True))
    summary = summarise(policies, results)
    figs_dir = args.out / "results"
    figs_dir.mkdir(parents=True, exist_ok=True)
    objects = [o for o in OBJECT_ORDER if any(s.obj == o for s in policies)]
    figures = {
        "fig4": fig_force_feedback(summary, objects, figs_dir / "force-feedback.png"),
        "fig6": fig_adaptation(policies, results, figs_dir / "adaptation.png"),
        "fig7": fig_lighter(summary, objects, figs_dir / "lighter.png"),
        "fig8": fig_noise(summary, objects, figs_dir / "torque-noise.png"),
        "fig3": fig_trajectories(policies, results, objects, figs_dir / "trajectories.png"),
    }
    if not args.no_videos:
        for o in objects:
            first = next(s for s in policies if s.obj == o and s.force_feedback) if any(
                s.obj == o and s.force_feedback for s in policies) else None
            if first is not None and (p := grasp_video(first, figs_dir / f"grasp-{o}.gif")) is not None:
                figures[f"grasp-{o}"] = p
    seconds = time.perf_counter() - t0
    (args.out / "results.json").write_text(json.dumps(
        {"protocol": name, "counts": PROTOCOLS[name], "seconds": round(seconds, 1), "policies": summary,
         "episodes": {n: {k: v for k, v in r.items() if k != "trajectory"} for n, r in results.items()}}, indent=1))
    page = write_page(policies, summary, figures, name, seconds, args.out)
    table = results_table(summary, objects)
    print("\n".join(table))
    if replace_between(args.out.parent / "README.md", "results-table", table):
        print(f"updated the results table of {args.out.parent / 'README.md'}")
    print(f"wrote {page}, {args.out / 'results.json'} and {len(figures)} figures in {figs_dir} ({seconds:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
