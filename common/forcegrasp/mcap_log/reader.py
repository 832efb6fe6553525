"""Reading an episode log back: metadata, every topic's JSON messages, joint and object poses."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from forcegrasp.scene import ALL_JOINTS
from forcegrasp.mcap_log.schemas import METADATA_NAME, OBJECT_FRAME


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

@dataclass
class EpisodeLog:
    """A decoded episode file: its metadata and the JSON messages of every topic, in log order."""

    path: Path
    metadata: dict[str, str]
    messages: dict[str, list[dict]] = field(default_factory=dict)
    schemas: dict[str, tuple[str, str]] = field(default_factory=dict)  # topic -> (schema name, encoding)
    log_times: dict[str, list[int]] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        return len(self.messages.get("/reward", [])) - 1

    def qpos(self) -> np.ndarray:
        """(steps + 1, 30) joint positions in ``ALL_JOINTS`` order."""
        order = {n: i for i, n in enumerate(ALL_JOINTS)}
        out = np.zeros((len(self.messages["/joint_states"]), len(ALL_JOINTS)))
        for t, msg in enumerate(self.messages["/joint_states"]):
            for j in msg["joints"]:
                out[t, order[j["name"]]] = j["position"]
        return out

    def object_poses(self) -> np.ndarray:
        """(steps + 1, 7) object position and quaternion (w, x, y, z) from ``/tf``."""
        rows = []
        for msg in self.messages["/tf"]:
            tf = next(t for t in msg["transforms"] if t["child_frame_id"] == OBJECT_FRAME)
            p, q = tf["translation"], tf["rotation"]
            rows.append([p["x"], p["y"], p["z"], q["w"], q["x"], q["y"], q["z"]])
        return np.array(rows)


def read_episode(path: str | os.PathLike, topics: Iterable[str] | None = None) -> EpisodeLog:
    """Decode an episode file written by :class:`EpisodeLogger` (any MCAP with JSON channels works)."""
    from mcap.reader import make_reader

    path = Path(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        metadata: dict[str, str] = {}
        for record in reader.iter_metadata():
            if record.name == METADATA_NAME:
                metadata = dict(record.metadata)
        log = EpisodeLog(path, metadata)
        for schema, channel, message in reader.iter_messages(topics=list(topics) if topics else None):
            log.schemas[channel.topic] = (schema.name if schema else "", schema.encoding if schema else "")
            if channel.message_encoding != "json":
                continue
            log.messages.setdefault(channel.topic, []).append(json.loads(message.data))
            log.log_times.setdefault(channel.topic, []).append(message.log_time)
    return log
