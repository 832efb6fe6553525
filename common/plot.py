"""``forcegrasp plot RUN_DIR``: training curves of a run as one PNG, from its TensorBoard scalars.

Panels: the actors' episode return and success rate (mean of the last 100 episodes), SAC's
critic loss and entropy coefficient, and the learner's update and ingestion rates.
"""

from __future__ import annotations

import argparse
from pathlib import Path

PANELS = (
    ("actors/return_mean_100", "episode return (last 100)"),
    ("actors/success_rate_100", "success rate (last 100)"),
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


def plot_run(run_dir: Path, out: Path, title: str | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scalars = read_scalars(run_dir / "tb")
    if not scalars:
        raise FileNotFoundError(f"no TensorBoard scalars under {run_dir / 'tb'}")
    fig, axes = plt.subplots(2, 3, figsize=(14, 6.5))
    for ax, (tag, label) in zip(axes.flat, PANELS):
        steps, values = scalars.get(tag, ([], []))
        ax.plot(steps, values, lw=1.2)
        ax.set(title=label, xlabel="environment steps")
        ax.grid(alpha=0.3)
    fig.suptitle(title or run_dir.name)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp plot", description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run directory, e.g. runs/default")
    parser.add_argument("--out", type=Path, default=None, help="PNG path (default RUN_DIR/curves.png)")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    out = plot_run(args.run_dir, args.out or args.run_dir / "curves.png", args.title)
    print(f"wrote {out}")
    return 0
