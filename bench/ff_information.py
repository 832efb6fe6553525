"""What do the policies of each observation arm see of the contact and of the object?

The paper's no-force-feedback policies (the 53 numbers of Table I without the 24 torques) stay
below 35 % success; ForceGrasp's learn nearly as well as those with torques (docs/results.md).
Suspected cause: every hand joint is a position servo (torque = kp (target - angle) - kv velocity),
and the targets all lie on the straight line J = h (Jg - J0) + J0, so a finger that a contact
stops leaves that line, and its joint angles show the contact the torque would have shown.
``env.proprioception = "commanded"`` (issue 46) fills those slots with the commands instead.

This measures it with ridge-regression probes (standardised inputs, fitted on some episodes,
scored on held-out ones) for four arms -- measured or commanded proprioception, with or without
the 24 torques -- on the same states: held-out R^2 of the 24 torques, of the contact state
(privileged ``hand_contact``, and the five ``fingertip_contacts`` flags) and of the object's
offset (the jitter), from what that arm observes. States come from a shipped force-feedback
policy's own episodes (sampled actions) on the evaluation's held-out placements; a commanded-mode
env is stepped alongside with the same placement and actions (its torques must equal the measured
env's: the same states), so both observations are the envs' own.

Whose actions drive the states matters. A policy that feels the torques steers after it felt the
object, so in its own episodes the commands it issued (base targets, h) carry what it felt, and
even the commanded-only arm would "see" the offset through them. By default (``--actions
open-loop``) each placement is therefore driven by the action sequence the policy produced on
*another* placement: grasp-like actions that do not depend on the object in front of them, so
what a probe recovers is what the observation channel itself carries. ``--actions closed-loop``
probes the policy's own episodes. The ``timing`` row is the floor of what anyone knows without
sensing anything: a probe from the step index and the commanded h alone (contact follows closing
the hand).

    python bench/ff_information.py                     # every object with a shipped ff policy
    python bench/ff_information.py --objects camera --episodes 60 --json out.json
    python bench/ff_information.py --actions closed-loop
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements
from forcegrasp.policy import Policy
from forcegrasp.task import PRIVILEGED_LAYOUT, observation_layout

POLICIES = Path(__file__).resolve().parent.parent / "assets" / "policies"
N_TORQUES = 24
#: (name, proprioception, sees the torques)
ARMS = (("measured+torques", "measured", True), ("measured only", "measured", False),
        ("commanded+torques", "commanded", True), ("commanded only", "commanded", False))
TARGETS = ("torques", "hand_contact", "fingertip_contacts", "object_offset")


def rollouts(obj: str, policy_file: Path, episodes: int, seed: int, actions: str = "open-loop"):
    """Observations (n, 77) of the measured and of the commanded env, privileged states (n, 16),
    episode index and step (n,). Closed loop: the policy's sampled-action episodes (it acts on the
    measured observation). Open loop: placement k replays the actions the policy chose on placement
    k + 1 (then holds still), so no action depends on the object it meets."""
    policy = Policy.load(policy_file, seed=seed)
    envs = {mode: FunctionalGraspEnv.for_policy(policy.metadata, proprioception=mode)
            for mode in ("measured", "commanded")}
    measured = envs["measured"]
    places = placements(seed, episodes, measured.jitter, "test", clear=measured.is_clear)
    scripts = None
    if actions == "open-loop":
        own = [_episode(envs, place, lambda obs, t: policy(obs["measured"], deterministic=False))["actions"]
               for place in places]
        scripts = own[1:] + own[:1]
    out = {"measured": [], "commanded": [], "priv": [], "episode": [], "step": []}
    for k, place in enumerate(places):
        if scripts is None:
            act = lambda obs, t: policy(obs["measured"], deterministic=False)  # noqa: E731
        else:
            act = lambda obs, t, s=scripts[k]: s[t] if t < len(s) else np.zeros(7, np.float32)  # noqa: E731
        for key, values in _episode(envs, place, act).items():
            if key != "actions":
                out[key] += values
        out["episode"] += [k] * (len(out["priv"]) - len(out["episode"]))
    return {key: np.array(value) for key, value in out.items()}


def _episode(envs: dict, place, act) -> dict:
    """One episode of both envs from ``place`` under ``act(obs, step)``; their torques must agree."""
    measured, commanded = envs["measured"], envs["commanded"]
    obs = {mode: env.reset(seed=place.seed, options={"offset": place.offset})[0] for mode, env in envs.items()}
    out = {"measured": [], "commanded": [], "priv": [], "step": [], "actions": []}
    done, t = False, 0
    while not done:
        if not np.array_equal(obs["measured"][:N_TORQUES], obs["commanded"][:N_TORQUES]):
            raise RuntimeError("the commanded env left the measured one's states")
        for mode in envs:
            out[mode].append(obs[mode])
        out["priv"].append(measured.privileged_state())
        out["step"].append(t)
        action = act(obs, t)
        out["actions"].append(action)
        obs["measured"], _, terminated, truncated, _ = measured.step(action)
        obs["commanded"], *_ = commanded.step(action)
        done, t = terminated or truncated, t + 1
    return out


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


def probe(obj: str, policy_file: Path, episodes: int, seed: int, actions: str = "open-loop") -> list[dict]:
    """One row per arm, and the timing floor: held-out R^2 of each target from what it observes."""
    data = rollouts(obj, policy_file, episodes, seed, actions)
    train = data["episode"] < int(0.75 * episodes)
    names = np.array([n for n, size in PRIVILEGED_LAYOUT for _ in range(size)])
    priv = data["priv"]
    targets = {"torques": data["measured"][:, :N_TORQUES], **{t: priv[:, names == t] for t in TARGETS[1:]}}
    contact = targets["hand_contact"]
    layout = observation_layout(True, 0, "commanded")
    start = sum(size for _, size in layout[:[name for name, _ in layout].index("h_command")])
    timing = np.stack([data["step"], data["commanded"][:, start]], 1).astype(float)
    rows = []
    for arm, mode, torques in (*ARMS, ("timing", "commanded", False)):
        seen = timing if arm == "timing" else data[mode] if torques else data[mode][:, N_TORQUES:]
        rows.append({"object": obj, "policy": policy_file.name, "episodes": episodes, "actions": actions,
                     "states": len(seen), "contact_share": float(contact.mean()), "arm": arm,
                     "proprioception": mode if arm != "timing" else None, "torques_observed": torques,
                     "obs_dim": seen.shape[1], **{t: ridge_r2(seen, y, train) for t, y in targets.items()}})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", nargs="*", default=None, help="default: every object with a shipped ff policy")
    parser.add_argument("--episodes", type=int, default=120, help="episodes per object; a quarter are held out")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--actions", choices=("open-loop", "closed-loop"), default="open-loop",
                        help="who drives the states: another placement's actions (default) or the policy itself")
    parser.add_argument("--json", default=None, help="write the figures here (one row per object and arm)")
    args = parser.parse_args()
    if args.episodes < 4:
        parser.error("--episodes must be at least 4 (a quarter are held out)")
    files = sorted(POLICIES.glob("*-ff-s0.safetensors"))
    if args.objects:
        files = [f for f in files if f.name.split("-ff-")[0] in args.objects]
        missing = set(args.objects) - {f.name.split("-ff-")[0] for f in files}
        if missing:
            parser.error(f"no shipped force-feedback policy for {', '.join(sorted(missing))}")
    print(f"Held-out R^2 of a ridge probe from what each arm observes ({args.actions} actions; 1 = fully "
          "predictable, 0 = no better than the mean)\n")
    print("| object | states (in contact) | arm | obs | torques | hand contact | fingertip contacts | object offset |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    rows = []
    for f in files:
        for r in probe(f.name.split("-ff-")[0], f, args.episodes, args.seed, args.actions):
            rows.append(r)
            print(f"| {r['object']} | {r['states']} ({r['contact_share']:.0%}) | {r['arm']} | {r['obs_dim']} | "
                  + " | ".join(f"{r[t]:.2f}" for t in TARGETS) + " |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
