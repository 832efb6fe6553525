"""The secure transport: TLS, user/password and the learner's access control, from one
credentials folder per service (`forcegrasp.certs`, ``network.credentials``).

With credentials the cluster is a hub: the learner opens a Zenoh *router* on its ``tls/``
endpoints and every other service is a *client* of it that listens on nothing. All traffic then
passes the learner, which checks it in one place:

- a peer without a certificate signed by the cluster's CA, or without a user and password from
  the learner's ``users.txt``, gets no session at all (nothing in, nothing out);
- the access control (default deny) lets each identity declare, publish and query only what its
  role needs, keyed on its user name *and* its certificate's common name:

  ============  ==================================================================
  actor-<id>    publish its own transitions and stats, its liveliness token; read
                weights and progress, query the latest weights
  evaluator     read checkpoint announcements, publish its stats, answer ``best``
  client        query ``best``, read stats (``forcegrasp best``, ``up``'s monitor)
  ============  ==================================================================

  Weights, progress and checkpoints are published by the learner's own session, which no rule
  lets anyone else do. Only the evaluator may declare the ``best`` queryable.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from forcegrasp.protocol.keys import Keys

#: Zenoh message kinds the access control names (zenoh.io/docs/manual/access-control).
_ALL = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
        "declare_liveliness_subscriber", "liveliness_query"]


class CredentialsError(ValueError):
    """A credentials folder that lacks a file or does not fit the service."""


def credentials_folder(path: str | Path, identity: str) -> Path:
    """`path` itself when it holds one identity's files, else ``path/<identity>``.

    An actor id ``actor-3.host7`` is identity ``actor-3``: several actors of one machine may
    share its credentials and still send distinct streams."""
    path = Path(path)
    if (path / "cert.pem").is_file():
        return path
    name = identity.split(".", 1)[0]
    if not (path / name).is_dir():
        raise CredentialsError(f"network.credentials: {path} has neither this service's files nor a folder "
                               f"{name!r} (identities there: {', '.join(sorted(p.name for p in path.iterdir() if p.is_dir())) or 'none'})"
                               if path.is_dir() else f"network.credentials: {path} is not a folder")
    return path / name


def read_credentials(folder: str | Path, need_users: bool = False) -> dict[str, Path | str]:
    folder = Path(folder)
    names = ["ca.pem", "cert.pem", "key.pem", "user", "password"] + (["users.txt"] if need_users else [])
    missing = [n for n in names if not (folder / n).is_file()]
    if missing:
        raise CredentialsError(f"network.credentials: {folder} lacks {', '.join(missing)} "
                               "(make it with `forcegrasp certs DIR` and point at DIR/<identity>)")
    out: dict[str, Path | str] = {n: (folder / n).resolve() for n in names}
    out["user"] = (folder / "user").read_text().strip()
    out["password"] = (folder / "password").read_text().strip()
    return out


def session_settings(folder: str | Path, service: str, run: str, mutual_tls: bool = True,
                     connect_timeout_ms: int = -1) -> dict[str, Any]:
    """Zenoh config paths for `service` (``learner`` or any other) from its credentials folder.

    The non-learner side waits for the learner (``connect_timeout_ms`` = -1: opening the session
    blocks until the router answers, then reconnects by itself); a client command passes a
    finite timeout to fail with a message instead."""
    learner = service == "learner"
    c = read_credentials(folder, need_users=learner)
    settings: dict[str, Any] = {
        "mode": "router" if learner else "client",
        "transport/link/tls/root_ca_certificate": str(c["ca.pem"]),
        "transport/link/tls/enable_mtls": bool(mutual_tls),
        "transport/auth/usrpwd/user": c["user"],
        "transport/auth/usrpwd/password": c["password"],
    }
    side = "listen" if learner else "connect"
    if learner or mutual_tls:
        settings[f"transport/link/tls/{side}_certificate"] = str(c["cert.pem"])
        settings[f"transport/link/tls/{side}_private_key"] = str(c["key.pem"])
    if learner:
        settings["transport/auth/usrpwd/dictionary_file"] = str(c["users.txt"])
        users = [line.split(":", 1)[0] for line in Path(c["users.txt"]).read_text().splitlines() if ":" in line]
        settings["access_control"] = access_control(run, users, by_certificate=mutual_tls)
    else:
        settings["listen/endpoints"] = []
        settings["connect/timeout_ms"] = int(connect_timeout_ms)
        settings["connect/exit_on_failure"] = connect_timeout_ms >= 0
    return settings


def access_control(run: str, users: list[str], by_certificate: bool = True) -> dict[str, Any]:
    """The learner's access-control table for the identities of its ``users.txt``."""
    keys = Keys(run)
    rules: list[dict[str, Any]] = [
        # What any authenticated identity may receive: the router sends only what a subscriber,
        # queryable or query of its own (each checked on the way in) asked for.
        _rule("receive", "egress", _ALL, [f"{keys.prefix}/**"]),
    ]
    subjects, policies = [], []
    for user in users:
        allowed = _role_rules(keys, user)
        if allowed is None:
            continue  # the learner itself, or a name that has no role
        ids = []
        for i, (messages, exprs) in enumerate(allowed):
            rules.append(_rule(f"{user}/{i}", "ingress", messages, exprs))
            ids.append(f"{user}/{i}")
        subject = {"id": user, "usernames": [user]}
        if by_certificate:
            subject["cert_common_names"] = [user]
        subjects.append(subject)
        policies.append({"id": user, "rules": ["receive", *ids], "subjects": [user]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _role_rules(keys: Keys, user: str) -> list[tuple[list[str], list[str]]] | None:
    if user.startswith("actor-"):
        return [
            (["put"], [keys.transitions(user), keys.stats("actor", user),  # and ids "actor-3.<anything>"
                       f"{keys.prefix}/transitions/{user}.$*", f"{keys.prefix}/stats/actor/{user}.$*"]),
            (["liveliness_token"], [keys.alive("actor", user), f"{keys.prefix}/alive/actor/{user}.$*"]),
            (["declare_subscriber"], [keys.weights, keys.progress]),
            (["query"], [keys.weights_latest]),
        ]
    if user == "evaluator":
        return [
            (["put"], [f"{keys.prefix}/stats/evaluator/*"]),
            (["liveliness_token"], [f"{keys.prefix}/alive/evaluator/*"]),
            (["declare_subscriber"], [keys.checkpoints]),
            (["declare_queryable", "reply"], [keys.best]),
        ]
    if user == "client":
        return [
            (["query"], [keys.best]),
            (["declare_subscriber"], [keys.all_stats]),
        ]
    return None


def _rule(rule_id: str, flow: str, messages: list[str], exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
            "key_exprs": list(exprs)}
