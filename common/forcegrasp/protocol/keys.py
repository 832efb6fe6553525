"""Zenoh key expressions of one training run: ``forcegrasp/<run>/...``."""

from __future__ import annotations

from forcegrasp.protocol.wire import ROOT, ProtocolError, R_FIELD, validate_name


class Keys:
    """All key expressions of one training run: ``forcegrasp/<run>/...``.

    One object per run keeps every service on the same spelling; the wildcard forms
    (``all_*``) are what the learner and monitors subscribe to.
    """

    def __init__(self, run: str) -> None:
        self.run = validate_name(run, "run name")
        self.prefix = f"{ROOT}/{self.run}"

    def transitions(self, actor_id: str | int) -> str:
        """Where one actor publishes its TransitionBatch messages."""
        return f"{self.prefix}/transitions/{validate_name(actor_id, 'actor id')}"

    @property
    def all_transitions(self) -> str:
        return f"{self.prefix}/transitions/*"

    @property
    def weights(self) -> str:
        """Learner broadcasts Weights here every N updates."""
        return f"{self.prefix}/weights"

    @property
    def weights_latest(self) -> str:
        """Learner's queryable answering with the current Weights (late joiners ask here)."""
        return f"{self.prefix}/weights/latest"

    @property
    def checkpoints(self) -> str:
        """Learner announces each written checkpoint (Checkpoint message)."""
        return f"{self.prefix}/checkpoints"

    @property
    def progress(self) -> str:
        """Learner's headroom and acknowledgements (Progress message, ~20 Hz): actors pause while it is used up,
        which holds the update-to-data ratio (the rate limiter)."""
        return f"{self.prefix}/progress"

    @property
    def best(self) -> str:
        """Evaluator's queryable answering with its best policy (Checkpoint message)."""
        return f"{self.prefix}/best"

    def stats(self, service: str, instance: str | int) -> str:
        return f"{self.prefix}/stats/{validate_name(service, 'service')}/{validate_name(instance, 'id')}"

    @property
    def all_stats(self) -> str:
        return f"{self.prefix}/stats/**"

    def alive(self, service: str, instance: str | int) -> str:
        """Liveliness token key of one service instance."""
        return f"{self.prefix}/alive/{validate_name(service, 'service')}/{validate_name(instance, 'id')}"

    def alive_of(self, service: str) -> str:
        return f"{self.prefix}/alive/{validate_name(service, 'service')}/*"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/alive/**"

    def parse_alive(self, key: str) -> tuple[str, str]:
        """``(service, id)`` of a liveliness key of this run; ProtocolError otherwise."""
        return self._parse_two(str(key), "alive")

    def parse_stats(self, key: str) -> tuple[str, str]:
        return self._parse_two(str(key), "stats")

    def actor_of(self, key: str) -> str:
        """Actor id from a transitions key, so a receiver can check it against the payload."""
        head = f"{self.prefix}/transitions/"
        key = str(key)
        if not key.startswith(head):
            raise ProtocolError(R_FIELD, f"{key!r} is not a transitions key of run {self.run!r}")
        return validate_name(key[len(head):], "actor id")

    def _parse_two(self, key: str, kind: str) -> tuple[str, str]:
        head = f"{self.prefix}/{kind}/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 2:
            raise ProtocolError(R_FIELD, f"{key!r} is not a {kind} key of run {self.run!r}")
        return validate_name(parts[0], "service"), validate_name(parts[1], "id")
