"""bench/ablation_table.py: levers are named from each record's own settings, a mark a run never
reached stays empty (never filled from another mark), steps to 90 % come from the pick that first
reached it, the table regenerates from the records kept in experiments/ alone, and a file that is not
a version-2 experiment record is refused, naming it."""

import importlib.util
import json
from pathlib import Path

import pytest

from forcegrasp.cli.experiment import RecordError, effective_settings
from forcegrasp.config import load_config

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("ablation_table", ROOT / "bench" / "ablation_table.py")
ablation_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ablation_table)
FIXTURES = ROOT / "tests" / "data" / "experiments"
EXPERIMENTS = ROOT / "experiments"


#: The table's baseline: the default recipe at the paper's fixed conditions, without observation
#: normalisation (what joined the recipe with the randomisation).
FIXED = ("env.mass_scale_range=[]", "env.torque_noise_range=[]", "env.jitter_range=[]", "evaluator.conditions=[]", "learner.sac.obs_norm=false")


def record(seed, marks, *overrides, obj="camera"):
    """A version-2 record of a run at the table's baseline with these configuration overrides, as
    `forcegrasp experiment` writes it."""
    config = load_config(env={}, overrides=[f"env.object={obj}", f"run.seed={seed}", *FIXED, *overrides])
    rec = {"format": "forcegrasp-experiment", "version": 2, "seed": seed, "object": obj, "force_feedback": True,
           "config": config.to_dict(), "effective": effective_settings(config),
           "marks": [{"minute": m, "elapsed_s": 60 * m, "steps": {"latest": 12_000 * m, "best": 10_000 * m},
                      "test": {"best": {"episodes": 50, "success_rate": s}}} for m, s in marks]}
    return json.loads(json.dumps(rec))  # as read back from disk: tuples become lists


def name(rec):
    return ablation_table.lever_name(ablation_table.settings(rec), rec["object"])


def cells_of(row):
    return [c.strip() for c in row.strip("|").split("|")]


def test_lever_names_are_differences_from_the_baseline():
    assert name(record(0, [])) == name(record(0, [], obj="mug")) == "fast (fixed conditions)"
    # today's default, randomised and normalised, names what it adds to the baseline
    assert name(record(0, [], "env.mass_scale_range=[0.5, 5]", "env.torque_noise_range=[0, 1]",
                       "learner.sac.obs_norm=true")) == \
        "fast, mass_scale_range = [0.5, 5.0], obs_norm = True, torque_noise_range = [0.0, 1.0]"
    assert name(record(0, [], "learner.sac.n_step=3")) == "fast, n_step = 3"
    assert name(record(0, [], "learner.recipe=paper")) == \
        "fast, − critic_layer_norm, − privileged_critic, − updates_per_step"
    assert name(record(0, [], "actor.demo_episodes=0")) == "fast, − demo_episodes"
    assert name(record(0, [], "actor.demo_episodes=4")) == "fast (fixed conditions)"  # the object's number, named
    assert name(record(0, [], "learner.sac.critic_layer_norm=false", obj="mug")) == "fast, − critic_layer_norm"
    assert name(record(0, [], "learner.sac.critic_hidden=[512, 512]")) == "fast, critic_hidden = [512, 512]"
    more_envs = record(0, [], "learner.sac.updates_per_step=0.1", "actor.envs_per_actor=16",
                       "env.max_translation_step=0.008")
    assert name(more_envs) == "fast, envs_per_actor = 16, max_translation_step = 0.008, updates_per_step = 0.1"
    history = record(0, [], "env.torque_history=3")
    assert name(history) == "fast, torque_history = 3 (not Table I)"  # reported apart: it changes Table I
    # runs at the first action step sizes say so in one term
    first = record(0, [], "learner.sac.n_step=3", "env.max_translation_step=0.004", "env.max_rotation_step=0.02",
                   "env.max_h_step=0.025")
    assert name(first) == "fast, first action steps, n_step = 3"


def test_the_records_own_settings_win_over_what_its_overrides_mean_today():
    """The record keeps what the run trained with (`effective`), so it keeps its meaning when the
    recipe later changes; the run's seed is not a lever."""
    paper = record(3, [], "learner.recipe=paper", obj="mug")
    paper["effective"]["sac"]["critic_layer_norm"] = True
    assert name(paper) == "fast, − privileged_critic, − updates_per_step"
    fewer = record(3, [])
    fewer["effective"]["demo_episodes"] = 0  # e.g. the object's number was 0 when it ran
    assert name(fewer) == "fast, − demo_episodes"


def test_table_pools_seeds_and_leaves_unreached_marks_empty(tmp_path):
    paths = []
    for seed, marks in ((0, [(10.0, 0.5), (20.0, 1.0)]), (1, [(10.0, 0.7), (20.0, 0.9), (40.0, 1.0)])):
        paths.append(tmp_path / f"fast-s{seed}.json")
        paths[-1].write_text(json.dumps(record(seed, marks)))
    table = ablation_table.table(paths).splitlines()
    assert cells_of(table[0])[:4] == ["object", "force feedback", "setting", "seeds"]  # no labels-era column
    cells = cells_of(table[2])
    assert cells[:4] == ["camera", "yes", "fast (fixed conditions)", "0, 1"]
    assert cells[4] == "60 % [50–70] (n=2)"
    assert cells[5] == "95 % [90–100] (n=2)"
    assert cells[6] == "100 % (n=1)"
    assert cells[7] == "–"
    # seed 0 first reached 90 % at minute 20 (pick of step 200 k), seed 1 at minute 20 too (0.9)
    assert cells[8] == "200 k [200–200] (2 of 2)"
    assert cells[9] == "20, 40 min" and cells[10] == "200, 200"  # 12 k steps per 60 s


def test_steps_to_90_counts_the_runs_that_never_got_there(tmp_path):
    paths = [tmp_path / "a-s0.json", tmp_path / "a-s1.json"]
    paths[0].write_text(json.dumps(record(0, [(10.0, 0.95), (20.0, 0.5)])))  # reached, then fell
    paths[1].write_text(json.dumps(record(1, [(10.0, 0.2), (20.0, 0.89)])))  # never reached
    assert cells_of(ablation_table.table(paths).splitlines()[2])[8] == "100 k (1 of 2)"
    paths[0].write_text(json.dumps(record(0, [(10.0, 0.1)])))
    assert cells_of(ablation_table.table(paths).splitlines()[2])[8] == "– (0 of 2)"


def test_table_from_a_fixture_folder_of_records():
    """Three records as `forcegrasp experiment` writes them: the default recipe (seed 0), n-step 3
    in its own row, and one scored on a mix of test conditions, which is the robustness table's."""
    table = ablation_table.table(sorted(FIXTURES.glob("*.json"))).splitlines()
    assert len(table) == 4
    assert table[2] == ("| camera | yes | fast (fixed conditions) | 0 | 80 % (n=1) | 96 % (n=1) | – | – "
                        "| 50 k (1 of 1) | 20 min | 50 |")
    assert cells_of(table[3])[2:5] == ["fast, n_step = 3", "0", "90 % (n=1)"]
    assert ablation_table.main([str(p) for p in sorted(FIXTURES.glob("*.json"))]) == 0


def test_the_kept_records_regenerate_the_table_and_hold_every_shipped_run():
    """experiments/ holds the records of runs on today's grasp labels, all of version 2: the table
    is made from them alone, and every shipped policy's sidecar names a run whose record is there."""
    paths = sorted(EXPERIMENTS.glob("*.json"))
    assert len(paths) >= 100
    table = ablation_table.table(paths)
    assert ("| mug | yes | fast, actor_ema = 0.002 | 0, 1 | 100 % [100–100] (n=2) | 100 % (n=1) | 100 % (n=1) "
            "| 99 % (n=1) | 83 k [79–87] (2 of 2) | 60, 15 min | 353, 347 |") in table.splitlines()
    runs = {json.loads(p.read_text())["config"]["run"]["name"] for p in paths}
    for sidecar in sorted((ROOT / "assets" / "policies").glob("*.json")):
        assert json.loads(sidecar.read_text())["run"]["name"] in runs, sidecar.name
    for path in paths:  # no machine's absolute paths
        assert '"/' not in path.read_text(), path.name


def test_a_file_that_is_not_a_version_2_record_is_refused_naming_it(tmp_path, capsys):
    good = tmp_path / "good.json"
    good.write_text(json.dumps(record(0, [(10.0, 1.0)])))
    unversioned = tmp_path / "old.json"  # as records were before they were versioned
    unversioned.write_text(json.dumps({k: v for k, v in record(0, [(10.0, 1.0)]).items()
                                       if k not in ("format", "version")}))
    with pytest.raises(RecordError, match=r"old\.json: not a versioned experiment record .* version 2"):
        ablation_table.table([good, unversioned])
    assert ablation_table.main([str(good), str(unversioned)]) == 2
    assert "old.json" in capsys.readouterr().err
    other = tmp_path / "v3.json"
    other.write_text(json.dumps({**record(0, []), "version": 3}))
    with pytest.raises(RecordError, match=r"v3\.json: experiment record version 3 is not supported"):
        ablation_table.table([other])
    spread = tmp_path / "spread.json"  # not an experiment record at all
    spread.write_text(json.dumps({"run": "x", "snapshots": []}))
    with pytest.raises(RecordError, match="spread.json"):
        ablation_table.table([spread])
