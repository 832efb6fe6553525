"""What `forcegrasp up` prints: a status line that fits 100 columns with every figure named, a
notice when a run resumes, and an exit summary that names the best policy file."""

from __future__ import annotations

import json

from forcegrasp.config import load_config
from forcegrasp.console import StatusPrinter, exit_summary, read_checkpoint_step, resume_notice, status_line
from forcegrasp.rundir import RunDir
from forcegrasp.sac import SAC, SACConfig

BIG = {
    "learner": {"ingested": 123_456_789, "updates": 98_765_432, "updates_per_s": 1234.0, "policy_version": 99999,
                "return_mean": -12345.6, "success_rate": 0.94, "rejected": 123456},
    "evaluator": {"evaluations": 12345, "best_success_rate": 0.88, "best_episodes": 100, "best_step": 123_000_000},
    **{f"actor-{i}": {"steps_per_s": 412.5, "policy_version": 99999} for i in range(16)},
}


def test_status_line_fits_100_columns_and_names_its_figures():
    for elapsed in (0.0, 59.0, 3600.0 * 99):
        line = status_line(BIG, elapsed)
        assert len(line) <= 100, line
    line = status_line(BIG, 600.0)
    assert "env steps" in line and "online success 94%" in line and "best held-out 88%" in line
    assert "6600/s" in line
    assert "waiting for the learner" in status_line({}, 3.0)


def test_a_long_line_without_a_curriculum_drops_its_optional_figures_and_still_prints():
    """Several objects' worst online success lengthens the line; with no curriculum there is no
    ranges figure to drop, and the line must still come out within its width."""
    stats = {**BIG, "learner": {**BIG["learner"], "objects": {
        "spray_bottle": {"success_rate": 0.5}, "power_drill": {"success_rate": 0.4}}}}
    line = status_line(stats, 1200.0, width=80)
    assert len(line) <= 80 and "updates" not in line and "actors" not in line
    assert line.startswith("20.0 min") and "worst power_drill 40%" in line


def test_status_line_shows_how_much_of_the_randomisation_ranges_the_actors_have_opened():
    stats = {"learner": {"ingested": 5000, "updates": 1200, "success_rate": 0.5},
             "actor-0": {"steps_per_s": 100.0, "curriculum_level": 0.2},
             "actor-1": {"steps_per_s": 100.0, "curriculum_level": 0.4}}
    line = status_line(stats, 60.0)
    assert "ranges 30% open" in line and len(line) <= 100
    assert "ranges" not in status_line({**stats, "actor-0": {"steps_per_s": 1.0}, "actor-1": {}}, 60.0)


def test_status_line_of_a_multi_object_run_names_its_worst_object_online():
    learner = {"ingested": 5000, "updates": 1200, "success_rate": 0.6,
               "objects": {"mug": {"episodes": 30, "success_rate": 0.8}, "camera": {"episodes": 20, "success_rate": 0.4},
                           "power_drill": {"episodes": 0, "success_rate": None}}}
    line = status_line({"learner": learner, "actor-0": {"steps_per_s": 100.0}}, 60.0)
    assert "online success 60% (worst camera 40%)" in line and len(line) <= 100


def test_status_is_rewritten_in_place_on_a_terminal_and_plain_in_a_log():
    out = []

    def write(text, end="\n"):
        out.append(text + end)

    tty = StatusPrinter(write, is_tty=True)
    tty.status("a")
    tty.status("b")
    tty.say("done")
    assert out[0].startswith("\ra") and out[1].startswith("\rb") and "\n" not in out[0] + out[1]
    assert out[2:] == ["\n", "done\n"]  # the status line is ended before a message
    out.clear()
    plain = StatusPrinter(write, is_tty=False, every_s=60.0)
    plain.status("a")
    plain.status("b")  # within the interval: not printed
    assert out == ["a\n"]


def _run_with_checkpoint_and_best(tmp_path, step=4321):
    config = load_config(env={}, overrides=["run.name=con", f"run.output_dir={tmp_path}"])
    files = RunDir.of(config)
    files.root.mkdir(parents=True)
    SAC(5, 2, SACConfig(hidden=(4,), device="cpu")).save_checkpoint(files.checkpoint, extra={"ingested": step})
    files.top.mkdir(parents=True)
    members = [{"file": "policy-000004000.safetensors", "step": 4000, "best": True, "rank_success_rate": 0.97,
                "rank_episodes": 100},
               {"file": "policy-000002000.safetensors", "step": 2000, "best": False, "rank_success_rate": 0.5,
                "rank_episodes": 100}]
    files.top_index.write_text(json.dumps({"members": members, "best": members[0]["file"]}))
    return config, files


def test_a_resumed_run_says_so(tmp_path):
    config, files = _run_with_checkpoint_and_best(tmp_path)
    assert read_checkpoint_step(files.checkpoint) == 4321
    notice = resume_notice(files)
    assert "resumed" in notice and "step 4,321" in notice and "keeps 2 checkpoints" in notice
    fresh = RunDir.of(load_config(env={}, overrides=["run.name=new", f"run.output_dir={tmp_path}"]))
    assert resume_notice(fresh) is None
    files.checkpoint.write_bytes(b"garbage")  # a corrupt checkpoint is not a resume the console can claim
    assert resume_notice(files) is None


def test_exit_summary_names_the_best_policy_file_and_how_to_fetch_it(tmp_path):
    config, files = _run_with_checkpoint_and_best(tmp_path)
    lines = exit_summary(files, {"learner": {"ingested": 5000}}, 125.0, "con")
    text = "\n".join(lines)
    assert "5,000 env steps in 2.1 min" in text
    assert str(files.top / "policy-000004000.safetensors") in text and "97% of 100" in text
    assert "forcegrasp best --set run.name=con" in text
