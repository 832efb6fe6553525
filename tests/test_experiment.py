"""`forcegrasp experiment`: a short real cluster run leaves marks, tests them, and resumes."""

import json
import threading

import pytest

from forcegrasp.cli import experiment
from forcegrasp.config import load_config
from forcegrasp.cli.experiment import RECORD, RecordError, check_record, online_at, plot_records, run_experiment
from forcegrasp.transport import free_tcp_port


def _watch_clock(path, stop, seen):
    """What a reader of the record on disk saw of the clock while the run went on."""
    while not stop.wait(0.5):
        try:
            seen.append(json.loads(path.read_text())["elapsed_s"])
        except (OSError, ValueError, KeyError):
            pass


def test_experiment_records_marks_tests_them_and_resumes(tmp_path, monkeypatch):
    monkeypatch.setattr(experiment, "CLOCK_SAVE_S", 3.0)
    port = free_tcp_port()
    config = load_config(overrides=[
        "run.name=exp", f"run.output_dir={tmp_path}", "env.object=camera", "actor.num_actors=1",
        "actor.envs_per_actor=2", "actor.random_steps=100", f'network.learner_listen=["tcp/127.0.0.1:{port}"]',
        "learner.sac.hidden=[16, 16]", "learner.sac.batch_size=32", "learner.sac.learning_starts=200",
        "learner.sac.updates_per_step=0.25", "learner.sac.n_step=3", "learner.sac.obs_norm=true",
        "learner.sac.privileged_critic=true", "evaluator.eval_every=300", "evaluator.eval_episodes=2",
        "evaluator.final_rank_episodes=2", "evaluator.http_port=0", "learner.checkpoint_every=400",
        "evaluator.conditions=[]",  # marks under the run's own env: the mix has its own test
    ])
    lines, seen, stop = [], [], threading.Event()
    run_dir = tmp_path / "exp"
    watcher = threading.Thread(target=_watch_clock, args=(run_dir / RECORD, stop, seen), daemon=True)
    watcher.start()
    try:
        record = run_experiment(config, minutes=0.75, mark_every=0.25, episodes=3, test_seed=0, label="tiny",
                                workers=2, log=lines.append)
    finally:
        stop.set()
        watcher.join()
    assert [m["minute"] for m in record["marks"]] == [0.25, 0.5, 0.75]
    final = record["marks"][-1]
    assert {"latest", "best"} <= set(final["files"]) and final["steps"]["latest"] > 0
    for m in record["marks"]:
        for kind, score in m["test"].items():
            assert score["episodes"] == 3 and 0.0 <= score["success_rate"] <= 1.0
            assert (run_dir / "marks" / m["files"][kind]).is_file()
    assert any("held-out success" in line for line in lines)
    online = final["online"]  # the actors' figure beside the held-out tests, read from TensorBoard
    assert 0.0 <= online["success_rate"] <= 1.0 and 0 < online["step"] <= final["steps"]["latest"]
    on_disk = json.loads((run_dir / RECORD).read_text())
    assert on_disk["elapsed_s"] >= 45 and on_disk["marks"] == record["marks"]
    assert list(on_disk)[:2] == ["format", "version"] and check_record(on_disk, "x") is on_disk
    # The clock reached the disk between marks too (a run killed outright loses at most
    # CLOCK_SAVE_S of it), and only ever forwards.
    between = {t for t in seen if all(abs(t - m["elapsed_s"]) > 0.5 for m in record["marks"]) and 0 < t < 45}
    assert len(between) >= 5, seen
    assert seen == sorted(seen)
    assert "resumed_at_s" not in record
    # Same command, longer budget: training resumes where it stopped and the clock counts on.
    steps_before = final["steps"]["latest"]
    again = run_experiment(config, minutes=1.0, mark_every=0.25, episodes=3, test_seed=0, label="tiny",
                           workers=2, log=lines.append)
    assert [m["minute"] for m in again["marks"]] == [0.25, 0.5, 0.75, 1.0]
    assert again["marks"][:3] == record["marks"]  # kept, not re-tested
    assert again["marks"][-1]["steps"]["latest"] > steps_before
    assert again["resumed_at_s"] == [on_disk["elapsed_s"]]
    assert any(line.startswith("experiment tiny: resuming at") for line in lines)
    assert plot_records([again], tmp_path / "x.png").stat().st_size > 10_000


def test_online_figure_is_the_last_logged_at_or_before_the_snapshot():
    scalars = {"actors/success_rate_100": ([100, 200, 300], [0.1, 0.5, 0.9]),
               "actors/return_mean_100": ([100, 200, 300], [10.0, 50.0, 90.0])}
    assert online_at(scalars, 250) == {"success_rate": 0.5, "return_mean": 50.0, "step": 200}
    assert online_at(scalars, 300)["success_rate"] == 0.9
    assert online_at(scalars, 99) is None  # nothing logged yet: no figure rather than a later one
    assert online_at({}, 1000) is None


def test_a_record_of_another_format_or_version_is_refused_naming_the_file_and_version(tmp_path, capsys):
    """--plot, ship and resuming read only version-2 records: an older one (no 'format'/'version')
    or another version is refused before anything starts."""
    assert check_record({"format": "forcegrasp-experiment", "version": 2}, "r.json")
    with pytest.raises(RecordError, match=r"r\.json: experiment record version 1 is not supported.*version 2"):
        check_record({"format": "forcegrasp-experiment", "version": 1}, "r.json")
    with pytest.raises(RecordError, match=r"r\.json: format 'other' is not an experiment record"):
        check_record({"format": "other", "version": 2}, "r.json")
    old = tmp_path / "old" / RECORD
    old.parent.mkdir()
    old.write_text(json.dumps({"label": "old", "seed": 0, "object": "camera", "marks": []}))
    with pytest.raises(SystemExit) as exit_:
        experiment.main(["--plot", str(tmp_path / "x.png"), str(old.parent)])
    assert exit_.value.code == 2 and not (tmp_path / "x.png").exists()
    err = capsys.readouterr().err
    assert f"{old}: not a versioned experiment record" in err and "version 2" in err
    config = load_config(env={}, overrides=["run.name=old", f"run.output_dir={tmp_path}"])
    with pytest.raises(RecordError, match="not a versioned experiment record"):
        run_experiment(config, minutes=1.0, mark_every=0.5, episodes=1, test_seed=0, label="old")
    assert json.loads(old.read_text())["label"] == "old"  # left as it was
