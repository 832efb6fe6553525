"""Gradient updates per second: ForceGrasp's SAC against stable-baselines3's SAC, same run.

Both learners get the same synthetic replay data (observation 77, action 7, as in the grasping
task), batch 256, two 256-unit hidden layers, and their default use of the cores: stable-baselines3
one torch team over all cores (torch's default), ForceGrasp two concurrent gradient branches of
half the cores each (`--threads` / `--sb3-threads` override). Each repetition
times N updates of ours (replay sampling + `SAC.update`, metrics included) and then N of SB3's
`model.train(gradient_steps=N, batch_size=256)` (its sampling + update + logging), so slow
phases of a shared machine hit both alike. The table reports the median and best repetition.

    python bench/bench_sac_updates.py                 # CPU
    python bench/bench_sac_updates.py --device cuda   # GPU, when present
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np
import torch


def synthetic_data(n: int, obs_dim: int, act_dim: int, priv_dim: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return {
        "privileged": rng.standard_normal((n, priv_dim), dtype=np.float32),
        "next_privileged": rng.standard_normal((n, priv_dim), dtype=np.float32),
        "obs": rng.standard_normal((n, obs_dim), dtype=np.float32),
        "action": rng.uniform(-1, 1, (n, act_dim)).astype(np.float32),
        "reward": rng.standard_normal(n, dtype=np.float32),
        "next_obs": rng.standard_normal((n, obs_dim), dtype=np.float32),
        "terminated": (rng.random(n) < 0.01).astype(np.float32),
    }


def make_ours(args, data, layer_norm=False):
    from forcegrasp.replay import ReplayBuffer
    from forcegrasp.sac import SAC, SACConfig

    sac = SAC(args.obs, args.act, SACConfig(hidden=tuple(args.hidden), batch_size=args.batch, device=args.device,
                                            num_threads=args.threads, parallel_branches=False if args.serial else None,
                                            privileged_critic=args.priv > 0, critic_layer_norm=layer_norm),
              priv_dim=args.priv)
    buffer = ReplayBuffer(args.obs, args.act, capacity=len(data["reward"]), priv_dim=args.priv)
    priv = {"privileged": data["privileged"], "next_privileged": data["next_privileged"]} if args.priv else {}
    buffer.add_batch(data["obs"], data["action"], data["reward"], data["next_obs"], data["terminated"], **priv)
    rng = np.random.default_rng(1)

    def run(n):
        torch.set_num_threads(args.threads)
        for _ in range(n):
            sac.update(buffer.sample(args.batch, rng))

    return run


def make_sb3(args, data, obs_dim):
    """SB3's SAC on observations of ``obs_dim`` numbers: ``args.obs`` (its own defaults: one
    observation for actor and critics), or ``args.obs + args.priv`` (the same critic input as
    ForceGrasp's asymmetric critic; SB3's actor then sees it too, slightly more work)."""
    import gymnasium as gym
    from stable_baselines3 import SAC as SB3SAC
    from stable_baselines3.common.logger import configure

    class SyntheticEnv(gym.Env):  # only its spaces are used: train() never steps it
        observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (args.act,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(obs_dim, np.float32), {}

        def step(self, action):
            return np.zeros(obs_dim, np.float32), 0.0, False, False, {}

    n = len(data["reward"])
    model = SB3SAC("MlpPolicy", SyntheticEnv(), buffer_size=n, batch_size=args.batch, learning_starts=0,
                   policy_kwargs={"net_arch": list(args.hidden)}, device=args.device, seed=0)
    model.set_logger(configure(None, []))
    rb = model.replay_buffer
    extra = obs_dim - args.obs  # the privileged values, appended as the asymmetric critic gets them
    rb.observations[:, 0] = np.concatenate([data["obs"], data["privileged"][:, :extra]], axis=1)
    rb.next_observations[:, 0] = np.concatenate([data["next_obs"], data["next_privileged"][:, :extra]], axis=1)
    rb.actions[:, 0] = data["action"]
    rb.rewards[:, 0] = data["reward"]
    rb.dones[:, 0] = data["terminated"]
    rb.full, rb.pos = True, 0

    def run(n):
        torch.set_num_threads(args.sb3_threads)
        model.train(gradient_steps=n, batch_size=args.batch)

    return run


def timed(run, n, device) -> float:
    """Seconds per update over n updates (waiting for the GPU to finish)."""
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    run(n)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / n


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--updates", type=int, default=100, help="updates per timed repetition")
    parser.add_argument("--reps", type=int, default=7, help="interleaved repetitions per learner")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--obs", type=int, default=77)
    parser.add_argument("--act", type=int, default=7)
    parser.add_argument("--priv", type=int, default=None,
                        help="privileged critic inputs (default: the fast recipe's asymmetric critic, "
                             "task.PRIV_DIM; 0: the paper's symmetric critic)")
    parser.add_argument("--buffer", type=int, default=100_000, help="filled replay size")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads per ForceGrasp gradient branch (default: half the cores, see configure_threads)")
    parser.add_argument("--sb3-threads", type=int, default=None,
                        help="torch threads for stable-baselines3 (default: all usable cores, torch's own default)")
    parser.add_argument("--serial", action="store_true", help="run ForceGrasp's two gradient branches one after the other")
    parser.add_argument("--no-sb3", action="store_true", help="time ForceGrasp's SAC only")
    parser.add_argument("--layer-norm", action="store_true",
                        help="also time ForceGrasp's SAC with critic LayerNorm (the default recipe's since 2026-12-05)")
    args = parser.parse_args(argv)

    from forcegrasp.policy import configure_threads, select_device, usable_cores

    device = select_device(args.device)
    args.device = str(device)
    args.threads = configure_threads(args.threads)
    args.sb3_threads = args.sb3_threads or usable_cores()
    if args.priv is None:
        from forcegrasp.task import PRIV_DIM
        args.priv = PRIV_DIM
    print(f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, device {device}"
          + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""), flush=True)
    print(f"# torch threads: forcegrasp {args.threads} per gradient branch"
          f" ({'serial' if args.serial else 'concurrent branches where >= 2 cores'}), stable-baselines3 {args.sb3_threads}",
          flush=True)
    print(f"# batch {args.batch}, hidden {args.hidden}, obs {args.obs}, privileged {args.priv}, act {args.act}, "
          f"{args.reps} x {args.updates} updates each, interleaved", flush=True)
    print(f"# {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start "
          "(other busy processes slow both learners; compare within one run)", flush=True)

    data = synthetic_data(args.buffer, args.obs, args.act, args.priv)
    learners = {"forcegrasp": make_ours(args, data)}
    if args.layer_norm:
        learners["forcegrasp, critic LayerNorm"] = make_ours(args, data, layer_norm=True)
    if not args.no_sb3:
        import stable_baselines3
        sb3 = f"stable-baselines3 {stable_baselines3.__version__}"
        learners[f"{sb3} (obs {args.obs})"] = make_sb3(args, data, args.obs)
        if args.priv:  # the same critic input as ours
            learners[f"{sb3} (obs {args.obs}+{args.priv})"] = make_sb3(args, data, args.obs + args.priv)

    for name, run in learners.items():  # warm-up: allocator, kernels, optimizer state
        timed(run, max(10, args.updates // 5), device)
    times = {name: [] for name in learners}
    for rep in range(args.reps):
        line = []
        for name, run in learners.items():
            times[name].append(timed(run, args.updates, device))
            line.append(f"{name.replace('stable-baselines3', 'sb3')} {times[name][-1] * 1e3:.2f} ms")
        print(f"  rep {rep + 1}/{args.reps}: " + ", ".join(line), flush=True)

    print(f"# load average {os.getloadavg()[0]:.2f} at end")
    print()
    print("| learner | ms / update (median) | ms / update (best) | updates / s (median) |")
    print("|---|---:|---:|---:|")
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"| {name} | {med * 1e3:.2f} | {min(ts) * 1e3:.2f} | {1 / med:.0f} |")
    for mine, ours in ((n, t) for n, t in times.items() if n.startswith("forcegrasp")):
        for name, other in ((n, t) for n, t in times.items() if not n.startswith("forcegrasp")):
            ratios = [s / o for o, s in zip(ours, other)]  # per interleaved pair: same machine state
            print(f"\n{mine}: speed-up over {name}: {statistics.median(other) / statistics.median(ours):.2f}x "
                  f"(ratio of medians); per-repetition ratios {min(ratios):.2f}x to {max(ratios):.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
