"""The files of one training run, named in one place.

    <output_dir>/<run>/
        config.toml                  the resolved configuration the learner started with
        cluster.toml                 what `forcegrasp up` handed its services
        checkpoint.safetensors       learner state, written last: it marks a complete checkpoint
        replay.npz                   replay snapshot (unless learner.snapshot_replay = false)
        policy.safetensors           the learner's latest policy snapshot
        checkpoints/policy-<step>.safetensors   snapshots for the evaluator, every eval_every steps
        tb/                          TensorBoard scalars (learner and evaluator)
        logs/<service>.log           service logs under `forcegrasp up`
        evaluator/top/index.json     the evaluator's top k, their scores, the best, the history
        evaluator/top/policy-<step>.safetensors
        evaluator/episodes/<step>/   MCAP logs of evaluated episodes
        experiment.json, marks/      `forcegrasp experiment`'s record and frozen policies

Library code, services and tools all reach a run's files through `RunDir`.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

POLICY_RE = re.compile(r"^policy-(\d{1,18})\.safetensors$")
INDEX_NAME = "index.json"


def policy_file_name(step: int) -> str:
    """The name of the policy snapshot taken at learner step ``step``."""
    return f"policy-{int(step):09d}.safetensors"


def step_of(name: str) -> int | None:
    """Learner step in a ``policy-<step>.safetensors`` name, or None for any other name."""
    m = POLICY_RE.match(name)
    return int(m.group(1)) if m else None


@dataclass(frozen=True)
class RunDir:
    root: Path

    @classmethod
    def of(cls, config) -> "RunDir":
        """The run folder of a `forcegrasp.config.Config`."""
        return cls(Path(config.run.output_dir) / config.run.name)

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    config = property(lambda self: self.root / "config.toml")
    cluster_config = property(lambda self: self.root / "cluster.toml")
    checkpoint = property(lambda self: self.root / "checkpoint.safetensors")
    replay = property(lambda self: self.root / "replay.npz")
    latest_policy = property(lambda self: self.root / "policy.safetensors")
    checkpoints = property(lambda self: self.root / "checkpoints")
    tensorboard = property(lambda self: self.root / "tb")
    logs = property(lambda self: self.root / "logs")
    evaluator = property(lambda self: self.root / "evaluator")
    top = property(lambda self: self.root / "evaluator" / "top")
    top_index = property(lambda self: self.root / "evaluator" / "top" / INDEX_NAME)
    episodes = property(lambda self: self.root / "evaluator" / "episodes")
    experiment = property(lambda self: self.root / "experiment.json")
    marks = property(lambda self: self.root / "marks")

    def snapshot(self, step: int) -> Path:
        return self.checkpoints / policy_file_name(step)

    def log(self, service: str) -> Path:
        return self.logs / f"{service}.log"

    def read_index(self) -> dict | None:
        """The evaluator's top-k index, read-only; None if it has none yet."""
        return json.loads(self.top_index.read_text()) if self.top_index.is_file() else None

    def best_policy(self) -> Path | None:
        """The evaluator's best checkpoint file, if it has one."""
        index = self.read_index()
        if index and index.get("best") and (self.top / index["best"]).is_file():
            return self.top / index["best"]
        return None


def top_folder(run_dir: str | os.PathLike) -> Path:
    """Where a run's evaluator keeps its top k: ``<run_dir>/evaluator/top``."""
    return RunDir(Path(run_dir)).top


def read_run_index(run_dir: str | os.PathLike) -> dict | None:
    """A run's top-k index, read-only (plots, ``forcegrasp eval``); None if it has none yet."""
    return RunDir(Path(run_dir)).read_index()
