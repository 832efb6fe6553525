"""``forcegrasp plot RUN_DIR [RUN_DIR ...]``: training curves as one PNG, several runs overlaid.

Panels: the actors' episode return and success rate (mean of the last 100 episodes), the
evaluator's periodic test (deterministic policy, fixed placements) return and success rate,
SAC's critic loss and entropy coefficient, and the learner's update and ingestion rates.
Overlaying runs compares them, e.g. with and without force feedback (the paper's ablation).
"""

from __future__ import annotations

import argparse
from pathlib import Path

PANELS = (
    ("actors/return_mean_100", "episode return (actors, last 100)"),
    ("actors/success_rate_100", "success rate (actors, last 100)"),
    ("eval/score", "evaluator: test return"),
    ("eval/success_rate", "evaluator: test success rate"),
    ("sac/critic_loss", "critic loss"),
    ("sac/alpha", "entropy coefficient alpha"),
    ("learner/updates_per_s", "updates / s"),
    ("learner/ingest_per_s", "env steps ingested / s"),
)


def read_scalars(tb_dir: Path) -> dict[str, tuple[list[int], list[float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tb_dir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: ([e.step for e in acc.Scalars(tag)], [e.value for e in acc.Scalars(tag)]) for tag in acc.Tags()["scalars"]}


def read_evaluations(run_dir: Path) -> dict[str, tuple[list[int], list[float]]]:
    """The evaluator's history (every evaluated checkpoint's test score), if the run has one."""
    from forcegrasp.rundir import RunDir

    index = RunDir(run_dir).read_index()
    if index is None:
        return {}
    history = sorted(index.get("history", []), key=lambda h: h["step"])
    steps = [int(h["step"]) for h in history]
    return {"eval/score": (steps, [float(h["score"]) for h in history]),
            "eval/success_rate": (steps, [float(h["success_rate"]) for h in history])}


def run_label(run_dir: Path) -> str:
    """The run's name, with the object and force-feedback setting from its recorded config."""
    try:
        import tomllib

        from forcegrasp.rundir import RunDir

        env = tomllib.loads(RunDir(run_dir).config.read_text()).get("env", {})
        return f"{run_dir.name} ({env['object']}, force feedback {'on' if env['force_feedback'] else 'off'})"
    except (OSError, KeyError, ValueError):
        return run_dir.name


def plot_runs(run_dirs: list[Path], out: Path, title: str | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = []
    for run_dir in run_dirs:
        from forcegrasp.rundir import RunDir

        tb = RunDir(run_dir).tensorboard
        scalars = read_scalars(tb) if tb.is_dir() else {}
        if not scalars:
            raise FileNotFoundError(f"no TensorBoard scalars under {tb}")
        runs.append((run_label(run_dir), {**scalars, **read_evaluations(run_dir)}))
    fig, axes = plt.subplots(2, 4, figsize=(18, 6.5))
    for ax, (tag, label) in zip(axes.flat, PANELS):
        for name, scalars in runs:
            steps, values = scalars.get(tag, ([], []))
            ax.plot(steps, values, lw=1.2, marker="." if tag.startswith("eval/") else None, label=name)
        ax.set(title=label, xlabel="environment steps")
        ax.grid(alpha=0.3)
    if len(runs) > 1:
        axes.flat[0].legend(fontsize=8)
    fig.suptitle(title or " vs ".join(name for name, _ in runs))
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp plot", description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+", metavar="run_dir", help="run directories, e.g. runs/default")
    parser.add_argument("--out", type=Path, default=None, help="PNG path (default FIRST_RUN_DIR/curves.png)")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    try:
        out = plot_runs(args.run_dirs, args.out or args.run_dirs[0] / "curves.png", args.title)
    except FileNotFoundError as exc:
        parser.exit(2, f"forcegrasp plot: {exc}\n")
    print(f"wrote {out}")
    return 0
