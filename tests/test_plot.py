"""`forcegrasp plot`: curves of one or several runs from their TensorBoard scalars and evaluator history."""

import json

import matplotlib.image
import pytest
from torch.utils.tensorboard import SummaryWriter

from forcegrasp.cli.plot import main, read_evaluations, run_label


def fake_run(root, name, force_feedback, success):
    run = root / name
    with SummaryWriter(str(run / "tb")) as writer:
        for step in range(0, 5000, 500):
            writer.add_scalar("actors/success_rate_100", success * step / 5000, step)
            writer.add_scalar("sac/alpha", 1.0 - step / 10000, step)
    (run / "config.toml").write_text(f'[env]\nobject = "mug"\nforce_feedback = {str(force_feedback).lower()}\n')
    top = run / "evaluator" / "top"
    top.mkdir(parents=True)
    history = [{"step": s, "score": float(s), "success_rate": success * s / 4000, "episodes": 10} for s in (4000, 2000)]
    (top / "index.json").write_text(json.dumps({"history": history}))
    return run


def test_plot_overlays_runs_into_one_png(tmp_path, capsys):
    a = fake_run(tmp_path, "with", True, 0.4)
    b = fake_run(tmp_path, "without", False, 0.1)
    assert run_label(a) == "with (mug, force feedback on)" and run_label(b) == "without (mug, force feedback off)"
    assert read_evaluations(a)["eval/success_rate"] == ([2000, 4000], [0.2, 0.4])  # sorted by step
    out = tmp_path / "cmp.png"
    assert main([str(a), str(b), "--out", str(out)]) == 0
    image = matplotlib.image.imread(out)
    assert image.shape[0] > 400 and image.shape[1] > 1000
    assert str(out) in capsys.readouterr().out


def test_plot_of_a_run_without_scalars_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "missing")])
    assert exc.value.code == 2 and "no TensorBoard scalars" in capsys.readouterr().err
