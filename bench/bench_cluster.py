"""End-to-end training throughput: the local cluster against stable-baselines3 SAC, same env,
same machine, one gradient update per environment step, measured one after the other in one run.

- SB3: ``SAC("MlpPolicy", env, batch_size=256, train_freq=1, gradient_steps=1)``, networks
  [256, 256]; the rate is timed from the first update to the end (random warm-up excluded).
- ForceGrasp: ``forcegrasp up --no-evaluator`` (learner + actors as processes on loopback; SB3
  evaluates nothing either) with the same SAC settings; the rate is read from the learner's stats over a window after learning started.
  At a 1:1 update-to-data ratio the training rate is min(env steps ingested/s, updates/s):
  both are printed.

    python bench/bench_cluster.py --seconds 60 --sb3-steps 1500
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path


from forcegrasp.protocol import Keys, decode_stats
from forcegrasp.transport import QueueSubscriber, close_session, free_tcp_port, open_session

WARMUP = 1000


def bench_sb3(object_name: str, steps: int) -> float:
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback

    from forcegrasp.env import FunctionalGraspEnv

    class Clock(BaseCallback):
        def __init__(self):
            super().__init__()
            self.t_start = None

        def _on_step(self) -> bool:
            if self.num_timesteps == WARMUP + 1:
                self.t_start = time.perf_counter()
            if self.num_timesteps % 250 == 0:
                print(f"  sb3: {self.num_timesteps}/{WARMUP + steps} steps", flush=True)
            return True

    env = FunctionalGraspEnv(object_name)
    model = SAC("MlpPolicy", env, batch_size=256, learning_starts=WARMUP, train_freq=1, gradient_steps=1,
                policy_kwargs={"net_arch": [256, 256]}, seed=0, device="cpu", verbose=0)
    clock = Clock()
    model.learn(total_timesteps=WARMUP + steps, callback=clock)
    return steps / (time.perf_counter() - clock.t_start)


def bench_cluster(object_name: str, seconds: float, actors: int, envs: int) -> tuple[float, float]:
    port = free_tcp_port()
    with tempfile.TemporaryDirectory() as tmp:
        run = "bench"
        cmd = [sys.executable, "-m", "forcegrasp.cli", "up", "--no-evaluator", "--stop-after", str(seconds + 60),
               "--set", f"run.name={run}", "--set", f"run.output_dir={tmp}", "--set", f"env.object={object_name}",
               "--set", f"actor.num_actors={actors}", "--set", f"actor.envs_per_actor={envs}",
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
    args = parser.parse_args()
    print("stable-baselines3 SAC, one process:", flush=True)
    sb3 = bench_sb3(args.object, args.sb3_steps)
    print(f"  sb3: {sb3:.1f} training steps/s", flush=True)
    print(f"forcegrasp up: learner + {args.actors} actors x {args.envs} envs:", flush=True)
    ingest, updates = bench_cluster(args.object, args.seconds, args.actors, args.envs)
    ours = min(ingest, updates)
    print(f"\n| system | env steps/s | updates/s | training steps/s at 1:1 |\n|---|---|---|---|\n"
          f"| stable-baselines3 SAC | {sb3:.1f} | {sb3:.1f} | {sb3:.1f} |\n"
          f"| ForceGrasp local cluster | {ingest:.1f} | {updates:.1f} | {ours:.1f} |\n\nratio {ours / sb3:.2f}x")


if __name__ == "__main__":
    main()
