"""How much of the joint torques can a policy *without* force feedback read off what it still sees?

The paper's no-force-feedback policies (the 53 numbers of Table I without the 24 torques) stay
below 35 % success; ForceGrasp's learn nearly as well as those with torques (docs/results.md).
Suspected cause: every hand joint is a position servo (torque = kp (target - angle) - kv velocity),
and the targets all lie on the straight line J = h (Jg - J0) + J0, so a finger that a contact
stops leaves that line, and its joint angles show the contact the torque would have shown.

This measures it with ridge-regression probes (standardised inputs, fitted on some episodes,
scored on held-out ones): R^2 of the 24 torques from the 53 no-force-feedback numbers, and of two
things the policy needs to know -- hand-object contact and the object's offset (the jitter) --
from the 53 numbers versus all 77. States come from a shipped force-feedback policy's own
episodes (sampled actions) on the evaluation's held-out placements.

    python bench/ff_information.py                     # every object with a shipped ff policy
    python bench/ff_information.py --objects camera --episodes 60 --json out.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements
from forcegrasp.policy import Policy
from forcegrasp.task import PRIVILEGED_LAYOUT

POLICIES = Path(__file__).resolve().parent.parent / "assets" / "policies"
N_TORQUES = 24


def rollouts(obj: str, policy_file: Path, episodes: int, seed: int):
    """(observations (n, 77), privileged states (n, 14), episode index (n,)) of sampled-action episodes."""
    policy = Policy.load(policy_file, seed=seed)
    env = FunctionalGraspEnv(obj, force_feedback=True)
    obs_all, priv_all, ep_all = [], [], []
    for k, place in enumerate(placements(seed, episodes, env.jitter, "test", clear=env.is_clear)):
        obs, _ = env.reset(seed=place.seed, options={"offset": place.offset})
        done = False
        while not done:
            obs_all.append(obs)
            priv_all.append(env.privileged_state())
            ep_all.append(k)
            obs, _, terminated, truncated, _ = env.step(policy(obs, deterministic=False))
            done = terminated or truncated
    return np.array(obs_all), np.array(priv_all), np.array(ep_all)


def ridge_r2(x: np.ndarray, y: np.ndarray, train: np.ndarray, lam_per_100: float = 1.0) -> float:
    """Held-out R^2 (all outputs pooled) of a ridge fit on standardised ``x``; 1 = fully predictable."""
    mu, sd = x[train].mean(0), x[train].std(0) + 1e-6
    a = (x - mu) / sd
    y_mean = y[train].mean(0)
    lam = lam_per_100 * train.sum() / 100
    w = np.linalg.solve(a[train].T @ a[train] + lam * np.eye(a.shape[1]), a[train].T @ (y[train] - y_mean))
    test = ~train
    residual = ((y[test] - a[test] @ w - y_mean) ** 2).sum()
    total = ((y[test] - y[test].mean(0)) ** 2).sum()
    return float(1.0 - residual / total)


def probe(obj: str, policy_file: Path, episodes: int, seed: int) -> dict:
    obs, priv, ep = rollouts(obj, policy_file, episodes, seed)
    train = ep < int(0.75 * episodes)
    torques, seen = obs[:, :N_TORQUES], obs[:, N_TORQUES:]
    names = [n for n, size in PRIVILEGED_LAYOUT for _ in range(size)]
    contact = priv[:, [i for i, n in enumerate(names) if n == "hand_contact"]]
    offset = priv[:, [i for i, n in enumerate(names) if n == "object_offset"]]
    return {
        "object": obj, "policy": policy_file.name, "episodes": episodes, "states": len(obs),
        "contact_share": float(contact.mean()),
        "torques_from_53": ridge_r2(seen, torques, train),
        "contact_from_53": ridge_r2(seen, contact, train), "contact_from_77": ridge_r2(obs, contact, train),
        "offset_from_53": ridge_r2(seen, offset, train), "offset_from_77": ridge_r2(obs, offset, train),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", nargs="*", default=None, help="default: every object with a shipped ff policy")
    parser.add_argument("--episodes", type=int, default=120, help="episodes per object; a quarter are held out")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="write the figures here")
    args = parser.parse_args()
    files = sorted(POLICIES.glob("*-ff-s0.safetensors"))
    if args.objects:
        files = [f for f in files if f.name.split("-ff-")[0] in args.objects]
    print("| object | states (in contact) | torques from the 53 | contact from 53 / 77 | object offset from 53 / 77 |")
    print("|---|---:|---:|---:|---:|")
    rows = []
    for f in files:
        r = probe(f.name.split("-ff-")[0], f, args.episodes, args.seed)
        rows.append(r)
        print(f"| {r['object']} | {r['states']} ({r['contact_share']:.0%}) | {r['torques_from_53']:.2f} | "
              f"{r['contact_from_53']:.2f} / {r['contact_from_77']:.2f} | {r['offset_from_53']:.2f} / "
              f"{r['offset_from_77']:.2f} |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
