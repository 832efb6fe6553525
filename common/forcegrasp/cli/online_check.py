"""``forcegrasp online-check POLICY``: is the actors' online success rate the policy's success rate?

Serves one frozen policy file, as a learner would (``weights/latest``), to a real actor process
over Zenoh, collects the episodes the actor reports in its transition batches, and runs the same
policy offline (sampled actions, random placements, the conditions the policy trained on, which the
actor is given too) for as many episodes. With weights frozen, the two rates must agree within
sampling error: if they do, a gap between the online figure and held-out tests during training
comes from the weights changing under the actors, not from bookkeeping. A multi-object policy is
compared object by object (the actor's envs go round its objects; each ended episode says which
it was).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def two_proportion_z(k1: int, n1: int, k2: int, n2: int) -> float:
    """z statistic of the difference of two binomial rates (pooled variance); 0 when both are 0 or 1."""
    p = (k1 + k2) / (n1 + n2)
    se = math.sqrt(p * (1 - p) * (1 / n1 + 1 / n2))
    return 0.0 if se == 0 else (k1 / n1 - k2 / n2) / se


def offline_successes(policy_path: Path, episodes: int | dict[str, int],
                      seed: int = 12345) -> list[bool] | dict[str, list[bool]]:
    """Episodes the way an actor runs them: sampled actions, random placements, resets in a row,
    under the conditions the policy trained on (its per-episode draws included); with
    ``{object: count}`` (a multi-object policy) that many on each object, by object."""
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.policy import Policy

    policy = Policy.load(policy_path, seed=seed)
    counts = episodes if isinstance(episodes, dict) else {None: episodes}
    out: dict = {}
    for obj, count in counts.items():
        env = FunctionalGraspEnv.for_policy(policy.metadata, obj)
        out[obj] = []
        obs, _ = env.reset(seed=seed)
        while len(out[obj]) < count:
            obs, _, terminated, truncated, info = env.step(policy(obs, deterministic=False))
            if terminated or truncated:
                out[obj].append(bool(info["success"]))
                obs, _ = env.reset()
    return out if isinstance(episodes, dict) else out[None]


def online_successes(policy_path: Path, episodes: int, envs: int = 8, seed: int = 777, timeout_s: float = 600.0,
                     log=print) -> list[bool] | dict[str, list[bool]]:
    """Episodes reported by a real actor process acting with the frozen policy file; for a
    multi-object policy (its envs go round the objects) the first ``episodes`` by object."""
    from forcegrasp.config import load_config
    from forcegrasp.multi_object import policy_objects
    from forcegrasp.policy_file import load_policy_file
    from forcegrasp.task import action_steps_of, proprioception_of
    from forcegrasp.protocol import Keys, ProtocolError, Weights, decode_transitions, encode_weights
    from forcegrasp.transport import (QueueSubscriber, close_session, declare_queryable, free_tcp_port,
                                      open_session)

    weights, meta = load_policy_file(policy_path)
    objects = policy_objects(meta)
    # the conditions the policy trained on, as `FunctionalGraspEnv.for_policy` rebuilds them offline
    # (a file without the record trained at the paper's fixed conditions)
    trained = {"mass_scale_range": [], "torque_noise_range": [], "jitter_range": [], **(meta.extra.get("training_conditions") or {})}
    port = free_tcp_port()
    run = "online-check"
    config = load_config(overrides=[
        f"run.name={run}", f"env.objects={json.dumps(objects)}", f"env.force_feedback={str(meta.force_feedback).lower()}",
        f"actor.envs_per_actor={envs}", "actor.random_steps=0", "actor.publish_batch=64",
        f'network.learner_listen=["tcp/127.0.0.1:{port}"]', "network.lease_ms=1000",
        f"learner.sac.obs_norm={str(meta.obs_norm).lower()}", f"env.proprioception={proprioception_of(meta)}",
        *(f"env.{k}={v}" for k, v in action_steps_of(meta).items()),  # the file's step sizes, not today's
        *(f"env.{k}={json.dumps(v)}" for k, v in trained.items()),
    ])
    keys = Keys(run)
    by_object: dict[str, list[bool]] = {o: [] for o in objects}
    payload = encode_weights(Weights(1, 0, weights, meta={"policy_metadata": meta.to_json()}))
    session = open_session([f"tcp/127.0.0.1:{port}"], [])
    inbox = QueueSubscriber(session, keys.all_transitions, maxsize=4096, put_timeout=1.0)
    queryable = declare_queryable(session, keys.weights_latest, lambda: payload)
    successes: list[bool] = []
    warmup = 2 * envs  # episodes that may have begun before the policy arrived (the actor asks at start)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "actor.toml"
        path.write_text(config.to_toml())
        log_file = open(Path(tmp) / "actor.log", "wb")
        proc = subprocess.Popen([sys.executable, "-m", "forcegrasp_actor", "--config", str(path),
                                 "--id", "check", "--seed", str(seed)], stdout=log_file, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + timeout_s
            while len(successes) < episodes:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError(f"actor gave {len(successes)} of {episodes} episodes "
                                       f"(exit code {proc.poll()}); see its log")
                item = inbox.get(timeout=0.5)
                if item is None:
                    continue
                try:
                    batch = decode_transitions(item)
                except ProtocolError:
                    continue
                if batch.policy_version != 1 or not batch.has_episodes:
                    continue  # acted before it had the policy (it asks at start): not this policy's episodes
                ended = batch.episode_objects if batch.episode_objects is not None else [0] * len(batch.episode_successes)
                for s, o in zip(batch.episode_successes, ended):
                    if warmup > 0:
                        warmup -= 1
                    elif len(successes) < episodes:
                        successes.append(bool(s))
                        by_object[batch.objects[o]].append(bool(s))
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            queryable.undeclare()
            inbox.close()
            close_session(session)
    return by_object if len(objects) > 1 else successes


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp online-check", description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path)
    parser.add_argument("--episodes", type=int, default=200)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    online = online_successes(args.policy, args.episodes)
    if isinstance(online, dict):  # several objects: each compared on its own episodes
        offline = offline_successes(args.policy, {o: len(v) for o, v in online.items()})
        rows = [(o, online[o], offline[o]) for o in online] + [
            ("all", [x for v in online.values() for x in v], [x for v in offline.values() for x in v])]
    else:
        rows = [(None, online, offline_successes(args.policy, args.episodes))]
    for name, on, off in rows:
        k1, k2, n = sum(on), sum(off), len(on)
        z = two_proportion_z(k1, n, k2, n) if n else 0.0
        print((f"{name}: " if name else "") + f"online (actor process, frozen weights): {k1}/{n} = {k1 / max(n, 1):.1%}\n"
              f"offline (same policy, sampled actions):  {k2}/{n} = {k2 / max(n, 1):.1%}\n"
              f"difference z = {z:+.2f} ({'within' if abs(z) < 2.576 else 'OUTSIDE'} the 99 % band)")
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
