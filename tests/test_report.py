"""The shipped policies and `forcegrasp report`: every committed policy matches its env and
succeeds at the rate its record and docs/results.md claim; the quick report agrees with the full."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements, run_episode
from forcegrasp.policy import Policy
from forcegrasp.report import POLICIES_DIR, shipped_policies, wilson

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "docs" / "results.json"
SHIPPED = shipped_policies()
Z99 = 2.576


def agree(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Two success counts agree within sampling error: their 99 % Wilson intervals overlap."""
    lo_a, hi_a = wilson(*a, Z99)
    lo_b, hi_b = wilson(*b, Z99)
    return lo_a <= hi_b and lo_b <= hi_a


def test_policies_are_shipped():
    assert SHIPPED, f"no policies in {POLICIES_DIR}"
    for s in SHIPPED:
        assert s.name == f"{s.obj}-{'ff' if s.force_feedback else 'noff'}-s{s.meta['seed']}"


@pytest.mark.parametrize("shipped", SHIPPED, ids=[s.name for s in SHIPPED])
def test_shipped_policy_fits_its_env_and_succeeds_as_claimed(shipped):
    policy = Policy.load(shipped.path)
    meta = policy.metadata
    env = FunctionalGraspEnv.for_policy(meta)  # its object, observation and action step sizes
    assert meta.object_name == shipped.obj and meta.force_feedback == shipped.force_feedback
    assert meta.obs_dim == env.observation_space.shape[0] == (77 if shipped.force_feedback else 53)
    assert meta.act_dim == env.action_space.shape[0] == 7
    assert meta.training_steps == shipped.meta["picked_step"] <= shipped.meta["env_steps"]
    assert shipped.meta["env"]["mass_scale"] == 5.0 and shipped.meta["env"]["jitter"] == 0.02
    n = 20
    results = [run_episode(env, policy, p) for p in placements(0, n, env.jitter, "test", clear=env.is_clear)]
    k = sum(r.success for r in results)
    held = shipped.meta["held_out"]
    claims = {"its record": (round(held["success_rate"] * held["episodes"]), held["episodes"])}
    if RESULTS.is_file():
        report = json.loads(RESULTS.read_text())["policies"].get(shipped.name)
        if report is not None:
            cell = report["held_out"][""]
            claims["docs/results.md"] = (cell["successes"], cell["episodes"])
    for source, claim in claims.items():
        assert agree((k, n), claim), f"{shipped.name}: {k}/{n} here, {claim[0]}/{claim[1]} in {source}"


def test_quick_report_agrees_with_the_committed_results(tmp_path):
    full = json.loads(RESULTS.read_text())
    assert full["protocol"] == "full"
    assert set(full["policies"]) == {s.name for s in SHIPPED}, "docs/results.md is older than assets/policies/"
    proc = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "report", "--quick", "--out", str(tmp_path),
                           "--no-strips"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    quick = json.loads((tmp_path / "results.json").read_text())
    assert (tmp_path / "results.md").read_text().count("| ") > 10
    for png in ("force-feedback", "adaptation", "lighter", "torque-noise", "trajectories"):
        assert (tmp_path / "results" / f"{png}.png").stat().st_size > 5000
    for name, row in quick["policies"].items():
        for kind in ("held_out", "mass", "noise"):
            for value, cell in row[kind].items():
                claimed = full["policies"][name][kind][value]
                assert agree((cell["successes"], cell["episodes"]), (claimed["successes"], claimed["episodes"])), \
                    (name, kind, value, cell, claimed)


def test_ship_copies_the_marked_pick_with_its_record(tmp_path):
    import shutil

    from forcegrasp.cli.ship import main as ship_main
    from forcegrasp.config import load_config

    src = SHIPPED[0]
    run = tmp_path / "run"
    (run / "marks").mkdir(parents=True)
    shutil.copyfile(src.path, run / "marks" / "best-005.0.safetensors")
    config = load_config(env={}, overrides=[f"env.object={src.obj}", "run.name=r", "actor.demo_episodes=2"]).to_dict()
    from forcegrasp.cli.experiment import effective_settings

    effective = effective_settings(load_config(env={}, overrides=[f"env.object={src.obj}", "actor.demo_episodes=2"]))
    record = {"format": "forcegrasp-experiment", "version": 2, "label": "x", "seed": 7, "test_seed": 0,
              "config": config, "effective": effective, "marks": [
        {"minute": 5.0, "files": {"best": "best-005.0.safetensors"}, "steps": {"best": src.meta["picked_step"],
                                                                              "latest": 999999}, "test": {}}]}
    (run / "experiment.json").write_text(json.dumps(record))
    out = tmp_path / "policies"
    assert ship_main([str(run), "--out", str(out), "--episodes", "3", "--workers", "1"]) == 0
    name = f"{src.obj}-{'ff' if src.force_feedback else 'noff'}-s7"
    meta = json.loads((out / f"{name}.json").read_text())
    assert (out / f"{name}.safetensors").read_bytes() == src.path.read_bytes()
    assert meta["env_steps"] == 999999 and meta["wall_clock_min"] == 5.0 and meta["held_out"]["episodes"] == 3
    assert meta["recipe"]["actor"]["demo_episodes"] == 2
    assert meta["recipe"]["sac"]["privileged_critic"] is True  # the recipe's settings, not only the overrides
    assert meta["recipe"]["sac"]["critic_layer_norm"] is True
    assert ship_main([str(run), "--mark", "10", "--out", str(out)]) == 2  # no such mark: a clear error
    (run / "experiment.json").write_text(json.dumps({k: v for k, v in record.items() if k not in ("format", "version")}))
    assert ship_main([str(run), "--out", str(tmp_path / "none")]) == 2  # a record of before versions: refused
    assert not (tmp_path / "none").exists()


def test_serve_hands_out_a_shipped_policy_like_an_evaluator(tmp_path):
    """`forcegrasp serve FILE`: `forcegrasp best` gets the same bytes over HTTP and over Zenoh."""
    import signal
    import time

    from forcegrasp.transport import free_tcp_port

    src = SHIPPED[0]
    http_port, zenoh_port = free_tcp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    proc = subprocess.Popen([sys.executable, "-m", "forcegrasp.cli", "serve", str(src.path),
                             "--set", f"evaluator.http_port={http_port}",
                             "--set", f'network.learner_listen=["{endpoint}"]'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert "serving" in proc.stdout.readline()
        for how in (["--url", f"http://127.0.0.1:{http_port}"],
                    ["--set", f"run.name={src.name}", "--set", f'network.connect=["{endpoint}"]']):
            out = tmp_path / f"{len(how)}.safetensors"
            got = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "best", "--out", str(out), *how],
                                 capture_output=True, text=True, timeout=60)
            assert got.returncode == 0, got.stdout + got.stderr
            assert out.read_bytes() == src.path.read_bytes()
            assert json.loads(got.stdout)["success_rate"] == src.meta["held_out"]["success_rate"]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert proc.returncode == 0


def test_eval_and_replay_work_on_a_shipped_policy(tmp_path):
    """`forcegrasp eval FILE --log-dir` writes MCAP episodes that `forcegrasp replay` renders."""
    src = SHIPPED[0]
    got = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "eval", str(src.path), "--episodes", "1",
                          "--log-dir", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    (episode,) = (tmp_path / "as-given").glob("*.mcap")
    got = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "replay", str(episode), "--out",
                          str(tmp_path / "strip.png"), "--frames", "3"], capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    assert (tmp_path / "strip.png").stat().st_size > 10000
