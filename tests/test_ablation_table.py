"""bench/ablation_table.py: levers are named from each record's own configuration, a mark a run
never reached stays empty (never filled from another mark), and steps to 90 % come from the pick
that first reached it."""

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("ablation_table", ROOT / "bench" / "ablation_table.py")
ablation_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ablation_table)
STEPS = {"max_translation_step": 0.006, "max_rotation_step": 0.03, "max_h_step": 0.0375}  # today's default


def record(seed, sac, marks, recipe="fast", demos=4, layer_norm=True):
    """A record without `effective` (as before 2026-12-05), at today's default unless told otherwise."""
    sac = {"critic_layer_norm": True, **sac} if layer_norm else sac
    return {"seed": seed, "object": "camera", "force_feedback": True,
            "config": {"learner": {"recipe": recipe, "sac": sac}, "actor": {"demo_episodes": demos},
                       "env": dict(STEPS)},
            "marks": [{"minute": m, "elapsed_s": 60 * m, "steps": {"latest": 12_000 * m, "best": 10_000 * m},
                       "test": {"best": {"episodes": 50, "success_rate": s}}} for m, s in marks]}


def test_lever_names_are_differences_from_the_default():
    name = lambda r: ablation_table.lever_name(ablation_table.settings(r), r["object"])  # noqa: E731
    assert name(record(0, {}, [])) == "fast (the default)"
    assert name(record(0, {"n_step": 3}, [])) == "fast, n_step = 3"
    assert name(record(0, {}, [], recipe="paper")) == "fast, − privileged_critic, − updates_per_step"
    assert name(record(0, {}, [], demos=0)) == "fast, − demo_episodes"
    # a record without `effective` is read with the presets of its day: `fast` had no LayerNorm, and
    # "-1 demonstrations" meant 4 on the mug and none elsewhere
    assert name(record(0, {}, [], layer_norm=False)) == "fast, − critic_layer_norm"
    assert name(record(0, {}, [], demos=-1)) == "fast, − demo_episodes"
    mug = lambda demos, ln=True: {**record(0, {}, [], demos=demos, layer_norm=ln), "object": "mug"}  # noqa: E731
    assert name(mug(4)) == name(mug(-1)) == "fast (the default)"
    assert name(mug(0)) == "fast, − demo_episodes"
    assert name(mug(-1, ln=False)) == "fast, − critic_layer_norm"
    more_envs = record(0, {"updates_per_step": 0.1}, [])
    more_envs["config"]["actor"]["envs_per_actor"] = 16
    more_envs["config"]["env"] = {**STEPS, "max_translation_step": 0.008}
    assert name(more_envs) == "fast, envs_per_actor = 16, max_translation_step = 0.008, updates_per_step = 0.1"
    history = record(0, {}, [])
    history["config"]["env"] = {**STEPS, "torque_history": 3}
    assert name(history) == "fast, torque_history = 3 (not Table I)"  # reported apart: it changes Table I
    # records from before the step keys, and runs at the first sizes, say so in one term
    earlier = record(0, {"n_step": 3}, [])
    del earlier["config"]["env"]
    assert name(earlier) == "fast, first action steps, n_step = 3"
    earlier["config"]["env"] = {"max_translation_step": 0.004, "max_rotation_step": 0.02, "max_h_step": 0.025}
    assert name(earlier) == "fast, first action steps, n_step = 3"


def test_table_pools_seeds_and_leaves_unreached_marks_empty(tmp_path):
    paths = []
    for seed, marks in ((0, [(10.0, 0.5), (20.0, 1.0)]), (1, [(10.0, 0.7), (20.0, 0.9), (40.0, 1.0)])):
        paths.append(tmp_path / f"n-fast-s{seed}.json")
        paths[-1].write_text(json.dumps(record(seed, {}, marks)))
    paths.append(tmp_path / "n-fast-spread.json")  # not an experiment record: ignored
    paths[-1].write_text(json.dumps({"run": "x", "snapshots": []}))
    row = ablation_table.table(paths).splitlines()[2]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:5] == ["human-like labels", "camera", "yes", "fast (the default)", "0, 1"]
    assert cells[5] == "60 % [50–70] (n=2)"
    assert cells[6] == "95 % [90–100] (n=2)"
    assert cells[7] == "100 % (n=1)"
    assert cells[8] == "–"
    # seed 0 first reached 90 % at minute 20 (pick of step 200 k), seed 1 at minute 20 too (0.9)
    assert cells[9] == "200 k [200–200] (2 of 2)"
    assert cells[10] == "20, 40 min" and cells[11] == "200, 200"  # 12 k steps per 60 s


def test_steps_to_90_counts_the_runs_that_never_got_there(tmp_path):
    paths = [tmp_path / "n-a-s0.json", tmp_path / "n-a-s1.json"]
    paths[0].write_text(json.dumps(record(0, {}, [(10.0, 0.95), (20.0, 0.5)])))  # reached, then fell
    paths[1].write_text(json.dumps(record(1, {}, [(10.0, 0.2), (20.0, 0.89)])))  # never reached
    cells = [c.strip() for c in ablation_table.table(paths).splitlines()[2].strip("|").split("|")]
    assert cells[9] == "100 k (1 of 2)"
    paths[0].write_text(json.dumps(record(0, {}, [(10.0, 0.1)])))
    cells = [c.strip() for c in ablation_table.table(paths).splitlines()[2].strip("|").split("|")]
    assert cells[9] == "– (0 of 2)"


def test_records_with_effective_settings_are_read_from_them():
    """Since per-object recipes, `forcegrasp experiment` records the settings a run trained with,
    so a record keeps its meaning when the recipe later changes; the run's seed is not a lever."""
    from forcegrasp.cli.experiment import effective_settings
    from forcegrasp.config import load_config

    def run(obj, *overrides):
        config = load_config(env={}, overrides=[f"env.object={obj}", "run.seed=3", *overrides])
        rec = {**record(3, {}, []), "object": obj, "config": config.to_dict(), "effective": effective_settings(config)}
        return json.loads(json.dumps(rec))  # as read back from disk: tuples become lists
    name = lambda r: ablation_table.lever_name(ablation_table.settings(r), r["object"])  # noqa: E731
    assert name(run("camera")) == name(run("mug")) == "fast (the default)"
    assert name(run("mug", "learner.sac.critic_layer_norm=false")) == "fast, − critic_layer_norm"
    assert name(run("camera", "actor.demo_episodes=0")) == "fast, − demo_episodes"
    assert name(run("camera", "learner.sac.critic_hidden=[512, 512]")) == "fast, critic_hidden = [512, 512]"
    paper = run("mug", "learner.recipe=paper")
    assert name(paper) == "fast, − critic_layer_norm, − privileged_critic, − updates_per_step"
    # the record's own settings win over what its overrides would mean under today's recipe
    paper["effective"]["sac"]["critic_layer_norm"] = True
    assert name(paper) == "fast, − privileged_critic, − updates_per_step"
