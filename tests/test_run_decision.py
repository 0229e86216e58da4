"""A run's life decided once (``runs.decide_run``): reuse, resume, retrain (and why) or fresh,
for every state a run directory can be in."""

import json

import pytest

from benchmarks.suite.runs import CONFIG_FILE, RESUME_IGNORES, decide_run

torch = pytest.importorskip("torch")

CONFIG = {"case": "c", "model": "m", "overrides": [], "train": {"epochs": 2, "lr": 1e-3}}
FINISHED = ("record.json", "metrics.csv")


def _store(d, config=CONFIG, checkpoint=True, record=False):
    d.mkdir(exist_ok=True)
    (d / CONFIG_FILE).write_text(json.dumps(config))
    if checkpoint:
        from meshodenet.training.train import CHECKPOINT_KEYS

        torch.save({k: 0 for k in CHECKPOINT_KEYS}, d / "last.pt")
    if record:
        (d / "record.json").write_text(json.dumps({"config": config, "run": "x"}))
        (d / "metrics.csv").write_text("rmse\n")
    return d


def test_fresh_reuse_and_resume(tmp_path):
    assert decide_run(tmp_path / "none", CONFIG).action == "fresh"
    d = _store(tmp_path / "r", record=True)
    reuse = decide_run(d, CONFIG, finished=FINISHED)
    assert reuse.action == "reuse" and reuse.stored["run"] == "x"
    assert decide_run(d, CONFIG).action == "resume"  # meshbench train never reuses
    (d / "metrics.csv").unlink()  # not finished: resumed
    resume = decide_run(d, CONFIG, finished=FINISHED)
    assert resume.action == "resume" and resume.stored == CONFIG


@pytest.mark.parametrize("fault,problem", [
    ("changed", "config_changed"), ("unreadable", "bad_config"),
    ("no_checkpoint", "no_checkpoint"), ("bad_checkpoint", "bad_checkpoint")])
def test_a_run_that_cannot_continue_is_retrained_and_says_why(tmp_path, fault, problem):
    d = _store(tmp_path / "r", checkpoint=fault != "no_checkpoint")
    if fault == "changed":
        (d / CONFIG_FILE).write_text(json.dumps({**CONFIG, "train": {"epochs": 3, "lr": 1e-3}}))
    elif fault == "unreadable":
        (d / CONFIG_FILE).write_text("{")
    elif fault == "bad_checkpoint":
        (d / "last.pt").write_bytes(b"not a checkpoint")
    dec = decide_run(d, CONFIG, finished=FINISHED)
    assert dec.action == "retrain" and dec.problem == problem and dec.why
    if fault == "changed":
        assert dec.changes == ("train.epochs: 3 -> 2",)
        # meshbench train --resume continues through more epochs
        assert decide_run(d, CONFIG, ignore=RESUME_IGNORES).action == "resume"
