"""``forcegrasp serve POLICY``: the best-policy endpoint for a shipped policy, no training run needed.

Serves one policy file (e.g. ``assets/policies/mug-ff-s0.safetensors``) exactly as a running
evaluator serves its best: the read-only HTTP page (``/best``, ``/best/policy``, ``/top``) and
the Zenoh ``forcegrasp/<run>/best`` query, listening where a learner would (``network.
learner_listen``), so ``forcegrasp best --out FILE`` (over Zenoh or ``--url``) works on it
unchanged. The run name is the file's stem unless ``--run`` says otherwise; the scores are the
file's JSON record (its held-out test), else the policy file's own.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

from forcegrasp.config import ConfigError, add_config_arguments, config_from_args
from forcegrasp.protocol import Keys

log = logging.getLogger("forcegrasp.serve")


def best_from_file(path: Path, run: str):
    """A `BestPolicy` for a policy file and its optional JSON record."""
    from forcegrasp.policy_file import load_policy_bytes
    from forcegrasp.protocol.best import BestPolicy

    data = path.read_bytes()
    _, meta = load_policy_bytes(data, source=str(path))  # a corrupt file is refused here
    record = json.loads(path.with_suffix(".json").read_text()) if path.with_suffix(".json").is_file() else {}
    held = record.get("held_out", {})
    score = float(held.get("mean_return", meta.eval_score if meta.eval_score is not None else 0.0))
    rate = float(held.get("success_rate", 0.0))
    episodes = int(held.get("episodes", 0))
    return BestPolicy(run=run, step=int(meta.training_steps), score=score, success_rate=rate, episodes=episodes,
                      eval_score=score, eval_success_rate=rate, eval_episodes=episodes, object=meta.object_name,
                      force_feedback=bool(meta.force_feedback), policy_version=0,
                      sha256=hashlib.sha256(data).hexdigest(), policy=data, time=path.stat().st_mtime)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp serve", description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path, help="a policy file (e.g. assets/policies/camera-ff-s0.safetensors)")
    parser.add_argument("--run", default=None, help="run name to serve it under (default: the file's stem)")
    parser.add_argument("--no-zenoh", action="store_true", help="HTTP only")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from forcegrasp.policy_file import PolicyFileError
    from forcegrasp.runtime import open_service_session, stop_on_signals
    from forcegrasp.transport import close_session
    from forcegrasp_evaluator.endpoint import EvaluatorHTTPServer, Snapshot, declare_best_queryable

    run = args.run or args.policy.stem
    try:
        config = config_from_args(args)
        best = best_from_file(args.policy, run)
    except (ConfigError, PolicyFileError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    snap = Snapshot.build(run, best, {"members": [{**best.metadata(), "rank": 1, "best": True}]})
    ev = config.evaluator
    server = EvaluatorHTTPServer(ev.http_host, ev.http_port, lambda: snap).start()
    session = queryable = None
    if not args.no_zenoh:
        session = open_service_session(config, "learner")  # listen where a cluster's learner would
        queryable = declare_best_queryable(session, run, lambda: snap)
    print(f"serving {args.policy} as run {run!r}: http://{ev.http_host}:{server.port}/best"
          + ("" if args.no_zenoh else f", Zenoh {Keys(run).best} on {', '.join(config.network.learner_listen)}"),
          flush=True)
    stop = stop_on_signals()
    try:
        while not stop.is_set():
            time.sleep(0.2)
    finally:
        if queryable is not None:
            queryable.undeclare()
        close_session(session)
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
