"""``forcegrasp best --out FILE``: fetch the evaluator's best policy and write it atomically.

Over Zenoh by default (the shared ``--config``/``--set`` options say which run and where the
learner listens; the query reaches the evaluator through the learner's peer mesh), or over HTTP
with ``--url http://HOST:PORT``. The file is checked (SHA-256, full policy-file parse) before it
is written; nothing is written on any error, and the exit status is 1 with a message saying why.
The policy's metadata goes to stdout as JSON; for a policy of several objects (``env.objects``) it
carries their ranking figures (``objects``), also printed as a table on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys

from forcegrasp.config import ConfigError, add_config_arguments, config_from_args


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp best", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, metavar="FILE", help="where to write the policy file (.safetensors)")
    parser.add_argument("--url", default=None, help="the evaluator's HTTP address, e.g. http://127.0.0.1:8080 "
                                                    "(default: ask over Zenoh)")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for an answer (default 10)")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    from forcegrasp.policy_file import atomic_write
    from forcegrasp_evaluator.endpoint import BestFetchError, fetch_best_http

    try:
        config = config_from_args(args)
        run = config.run.name
        if args.url:
            best = fetch_best_http(args.url, run if _run_was_given(args) else None, timeout=args.timeout)
        else:
            best = _fetch_over_zenoh(config, args.timeout)
    except (BestFetchError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    with atomic_write(args.out) as f:
        f.write(best.policy)
    objects, how = _per_object(best.policy)
    print(json.dumps({**best.metadata(), **({"objects": objects} if objects else {}), "out": args.out}, indent=1))
    if objects:
        from forcegrasp.multi_object import object_table

        print("\n".join(object_table(objects, how)), file=sys.stderr)
    return 0


def _per_object(policy: bytes) -> tuple[dict, str | None]:
    """The ranking figures per object a policy file's evaluation records, and their aggregate."""
    from forcegrasp.policy_file import load_policy_bytes

    evaluation = load_policy_bytes(policy)[1].extra.get("evaluation") or {}
    return dict(evaluation.get("rank_objects") or {}), evaluation.get("object_aggregate")


def _run_was_given(args) -> bool:
    """With --url, the run is checked only if the user named one (else: whatever that server runs)."""
    import os

    from forcegrasp.config import CONFIG_FILE_ENV, ENV_PREFIX

    return bool(args.config or any(o.strip().startswith("run.name=") for o in args.overrides)
                or os.environ.get(f"{ENV_PREFIX}RUN_NAME") or os.environ.get(CONFIG_FILE_ENV))


def _fetch_over_zenoh(config, timeout: float):
    from forcegrasp.runtime import open_service_session
    from forcegrasp_evaluator.endpoint import BestFetchError, fetch_best_zenoh
    from forcegrasp.transport import close_session, wait_for_peers

    import zenoh

    try:  # with credentials a client session waits for the learner's router: give up after the timeout
        session = open_service_session(config, "client", connect_timeout_ms=int(min(timeout, 5.0) * 1000))
    except zenoh.ZError:
        raise BestFetchError(f"could not reach the cluster at {', '.join(config.network.connect_endpoints())} "
                             "(is it running? are the credentials right?)") from None
    try:
        if not wait_for_peers(session, 1, timeout=min(timeout, 5.0)):
            raise BestFetchError(f"could not reach the cluster at {', '.join(config.network.connect_endpoints())} "
                                 "(is it running? set network.connect, or use --url with the evaluator's HTTP address)")
        return fetch_best_zenoh(session, config.run.name, timeout=timeout)
    finally:
        close_session(session)


if __name__ == "__main__":
    raise SystemExit(main())
