"""Resumable single-process SAC training on a FunctionalGrasp task (``forcegrasp train``).

One env, one learner, in one process: the reference the distributed actor-learner services
are measured against, and the way to train on one machine today. Everything lives in a run
directory so a killed run resumes where its last checkpoint left it:

    runs/<name>/checkpoint.safetensors   learner state (networks, optimisers, alpha, counters)
    runs/<name>/replay.npz               replay snapshot (atomic)
    runs/<name>/policy.safetensors       the current policy file (what actors and users load)
    runs/<name>/progress.csv             one row per evaluation
    runs/<name>/tb/                      TensorBoard scalars
    runs/<name>/curve.png                return and success rate against steps
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from forcegrasp.env import ACTION_LAYOUT, FunctionalGraspEnv, observation_layout
from forcegrasp.evaluation import evaluate, placements
from forcegrasp.policy_file import PolicyMetadata
from forcegrasp.replay import ReplayBuffer
from forcegrasp.sac import SAC, SACConfig


@dataclass
class TrainConfig:
    object_name: str = "mug"
    force_feedback: bool = True
    mass_scale: float = 5.0
    jitter: float = 0.02
    run_dir: str = "runs/mug"
    checkpoint_every: int = 2_000  # env steps (the paper evaluates every 2,000 steps)
    eval_episodes: int = 10  # fixed placements, the same for every evaluation
    log_every: int = 500
    sac: SACConfig = field(default_factory=SACConfig)


class Trainer:
    def __init__(self, config: TrainConfig, log=print):
        self.cfg = config
        self.log = log
        self.dir = Path(config.run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        env_kwargs = dict(force_feedback=config.force_feedback, mass_scale=config.mass_scale, jitter=config.jitter)
        self.env = FunctionalGraspEnv(config.object_name, **env_kwargs)
        self.eval_env = FunctionalGraspEnv(config.object_name, **env_kwargs)
        self.obs_dim = self.env.observation_space.shape[0]
        self.step = 0
        self.episodes = 0
        ckpt = self.dir / "checkpoint.safetensors"
        if ckpt.exists():
            self.sac, extra = SAC.load_checkpoint(ckpt)
            self.buffer = ReplayBuffer.load(self.dir / "replay.npz")
            self.step, self.episodes = int(extra["step"]), int(extra["episodes"])
            self.log(f"resumed {self.dir} at step {self.step} ({len(self.buffer)} transitions in replay)")
        else:
            self.sac = SAC(self.obs_dim, 7, config.sac)
            self.buffer = ReplayBuffer(self.obs_dim, 7, min(config.sac.buffer_size, config.sac.total_steps))
            (self.dir / "config.json").write_text(json.dumps(asdict(config), indent=2, default=list))
        self.rng = np.random.default_rng(config.sac.seed + self.step)

    def metadata(self, score: float | None = None) -> PolicyMetadata:
        env = self.env
        return PolicyMetadata(
            obs_layout=list(observation_layout(self.cfg.force_feedback)),
            action_layout=list(ACTION_LAYOUT),
            hidden=self.cfg.sac.hidden,
            object_name=self.cfg.object_name,
            force_feedback=self.cfg.force_feedback,
            training_steps=self.step,
            eval_score=score,
            action_low=list(-env._action_scale),
            action_high=list(env._action_scale),
        )

    def checkpoint(self, score: float | None) -> None:
        """Replay first, learner last: the learner file marks a complete checkpoint."""
        self.buffer.save(self.dir / "replay.npz")
        self.sac.policy(self.metadata(score)).save(self.dir / "policy.safetensors")
        self.sac.save_checkpoint(self.dir / "checkpoint.safetensors", extra={"step": self.step, "episodes": self.episodes})

    def run(self, total_steps: int) -> list[dict]:
        from torch.utils.tensorboard import SummaryWriter

        cfg, sac_cfg = self.cfg, self.cfg.sac
        writer = SummaryWriter(str(self.dir / "tb"))
        history = self._read_history()
        obs, _ = self.env.reset(seed=sac_cfg.seed + self.step)
        episode_return, recent, updates_due, metrics = 0.0, [], 0.0, {}
        t0, steps0 = time.perf_counter(), self.step
        while self.step < total_steps:
            if self.step < sac_cfg.learning_starts:
                action = self.rng.uniform(-1.0, 1.0, 7).astype(np.float32)
            else:
                action = self.sac.act(obs)
            next_obs, reward, terminated, truncated, info = self.env.step(action)
            self.buffer.add(obs, action, reward, next_obs, float(terminated))
            episode_return += float(reward)
            obs = next_obs
            self.step += 1
            if terminated or truncated:
                self.episodes += 1
                recent = (recent + [(episode_return, info["success"])])[-20:]
                writer.add_scalar("train/episode_return", episode_return, self.step)
                writer.add_scalar("train/success", float(info["success"]), self.step)
                obs, _ = self.env.reset()
                episode_return = 0.0
            if self.step >= sac_cfg.learning_starts:
                updates_due += sac_cfg.updates_per_step
                while updates_due >= 1.0:
                    want = self.step % 100 == 0 and updates_due < 2.0
                    out = self.sac.update(self.buffer.sample(sac_cfg.batch_size, self.rng), metrics=want)
                    metrics = out or metrics
                    updates_due -= 1.0
                if self.step % 100 == 0 and metrics:
                    for k, v in metrics.items():
                        writer.add_scalar(f"learner/{k}", v, self.step)
            if self.step % cfg.log_every == 0:
                rate = (self.step - steps0) / (time.perf_counter() - t0)
                mean_ret = np.mean([r for r, _ in recent]) if recent else float("nan")
                succ = np.mean([s for _, s in recent]) if recent else float("nan")
                writer.add_scalar("train/steps_per_s", rate, self.step)
                self.log(
                    f"step {self.step:>8}/{total_steps}  {rate:6.1f} steps/s  episodes {self.episodes:>5}  "
                    f"return(20) {mean_ret:8.1f}  success(20) {succ:4.0%}  alpha {self.sac.alpha:.3f}"
                )
            if self.step % cfg.checkpoint_every == 0 or self.step == total_steps:
                # The evaluator's protocol: deterministic policy, the same seeded placements each time.
                scored = evaluate(self.eval_env, lambda o: self.sac.act(o, deterministic=True),
                                  placements(cfg.sac.seed, cfg.eval_episodes, cfg.jitter,
                                             clear=self.eval_env.is_clear))
                result = {"step": self.step, "return": scored.score, "success_rate": scored.success_rate}
                history.append(result)
                writer.add_scalar("eval/return", result["return"], self.step)
                writer.add_scalar("eval/success_rate", result["success_rate"], self.step)
                self._append_history(result)
                self.checkpoint(result["return"])
                self.log(f"eval at step {self.step}: return {result['return']:.1f}, success {result['success_rate']:.0%}; checkpoint written")
        writer.close()
        plot_curve(history, self.dir / "curve.png", title=f"{cfg.object_name} (force feedback {'on' if cfg.force_feedback else 'off'})")
        return history

    def _read_history(self) -> list[dict]:
        path = self.dir / "progress.csv"
        if not path.exists():
            return []
        with path.open() as f:
            return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]

    def _append_history(self, row: dict) -> None:
        path = self.dir / "progress.csv"
        new = not path.exists()
        with path.open("a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=["step", "return", "success_rate"])
            if new:
                w.writeheader()
            w.writerow({k: row[k] for k in ("step", "return", "success_rate")})


def plot_curve(history: list[dict], path: Path, title: str = "") -> None:
    if not history:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot(steps, [h["return"] for h in history], marker="o")
    ax[0].set(xlabel="environment steps", ylabel="evaluation return", title=title)
    ax[1].plot(steps, [h["success_rate"] for h in history], marker="o", color="tab:green")
    ax[1].set(xlabel="environment steps", ylabel="success rate", ylim=(-0.05, 1.05))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def config_from_args(args) -> TrainConfig:
    sac = replace(
        SACConfig(),
        total_steps=args.steps,
        learning_starts=args.learning_starts,
        seed=args.seed,
        batch_size=args.batch_size,
        hidden=tuple(args.hidden),
    )
    return TrainConfig(
        object_name=args.object,
        force_feedback=not args.no_force_feedback,
        mass_scale=args.mass_scale,
        run_dir=args.run_dir or f"runs/{args.object}",
        checkpoint_every=args.checkpoint_every,
        eval_episodes=args.eval_episodes,
        log_every=args.log_every,
        sac=sac,
    )
