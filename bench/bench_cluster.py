"""End-to-end training throughput: the local cluster against stable-baselines3 SAC, same env,
same machine, measured one after the other in one run.

- SB3 at its own defaults: ``SAC("MlpPolicy", env, batch_size=256, train_freq=1, gradient_steps=1)``
  (one update per step), networks [256, 256]; and, when the recipe's update-to-data ratio is
  below 1, SB3 at the same ratio (``train_freq=round(1/ratio)``). Its rate is timed from the first
  update to the end (random warm-up excluded). SB3 has no asymmetric critic: its critic sees
  the 77 observations only (a little less work than ours).
- ForceGrasp: ``forcegrasp up --no-evaluator`` (learner + actors as processes on loopback; SB3
  evaluates nothing either) with the recipe asked for (``--recipe``, default the default
  ``fast``); the rate is read from the learner's stats over a window after learning started.
  The training rate is min(env steps ingested/s, updates/s / ratio): both are printed.

    python bench/bench_cluster.py --seconds 60 --sb3-steps 1500                  # the default recipe
    python bench/bench_cluster.py --seconds 60 --sb3-steps 1500 --recipe paper   # 1 update per step
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
import time
from pathlib import Path


from forcegrasp.protocol import Keys, decode_stats
from forcegrasp.recipes import RECIPES
from forcegrasp.sac import SACConfig
from forcegrasp.transport import QueueSubscriber, close_session, free_tcp_port, open_session

WARMUP = 1000


def bench_sb3(object_name: str, steps: int, train_freq: int = 1) -> float:
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback

    from forcegrasp.env import FunctionalGraspEnv

    class Clock(BaseCallback):
        def __init__(self):
            super().__init__()
            self.t_start = None

        def _on_step(self) -> bool:
            if self.num_timesteps == WARMUP + 1:  # (SB3 updates from the first step past learning_starts)
                self.t_start = time.perf_counter()
            if self.num_timesteps % 250 == 0:
                print(f"  sb3: {self.num_timesteps}/{WARMUP + steps} steps", flush=True)
            return True

    env = FunctionalGraspEnv(object_name)
    model = SAC("MlpPolicy", env, batch_size=256, learning_starts=WARMUP, train_freq=train_freq, gradient_steps=1,
                policy_kwargs={"net_arch": [256, 256]}, seed=0, device="cpu", verbose=0)
    clock = Clock()
    model.learn(total_timesteps=WARMUP + steps, callback=clock)
    return steps / (time.perf_counter() - clock.t_start)


def bench_cluster(object_name: str, seconds: float, actors: int, envs: int, recipe: str) -> tuple[float, float]:
    port = free_tcp_port()
    with tempfile.TemporaryDirectory() as tmp:
        run = "bench"
        cmd = [sys.executable, "-m", "forcegrasp.cli", "up", "--no-evaluator", "--stop-after", str(seconds + 60),
               "--set", f"run.name={run}", "--set", f"run.output_dir={tmp}", "--set", f"env.object={object_name}",
               "--set", f"learner.recipe={recipe}", "--set", f"actor.num_actors={actors}", "--set", f"actor.envs_per_actor={envs}",
               "--set", f'network.learner_listen=["tcp/127.0.0.1:{port}"]', "--set", "learner.stats_every_s=1.0",
               "--set", f"learner.sac.learning_starts={WARMUP}", "--set", "learner.checkpoint_every=1000000000"]
        proc = subprocess.Popen(cmd, stdout=open(Path(tmp) / "up.log", "w"), stderr=subprocess.STDOUT)
        session = open_session([], [f"tcp/127.0.0.1:{port}"])
        sub = QueueSubscriber(session, Keys(run).stats("learner", "0"), maxsize=1024, put_timeout=0.0)
        samples = []
        try:
            deadline = time.monotonic() + seconds + 120
            while time.monotonic() < deadline:
                payload = sub.get(timeout=1.0)
                if payload is None:
                    continue
                v = decode_stats(payload).values
                if v["updates"] > 0:
                    samples.append((time.monotonic(), v["ingested"], v["updates"]))
                    print(f"  cluster: {v['ingested']} steps ingested, {v['updates']} updates", flush=True)
                    if samples[-1][0] - samples[0][0] >= seconds:
                        break
        finally:
            sub.close()
            close_session(session)
            proc.send_signal(2)
            proc.wait(timeout=60)
    (t0, n0, u0), (t1, n1, u1) = samples[0], samples[-1]
    return (n1 - n0) / (t1 - t0), (u1 - u0) / (t1 - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--seconds", type=float, default=60.0, help="cluster measuring window")
    parser.add_argument("--sb3-steps", type=int, default=1500, help="SB3 steps timed after its warm-up")
    parser.add_argument("--actors", type=int, default=2)
    parser.add_argument("--envs", type=int, default=4)
    parser.add_argument("--recipe", default="fast", choices=sorted(RECIPES), help="ForceGrasp's SAC preset")
    args = parser.parse_args()
    utd = dataclasses.replace(SACConfig(), **RECIPES[args.recipe]).updates_per_step
    sb3_runs = {"stable-baselines3 SAC, its defaults (1 update/step)": 1}
    if utd < 1.0:
        sb3_runs[f"stable-baselines3 SAC, {utd:g} updates/step"] = round(1 / utd)
    rows = []
    for name, freq in sb3_runs.items():
        print(f"{name}, one process:", flush=True)
        rate = bench_sb3(args.object, args.sb3_steps, freq)
        print(f"  sb3: {rate:.1f} training steps/s", flush=True)
        rows.append((name, rate, rate / freq))  # training steps/s = env steps/s for SB3
    print(f"forcegrasp up, recipe {args.recipe} ({utd:g} updates/step): learner + {args.actors} actors x {args.envs} envs:",
          flush=True)
    ingest, updates = bench_cluster(args.object, args.seconds, args.actors, args.envs, args.recipe)
    ours = min(ingest, updates / utd)
    print("\n| system | env steps/s | updates/s | training steps/s |\n|---|---:|---:|---:|")
    for name, rate, ups in rows:
        print(f"| {name} | {rate:.1f} | {ups:.1f} | {rate:.1f} |")
    print(f"| ForceGrasp local cluster, recipe {args.recipe} | {ingest:.1f} | {updates:.1f} | {ours:.1f} |\n")
    for name, rate, _ in rows:
        print(f"ratio over {name}: {ours / rate:.2f}x")


if __name__ == "__main__":
    main()
