"""The shipped policies and `forcegrasp report`: every committed policy matches its env and
succeeds at the rate its record and docs/results.md claim; the quick report agrees with the full;
the scripted rows run on the policies' placements; the figures draw every arm, and the
randomised family beside the 5x-only one."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements, run_episode
from forcegrasp.policy import Policy
from forcegrasp.policy_file import load_policy_file
from forcegrasp.report import ARMS, POLICIES_DIR, TABLE_I, Shipped, shipped_policies, wilson
from forcegrasp.task import proprioception_of

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
        cmd = "-cmd" if s.proprioception == "commanded" else ""
        fixed = "" if s.randomised else "-5x"
        assert s.name == f"{'+'.join(s.objects)}-{'ff' if s.force_feedback else 'noff'}{cmd}{fixed}-s{s.meta['seed']}"
    assert any(s.randomised for s in SHIPPED) and any(not s.randomised for s in SHIPPED)  # both families


def test_each_shipped_policys_arm_comes_from_its_file_and_sidecar():
    """The sidecar's force feedback and proprioception are the file's (measured and commanded
    policies observe the same sizes); the report sorts by object, arm, family (randomised first), seed."""
    for s in SHIPPED:
        meta = load_policy_file(s.path)[1]
        assert (meta.force_feedback, proprioception_of(meta)) == s.arm, s.name
        assert s.arm in ARMS
    arms = list(ARMS)
    assert [s.name for s in SHIPPED] == [s.name for s in sorted(SHIPPED, key=lambda s: (
        s.multi, "+".join(s.objects), arms.index(s.arm), not s.randomised, s.meta["seed"]))]


def test_a_sidecar_without_proprioception_is_refused(tmp_path, capsys):
    from forcegrasp.cli.report import main as report_main

    src = SHIPPED[0]
    shutil.copyfile(src.path, tmp_path / src.path.name)
    (tmp_path / f"{src.name}.json").write_text(json.dumps({k: v for k, v in src.meta.items() if k != "proprioception"}))
    with pytest.raises(ValueError, match=rf"{src.name}\.json: \"proprioception\" must be one of measured, commanded"):
        shipped_policies(tmp_path)
    assert report_main(["--policies", str(tmp_path), "--out", str(tmp_path / "docs")]) == 2
    assert "re-ship the policy or add the key" in capsys.readouterr().err


@pytest.mark.parametrize("shipped", SHIPPED, ids=[s.name for s in SHIPPED])
def test_shipped_policy_fits_its_env_and_succeeds_as_claimed(shipped):
    policy = Policy.load(shipped.path)
    meta = policy.metadata
    if shipped.multi:  # its objects' scores are checked by the report's generalist rows
        assert meta.extra["objects"] == shipped.objects and meta.object_name == ""
        return
    # its object, observation and action step sizes, at the conditions its record was tested under
    env = FunctionalGraspEnv.for_policy(meta, mass_scale_range=None, torque_noise_range=None, mass_scale=5.0)
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


def quick_sample() -> list[Shipped]:
    """The policies the quick report re-runs: every arm and both training families on one object,
    plus a policy of a second object. Each shipped policy's own claim is checked one by one above;
    this sample checks the report end to end in a time that does not grow with each policy shipped."""
    sample = [s for s in SHIPPED if s.obj == "mug" and s.name.endswith("-s0")]
    sample += [s for s in SHIPPED if s.name == "camera-ff-s0"]
    assert {s.arm for s in sample} == set(ARMS) and any("-5x-" not in s.name for s in sample), [s.name for s in sample]
    return sample


def test_quick_report_agrees_with_the_committed_results(tmp_path):
    from forcegrasp.report import PROTOCOLS

    full = json.loads(RESULTS.read_text())
    assert full["protocol"] == "full"
    assert set(full["policies"]) == {s.name for s in SHIPPED if not s.multi}, "docs/results.md is older than assets/policies/"
    assert set(full.get("generalists", {})) == {s.name for s in SHIPPED if s.multi}
    sample, policies = quick_sample(), tmp_path / "policies"
    policies.mkdir()
    for s in sample:
        shutil.copyfile(s.path, policies / s.path.name)
        shutil.copyfile(s.path.with_suffix(".json"), policies / f"{s.name}.json")
    out = tmp_path / "docs"
    proc = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "report", "--quick", "--policies", str(policies),
                           "--out", str(out), "--no-strips"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    quick = json.loads((out / "results.json").read_text())
    assert (out / "results.md").read_text().count("| ") > 10
    for png in ("force-feedback", "adaptation", "lighter", "torque-noise", "trajectories"):
        assert (out / "results" / f"{png}.png").stat().st_size > 5000
    assert set(quick["policies"]) == {s.name for s in sample}
    for name, row in quick["policies"].items():
        for kind in ("held_out", "mass", "noise", "condition"):
            for value, cell in row[kind].items():
                claimed = full["policies"][name][kind][value]
                assert agree((cell["successes"], cell["episodes"]), (claimed["successes"], claimed["episodes"])), \
                    (name, kind, value, cell, claimed)
    assert set(quick["scripted"]) == {s.obj for s in sample}
    for obj, modes in quick["scripted"].items():
        assert set(modes) == {"told", "blind"}
        for mode, kinds in modes.items():
            assert kinds["held_out"][""]["episodes"] == PROTOCOLS["quick"]["held_out"] and set(kinds["mass"]) == {"1", "0.5"}
            for kind, cells in kinds.items():  # once the committed results carry the scripted rows
                for value, cell in cells.items():
                    claimed = full.get("scripted", {}).get(obj, {}).get(mode, {}).get(kind, {}).get(value)
                    assert claimed is None or agree((cell["successes"], cell["episodes"]),
                                                    (claimed["successes"], claimed["episodes"])), (obj, mode, kind, value)


def test_scripted_rows_run_on_the_policies_placements():
    """Told the offset, the straight approach grasps the mug at 5x on (nearly) every held-out placement;
    blind, far fewer: on the very placements (offsets, episode seeds) the policies run."""
    from forcegrasp.report import BAR_CONDITIONS, run_experiments, scripted_env
    from forcegrasp.report_summary import summarise_scripted

    mug = next(s for s in SHIPPED if s.obj == "mug" and s.arm == TABLE_I)
    protocol = {"held_out": 8, "mass": 2, "noise": 1, "condition": 2}
    results, scripted = run_experiments([mug], protocol, workers=1, log=lambda s: None)
    for kind, values in (("held_out", [""]), ("mass", ["1", "0.5"]), ("condition", ["jitter_3cm", "0.5x_1cm"])):
        for value in values:
            offsets = [e["offset"] for e in results[mug.name][kind][value]]
            assert len(offsets) == protocol[kind]
            for mode in ("told", "blind") if kind != "condition" else ("told",):
                assert [e["offset"] for e in scripted["mug"][mode][kind][value]] == offsets, (mode, kind, value)
    assert set(results[mug.name]["condition"]) == set(BAR_CONDITIONS)
    assert "noise_0.5" not in scripted["mug"]["told"]["condition"] and "condition" not in scripted["mug"]["blind"]
    env = scripted_env("mug", "mass", 0.5)  # the policies' conditions: 0.5x mass, 0.03 m, their jitter
    assert (env.mass_scale, env.object_tolerance, env.jitter) == (0.5, 0.03, mug.meta["env"]["jitter"])
    summary = summarise_scripted(scripted)["mug"]
    assert set(summary["told"]) == {"held_out", "mass", "condition"}  # no noise: the script ignores observations
    told, blind = summary["told"]["held_out"][""]["successes"], summary["blind"]["held_out"][""]["successes"]
    assert told >= 7 and blind <= told - 3, (told, blind)


def _row(obj: str, arm: tuple[bool, str], seed: int, held: tuple[int, int]) -> dict:
    k, n = held
    return {"object": obj, "force_feedback": arm[0], "proprioception": arm[1], "seed": seed,
            "held_out": {"": {"successes": k, "episodes": n, "rate": k / n, "ci95": wilson(k, n)}}, "mass": {}, "noise": {}}


def _cell(k: int, n: int) -> dict:
    return {"successes": k, "episodes": n, "rate": k / n, "ci95": wilson(k, n)}


def test_fig4_groups_every_arm_with_the_scripted_lines(tmp_path):
    from forcegrasp.cli.report import results_table
    from forcegrasp.cli.report_figures import _plt, draw_force_feedback, fig_force_feedback

    arms = list(ARMS)
    four = {f"{o}-{j}-s{seed}": _row(o, arm, seed, (18 - 3 * j, 20)) for o in ("mug", "camera")
            for j, arm in enumerate(arms) for seed in (0, 1) if not (o == "camera" and j == 3)}
    two = {k: r for k, r in four.items() if (r["force_feedback"], r["proprioception"]) in arms[:2]}
    scripted = {o: {"told": {"held_out": {"": _cell(20, 20)}}, "blind": {"held_out": {"": _cell(6, 20)}}}
                for o in ("mug", "camera")}
    for summary, drawn in ((four, arms), (two, arms[:2])):
        fig, ax = _plt().subplots()
        draw_force_feedback(ax, summary, ["mug", "camera"], scripted)
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert [label for label in labels if label in ARMS.values()] == [ARMS[a] for a in drawn]
        assert len(ax.patches) == 2 * len(drawn) - (len(drawn) == 4)  # the camera has no commanded-only policy
        assert {round(p.get_width(), 3) for p in ax.patches} == {round(0.94 * 0.8 / len(drawn), 3)}
        assert [t.get_text() for t in ax.texts] == (["not\ntrained"] if len(drawn) == 4 else [])
        told = [line for line in ax.lines if line.get_label() == "scripted, told the offset"]
        blind = [line for line in ax.lines if line.get_label() == "scripted, blind (offset 0)"]
        assert len(told) == len(blind) == 1 and list(told[0].get_ydata()) == [100, 100]
        assert list(blind[0].get_ydata()) == [30, 30] and blind[0].get_linestyle() == ":"
        _plt().close(fig)
        assert fig_force_feedback(summary, ["mug", "camera"], tmp_path / "f.png", scripted).stat().st_size > 5000
    table = results_table(four, ["mug", "camera"], scripted)  # no randomised family: every Table I row
    assert table[0].startswith("| object | trained conditions | 1x mass, 3 cm |") and len(table) == 4
    assert table[2].startswith("| mug | **90%** (77%") and "| 100% / – / – / = / – |" in table[2]


def _light_row(obj: str, seed: int, randomised: bool, rate: int) -> dict:
    """A `summarise` row of Table I's arm with every Fig. 7/8 cell at ``rate`` of 10 and the bar's
    conditions at ``rate`` of 10 too."""
    from forcegrasp.report import BAR_CONDITIONS, MASSES, NOISE_LEVELS

    return {**_row(obj, TABLE_I, seed, (rate, 10)), "randomised": randomised,
            "mass": {f"{m:g}": _cell(rate, 10) for m in MASSES},
            "noise": {f"{v:g}": _cell(rate, 10) for v in NOISE_LEVELS},
            "condition": {c: _cell(rate, 10) for c in BAR_CONDITIONS}}


def test_the_randomised_family_is_reported_beside_the_5x_only_one():
    """With both families shipped, the table, Fig. 7 and Fig. 8 report the randomised policies and
    draw the 5x-only ones beside them (hatched bars, dashed lines in the object's colour); the
    ablation compares the fixed family only; with one family there is no comparison."""
    from forcegrasp.cli.report import results_table
    from forcegrasp.cli.report_figures import _plt, draw_lighter, draw_noise
    from forcegrasp.report import MASSES, ablation_rows, robust_and_reference

    objects = ["mug", "camera"]
    summary = {f"{o}-ff-s0": _light_row(o, 0, True, 10) for o in objects}
    summary |= {f"{o}-ff-5x-s0": _light_row(o, 0, False, 4) for o in objects}
    summary["mug-noff-5x-s0"] = {**_light_row("mug", 0, False, 2), "force_feedback": False}
    robust, reference = robust_and_reference(summary)
    assert set(robust) == {"mug-ff-s0", "camera-ff-s0"} and set(reference) == {"mug-ff-5x-s0", "camera-ff-5x-s0",
                                                                               "mug-noff-5x-s0"}
    assert set(ablation_rows(summary)) == set(reference)
    assert robust_and_reference({k: v for k, v in summary.items() if "5x" in k}) == (
        {k: v for k, v in summary.items() if "5x" in k}, None)
    assert all("**100%**" in line for line in results_table(summary, objects, {})[2:])  # the randomised rows
    scripted = {o: {"told": {"mass": {"1": _cell(10, 10), "0.5": _cell(9, 10)}}} for o in objects}
    for given in (reference, None):
        fig, (light, noise) = _plt().subplots(1, 2)
        draw_lighter(light, robust, objects, scripted, given)
        draw_noise(noise, robust, objects, given)
        hatched = [p for p in light.patches if p.get_hatch()]
        labels = [t.get_text() for t in light.get_legend().get_texts()]
        dashed = {line.get_label(): line for line in noise.lines if line.get_linestyle() == "--"}
        solid = {line.get_label(): line for line in noise.lines if line.get_linestyle() == "-"}
        assert all(list(line.get_ydata()) == [100.0] * 11 for line in solid.values())
        if given is None:
            assert not hatched and not dashed and len(light.patches) == len(objects) * len(MASSES)
        else:
            assert len(hatched) == len(light.patches) / 2 == len(objects) * len(MASSES)
            assert [p.get_height() for p in hatched] == [40.0] * len(hatched)  # Table I's arm of the 5x family
            assert {"1x mass, trained at 5x only", "0.5x mass, trained at 5x only"} <= set(labels)
            assert sorted(dashed) == sorted(f"{o}, trained at 5x only" for o in objects)
            for o in objects:
                assert dashed[f"{o}, trained at 5x only"].get_color() == solid[o].get_color()
                assert list(dashed[f"{o}, trained at 5x only"].get_ydata()) == [40.0] * 11
        diamonds = [line for line in light.lines if line.get_marker() == "D"]
        assert len(diamonds) == len(objects) * len(MASSES) and "scripted, told the offset" in labels
        _plt().close(fig)


def test_the_robustness_section_marks_each_policy_against_the_bar():
    from forcegrasp.cli.report_bar import misses, robustness_section

    good = _light_row("mug", 0, True, 10)
    short = _light_row("mug", 1, True, 10)
    short["condition"]["noise_0.5"] = _cell(8, 10)
    short["condition"]["0.5x_1cm"] = _cell(1, 10)  # the 1 cm conditions have no bar
    fixed = _light_row("mug", 0, False, 4)
    assert misses(good) == [] and misses(short) == ["torque noise 0.5 N·m: 80%"]
    assert len(misses(fixed)) == 5
    scripted = {"mug": {"told": {"held_out": {"": _cell(10, 10)}, "condition": {"jitter_3cm": _cell(7, 10)}}}}
    text = "\n".join(robustness_section({"mug-ff-s0": good, "mug-ff-s1": short, "mug-ff-5x-s0": fixed},
                                        ["mug"], scripted))
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert [r.split("`")[1] for r in rows] == ["mug-ff-s0", "mug-ff-s1", "mug-ff-5x-s0"]  # randomised first
    assert rows[1].count("*") == 2 and rows[2].count("*") == 10  # the misses in italics, 1 cm never
    assert "| scripted, told the offset: mug | – | – | 100% [" in text and "= trained" in text
    assert "1 of the 2 policies trained with randomisation meet every bar; short of it: `mug-ff-s1` " \
           "(torque noise 0.5 N·m: 80%)." in text
    assert robustness_section({"mug-noff-s0": {**good, "force_feedback": False}}, ["mug"], {}) == []


def test_ship_copies_the_marked_pick_with_its_record(tmp_path):
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
    assert meta["held_out"]["condition"] == "5x"  # tested at the paper's conditions, whatever it trained on
    assert meta["picked_by"] == ("the evaluator's top 5 by 4 placements per condition (5x, 1x_3cm, 0.5x_3cm, "
                                 "noise_0.5, jitter_3cm), ranked on their mean, re-scored on 20 each; the best")
    assert meta["recipe"]["actor"]["demo_episodes"] == 2
    assert meta["recipe"]["sac"]["privileged_critic"] is True  # the recipe's settings, not only the overrides
    assert meta["recipe"]["sac"]["critic_layer_norm"] is True
    fixed = load_config(env={}, overrides=[f"env.object={src.obj}", "run.name=r", "env.mass_scale_range=[]",
                                           "env.torque_noise_range=[]", "env.jitter_range=[]"]).to_dict()
    (run / "experiment.json").write_text(json.dumps({**record, "config": fixed}))
    assert ship_main([str(run), "--out", str(out), "--episodes", "1", "--workers", "1"]) == 0
    five = f"{src.obj}-{'ff' if src.force_feedback else 'noff'}-5x-s7"  # the paper's fixed conditions only
    assert json.loads((out / f"{five}.json").read_text())["env"]["mass_scale_range"] == []
    (run / "experiment.json").write_text(json.dumps(record))
    assert ship_main([str(run), "--mark", "10", "--out", str(out)]) == 2  # no such mark: a clear error
    (run / "experiment.json").write_text(json.dumps({k: v for k, v in record.items() if k not in ("format", "version")}))
    assert ship_main([str(run), "--out", str(tmp_path / "none")]) == 2  # a record of before versions: refused
    assert not (tmp_path / "none").exists()


def test_serve_hands_out_a_shipped_policy_like_an_evaluator(tmp_path):
    """`forcegrasp serve FILE`: `forcegrasp best` gets the same bytes over HTTP and over Zenoh."""
    import signal

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


def _two_object_policy(folder: Path) -> Shipped:
    """A shipped policy of two objects, mug and camera, made of the shipped mug policy's weights:
    on the mug it grasps like that policy; the camera is a task it never learnt."""
    import dataclasses

    from forcegrasp.policy_file import save_policy_file

    src = next(s for s in SHIPPED if s.obj == "mug" and s.arm == TABLE_I)
    weights, meta = load_policy_file(src.path)
    meta = dataclasses.replace(meta, object_name="", extra={**meta.extra, "objects": ["mug", "camera"]})
    folder.mkdir(parents=True, exist_ok=True)
    path = save_policy_file(folder / "mug+camera-ff-s0.safetensors", weights, meta)
    path.with_suffix(".json").write_text(json.dumps({**src.meta, "object": "", "objects": ["mug", "camera"]}))
    return Shipped(path, json.loads(path.with_suffix(".json").read_text()))


def test_a_policy_of_several_objects_is_tested_on_each_and_zero_shot_on_the_others(tmp_path):
    """The report runs a generalist on each of its objects (the env of that object: the mug weights
    grasp the mug) and zero-shot on the paper's objects it never saw; the section and figure show it."""
    from forcegrasp.cli.report import generalists_section
    from forcegrasp.cli.report_figures import draw_generalists, generalist_cells
    from forcegrasp.report import run_experiments
    from forcegrasp.report_summary import summarise, summarise_generalists

    two = _two_object_policy(tmp_path / "policies")
    assert two.multi and two.objects == ["mug", "camera"] and shipped_policies(tmp_path / "policies") == [two]
    protocol = {"held_out": 6, "mass": 0, "noise": 0, "trajectory": 0, "condition": 0}
    results, scripted = run_experiments([two], protocol, workers=2, log=lambda s: None)
    assert scripted == {} and summarise([two], results) == {}  # no one-object rows, no scripted rows
    row = summarise_generalists([two], results)[two.name]
    assert set(row["object"]) == {"mug", "camera"} and set(row["unseen"]) == {"spray_bottle", "power_drill"}
    assert all(c["episodes"] == 6 for c in [*row["object"].values(), *row["unseen"].values()])
    assert row["object"]["mug"]["successes"] >= 5  # run on the mug, where these weights grasp
    assert row["object"]["camera"]["successes"] <= 2  # and on the camera, which they never learnt
    failed = 6 - row["unseen"]["power_drill"]["successes"]
    assert sum(row["unseen"]["power_drill"]["failures"].values()) == failed
    lines = generalists_section({two.name: row}, {}, None, str)
    assert lines[0] == "## One policy for several objects"
    assert any(line.startswith(f"| `{two.name}` | 0 |") and "*" in line for line in lines)  # zero-shot in italics
    assert generalist_cells({}, {two.name: row}, "mug")[1] == (row["object"]["mug"]["successes"], 6)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    assert draw_generalists(ax, {}, {two.name: row}) == ["mug", "camera", "spray_bottle", "power_drill"]
    assert len(ax.patches) == 4  # a trained-on bar for mug and camera, a zero-shot bar for the other two
    plt.close(fig)


def test_ship_names_and_tests_a_policy_of_several_objects_on_each(tmp_path):
    from forcegrasp.cli.experiment import effective_settings
    from forcegrasp.cli.ship import main as ship_main
    from forcegrasp.config import load_config

    two = _two_object_policy(tmp_path / "made")
    run = tmp_path / "run"
    (run / "marks").mkdir(parents=True)
    (run / "marks" / "best-005.0.safetensors").write_bytes(two.path.read_bytes())
    overrides = ['env.objects=["mug","camera"]', "actor.demo_episodes=2"]
    record = {"format": "forcegrasp-experiment", "version": 2, "label": "x", "seed": 3, "test_seed": 0,
              "config": load_config(env={}, overrides=overrides).to_dict(),
              "effective": effective_settings(load_config(env={}, overrides=overrides)),
              "marks": [{"minute": 5.0, "files": {"best": "best-005.0.safetensors"},
                         "steps": {"best": two.meta["picked_step"], "latest": 999999}, "test": {}}]}
    (run / "experiment.json").write_text(json.dumps(record))
    out = tmp_path / "policies"
    assert ship_main([str(run), "--out", str(out), "--episodes", "4", "--workers", "2"]) == 0
    meta = json.loads((out / "mug+camera-ff-s3.json").read_text())
    assert meta["object"] == "" and meta["objects"] == ["mug", "camera"]
    each = meta["held_out"]["objects"]
    assert set(each) == {"mug", "camera"} and each["mug"]["success_rate"] >= 0.75 >= each["camera"]["success_rate"]
    assert meta["held_out"]["success_rate"] == min(r["success_rate"] for r in each.values())  # the worst object's
    (shipped,) = shipped_policies(out)
    assert shipped.multi and shipped.objects == ["mug", "camera"]


def test_a_report_carries_over_the_episodes_of_unchanged_policy_files_only(tmp_path):
    """``--reuse``: a policy whose file is byte-for-byte what the previous report tested keeps its
    episodes (only its trajectories and the settings it lacks run again); a changed file or another
    protocol runs afresh; the scripted cells it has are not run again."""
    from forcegrasp.report import carried_over, file_digest, run_experiments

    folder = tmp_path / "policies"
    folder.mkdir()
    for s in SHIPPED[:2]:
        for suffix in (".safetensors", ".json"):
            shutil.copyfile(s.path.with_suffix(suffix), folder / f"{s.name}{suffix}")
    a, b = shipped_policies(folder)
    kept = {"held_out": {"": [{"index": 0, "offset": [0.0, 0.0], "success": False, "failure": "made up", "length": 1}]}}
    cells = {mode: {"held_out": {"": {"successes": 1, "episodes": 2}}} for mode in ("told", "blind")}
    previous = {"protocol": "quick", "digests": {a.name: file_digest(a.path), b.name: "0" * 64},
                "episodes": {a.name: kept, b.name: kept}, "scripted": {a.obj: cells}}
    done, scripted_done = carried_over(previous, [a, b], "quick")
    assert list(done) == [a.name] and scripted_done == {a.obj: cells}  # b's file is not the one tested
    assert carried_over(previous, [a, b], "full") == ({}, {})  # another protocol measures other counts
    assert carried_over(None, [a, b], "quick") == ({}, {})
    protocol = {"held_out": 2, "mass": 0, "noise": 0, "trajectory": 3, "condition": 0}
    results, scripted = run_experiments([a], protocol, workers=2, log=lambda s: None, done=done,
                                        scripted_done=scripted_done)
    assert results[a.name]["held_out"] == kept["held_out"] and scripted == {}  # nothing ran again...
    assert len(results[a.name]["trajectory"][""]) == 3  # ...but the trajectories, which are not kept
    more = {**protocol, "mass": 1}  # an experiment the previous report did not run: only it runs
    results, scripted = run_experiments([a], more, workers=2, log=lambda s: None, done=done, scripted_done=scripted_done)
    assert results[a.name]["held_out"] == kept["held_out"] and len(results[a.name]["mass"]["0.5"]) == 1
    assert set(scripted[a.obj]["told"]) == {"mass"}
    assert done[a.name] == kept  # the caller's record is not changed


def test_the_four_arms_section_states_each_arms_pooled_rate_and_words_only_the_arms_shipped():
    from forcegrasp.cli.report import ablation_section

    def row(obj, ff, proprioception, k, n):
        return {"object": obj, "force_feedback": ff, "proprioception": proprioception,
                "held_out": {"": {"successes": k, "episodes": n, "rate": k / n}}}

    summary = {"a": row("mug", True, "measured", 100, 100), "b": row("mug", False, "commanded", 30, 50),
               "c": row("mug", False, "commanded", 31, 50)}  # two seeds pool to 61 of 100
    scripted = {"mug": {"told": {"held_out": {"": {"rate": 1.0}}}, "blind": {"held_out": {"": {"rate": 0.25}}}}}
    text = "\n".join(ablation_section(summary, ["mug"], scripted))
    lo, hi = wilson(61, 100)
    assert f"| mug | 100% [{wilson(100, 100)[0]:.0%}–100%] | – | – | 61% [{lo:.0%}–{hi:.0%}] | 100% / 25% |" in text
    assert "one open-loop trajectory" in text and f"the mug 61% [{lo:.0%}–{hi:.0%}]" in text
    assert "is the gap between Table I's arm and commanded only: the mug 39 points." in text
    assert "torque sensors alone" not in text and "Measured only" not in text  # arms not shipped are not worded
