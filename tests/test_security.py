"""Opening a run directory received from someone else runs no code from it.

Checkpoints load with ``torch.load(..., weights_only=True)``: a ``best.pt`` / ``last.pt``
crafted to run a shell command when unpickled is refused (exit 2, one line, the command never
runs) by ``rollout``, ``train --resume`` and the suite runner; a trusted old-format file is
converted only on request (``meshbench convert-checkpoint --i-trust-this-file``); genuine
checkpoints resume and roll out bit for bit as before. Ids that name directories cannot hold
path parts. See docs/SECURITY.md.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmarks.cli import main
from groundtruth import store

TINY = "rod_tiny_security"
SUITE = "security_one"
PLUGIN = f"""
from benchmarks.suite.registry import register_case
from benchmarks.suite.suites import RunSpec, Suite, register_suite
from groundtruth.cases import RodCase

register_case(RodCase(id="{TINY}", n_train=4, n_test=2, t_end=0.5), overwrite=True)
register_suite(Suite("{SUITE}", "one short run", (RunSpec("{TINY}", "mgn", "smoke"),)),
               overwrite=True)
"""


class Payload:
    """Unpickling this runs ``touch SENTINEL`` (what a malicious checkpoint would do)."""

    def __init__(self, sentinel: Path):
        self.sentinel = sentinel

    def __reduce__(self):
        return os.system, (f"touch {self.sentinel}",)


def write_crafted(path: Path, sentinel: Path, how: str = "torch") -> None:
    obj = {"model": Payload(sentinel), "epoch": 1}
    if how == "torch":
        torch.save(obj, path)
    else:  # a plain pickle: protocol 2 meets the refused global, 5 an unknown opcode first
        with open(path, "wb") as f:
            pickle.dump(obj, f, protocol=int(how[-1]))


def one_line_error(stderr: str, *needles) -> str:
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    assert "Traceback" not in stderr, stderr
    for n in needles:
        assert n in lines[-1], (n, lines[-1])
    return lines[-1]


def copy_run(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for f in src.iterdir():
        if f.is_file():
            (dst / f.name).write_bytes(f.read_bytes())
    return dst


@pytest.fixture(scope="module")
def sec(tmp_path_factory):
    """A plugin with a tiny case and suite, its data, and MeshODENet smoke runs trained for 2
    epochs (``two``) and for 3 epochs in one go (``three``)."""
    from benchmarks.suite import plugins, registry, suites

    root = tmp_path_factory.mktemp("security")
    plugin = root / "plugin.py"
    plugin.write_text(PLUGIN)
    pl, data = ["--plugin", str(plugin)], root / "data"
    assert main(pl + ["generate", TINY, "--data-dir", str(data), "--no-progress",
                      "--workers", "1"]) == 0
    for name, epochs in (("two", 2), ("three", 3)):
        assert main(pl + ["train", "--case", TINY, "--preset", "smoke", "--out",
                          str(root / name), "--data-dir", str(data), "--epochs", str(epochs),
                          "--no-progress", "--device", "cpu"]) == 0
    yield SimpleNamespace(pl=pl, data=data, two=root / "two", three=root / "three")
    registry.CASES.pop(TINY, None)
    suites.SUITES.pop(SUITE, None)
    plugins._loaded.discard(str(plugin.resolve()))


# --- genuine checkpoints ---------------------------------------------------------------------
def test_checkpoints_hold_only_tensors_and_plain_containers(sec):
    for f in ("best.pt", "last.pt"):
        ck = torch.load(sec.three / f, weights_only=True)
        assert ck["epoch"] == 3 and ck["model_info"]["name"] == "meshodenet"
        assert ck["generator"].dtype == torch.uint8 and ck["torch_rng"].dtype == torch.uint8


def test_resume_and_rollout_of_safe_checkpoints_are_bit_identical(sec, tmp_path, capsys):
    """2 epochs, then ``--resume`` to 3, equals 3 epochs in one go: weight for weight,
    optimizer and RNG states, history, and the rolled-out trajectories."""
    from meshodenet.training.train import load_checkpoint

    r = copy_run(sec.two, tmp_path / "resumed")
    assert main(sec.pl + ["train", "--case", TINY, "--preset", "smoke", "--out", str(r),
                          "--data-dir", str(sec.data), "--epochs", "3", "--resume",
                          "--no-progress", "--device", "cpu"]) == 0
    a, b = load_checkpoint(sec.three / "last.pt"), load_checkpoint(r / "last.pt")
    assert a["model"].keys() == b["model"].keys()
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    for k, sa in a["optimizer"]["state"].items():
        for name, v in sa.items():
            assert torch.equal(v, b["optimizer"]["state"][k][name]), (k, name)
    assert a["scheduler"] == b["scheduler"]
    assert torch.equal(a["generator"], b["generator"])
    assert torch.equal(a["torch_rng"], b["torch_rng"])
    keep = ("epoch", "train_loss", "val_rmse", "best_val_rmse", "lr")
    assert [{k: h[k] for k in keep} for h in a["history"]] == \
        [{k: h[k] for k in keep} for h in b["history"]]
    preds = []
    for run in (sec.three, r):
        out = tmp_path / f"{run.name}.npz"
        assert main(["rollout", "--run", str(run), "--checkpoint", "last", "--split", "test",
                     "--data-dir", str(sec.data), "--out", str(out), "--device", "cpu"]) == 0
        preds.append(store.load_npz(out)["pos"])
    capsys.readouterr()
    assert np.array_equal(preds[0], preds[1])


def test_save_checkpoint_refuses_objects_that_would_not_load_safely(tmp_path):
    from meshodenet.training.train import load_checkpoint, plain, save_checkpoint

    with pytest.raises(TypeError, match=r"\['extra'\]\['cfg'\].*cannot be stored"):
        plain({"extra": {"cfg": SimpleNamespace(a=1)}})
    x = {"loss": np.float64(0.1), "n": np.int64(3), "ok": np.bool_(True), "t": (1, [2.5])}
    y = plain(x)
    assert y == {"loss": 0.1, "n": 3, "ok": True, "t": (1, [2.5])}
    assert [type(v) for v in y.values()] == [float, int, bool, tuple]
    ck = {k: 0 for k in ("model", "optimizer", "scheduler", "generator", "torch_rng", "epoch",
                         "best_val_rmse", "best_epoch", "history", "model_info")}
    save_checkpoint(tmp_path / "c.pt", {**ck, "extra": x})
    assert load_checkpoint(tmp_path / "c.pt")["extra"] == y


# --- crafted checkpoints ---------------------------------------------------------------------
@pytest.mark.parametrize("how,says", [
    ("torch", "refused: it holds objects other than tensors"),
    ("pickle2", "refused: it holds objects other than tensors"),
    ("pickle5", "not a readable checkpoint")])
def test_crafted_best_checkpoint_under_rollout_runs_nothing(sec, tmp_path, capsys, how, says):
    r = copy_run(sec.two, tmp_path / "received")
    sentinel = tmp_path / "SENTINEL"
    write_crafted(r / "best.pt", sentinel, how)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch warns about plain pickle's protocol
        rc = main(["rollout", "--run", str(r), "--split", "test", "--data-dir", str(sec.data),
                   "--out", str(tmp_path / "p.npz"), "--device", "cpu"])
    assert rc == 2
    last = one_line_error(capsys.readouterr().err, str(r / "best.pt"), says)
    if "refused" in says:
        assert f"meshbench convert-checkpoint {r / 'best.pt'} --i-trust-this-file" in last
    assert not sentinel.exists()
    assert not (tmp_path / "p.npz").exists()


def test_crafted_last_checkpoint_under_resume_runs_nothing(sec, tmp_path, capsys):
    r = copy_run(sec.two, tmp_path / "received")
    sentinel = tmp_path / "SENTINEL"
    write_crafted(r / "last.pt", sentinel)
    crafted, sessions = (r / "last.pt").read_bytes(), (r / "sessions.json").read_bytes()
    rc = main(sec.pl + ["train", "--case", TINY, "--preset", "smoke", "--out", str(r),
                        "--data-dir", str(sec.data), "--epochs", "3", "--resume",
                        "--no-progress", "--device", "cpu"])
    assert rc == 2
    one_line_error(capsys.readouterr().err, "--resume", "last.pt", "refused",
                   "convert-checkpoint")
    assert not sentinel.exists()
    assert (r / "last.pt").read_bytes() == crafted  # kept for the user, not retrained over
    assert (r / "sessions.json").read_bytes() == sessions


def test_crafted_last_checkpoint_in_a_suite_run_runs_nothing(sec, tmp_path, capsys):
    """The runner would resume a run whose stored configuration matches: it refuses the
    crafted ``last.pt`` (in its worker process) and keeps it."""
    from benchmarks.suite.runs import resolve_run

    runs = tmp_path / "runs"
    run = runs / f"{TINY}-mgn-smoke-s0"
    run.mkdir(parents=True)
    config = resolve_run(TINY, "mgn", "smoke", data_dir=sec.data)["config"]
    store.save_json(run / "config.json", config)
    sentinel = tmp_path / "SENTINEL"
    write_crafted(run / "last.pt", sentinel)
    crafted = (run / "last.pt").read_bytes()
    rc = main(sec.pl + ["run", "--suite", SUITE, "--runs-dir", str(runs), "--results",
                        str(tmp_path / "res"), "--data-dir", str(sec.data), "--no-progress",
                        "--no-figures"])
    assert rc == 2
    one_line_error(capsys.readouterr().err, "last.pt", "refused", "convert-checkpoint")
    assert not sentinel.exists()
    assert (run / "last.pt").read_bytes() == crafted
    assert not (tmp_path / "res" / SUITE).exists()


# --- converting a trusted old-format checkpoint ----------------------------------------------
def test_convert_checkpoint_only_on_request(sec, tmp_path, capsys):
    """An old-format checkpoint (numpy numbers, a dataclass) is refused; ``convert-checkpoint``
    without ``--i-trust-this-file`` only reports it; with the flag it is rewritten once and
    then loads safely with the same tensors and values."""
    from meshodenet.training.train import TrainConfig, UnsafeCheckpointError, load_checkpoint

    r = copy_run(sec.two, tmp_path / "old")
    ck = torch.load(r / "last.pt", weights_only=True)
    loss = ck["history"][0]["train_loss"]
    ck["history"][0]["train_loss"] = np.float64(loss)
    ck["extra"] = {"train": TrainConfig(epochs=2), "dir": Path("runs/x")}
    torch.save(ck, r / "last.pt")
    old = (r / "last.pt").read_bytes()
    with pytest.raises(UnsafeCheckpointError, match="convert-checkpoint"):
        load_checkpoint(r / "last.pt")

    assert main(["convert-checkpoint", str(r)]) == 2
    captured = capsys.readouterr()
    assert "best.pt: already in the safe format" in captured.out
    one_line_error(captured.err, "last.pt", "--i-trust-this-file")
    assert (r / "last.pt").read_bytes() == old

    assert main(["convert-checkpoint", str(r / "last.pt"), "--i-trust-this-file"]) == 0
    assert "last.pt: converted" in capsys.readouterr().out
    new = load_checkpoint(r / "last.pt")
    assert type(new["history"][0]["train_loss"]) is float and \
        new["history"][0]["train_loss"] == loss
    assert new["extra"] == {"train": dataclasses.asdict(TrainConfig(epochs=2)), "dir": "runs/x"}
    for k, v in ck["model"].items():
        assert torch.equal(new["model"][k], v), k
    again = (r / "last.pt").read_bytes()
    assert main(["convert-checkpoint", str(r / "last.pt"), "--i-trust-this-file"]) == 0
    assert "unchanged" in capsys.readouterr().out and (r / "last.pt").read_bytes() == again


def test_convert_checkpoint_without_the_flag_runs_nothing(tmp_path, capsys):
    sentinel = tmp_path / "SENTINEL"
    write_crafted(tmp_path / "best.pt", sentinel)
    assert main(["convert-checkpoint", str(tmp_path / "best.pt")]) == 2
    one_line_error(capsys.readouterr().err, "best.pt", "--i-trust-this-file")
    assert not sentinel.exists()
    assert main(["convert-checkpoint", str(tmp_path / "nothing.pt")]) == 2
    one_line_error(capsys.readouterr().err, "nothing.pt", "no such file")


# --- ids that become paths -------------------------------------------------------------------
BAD_IDS = ["../evil", "a/../../b", "..", ".hidden", "a/b", "a\\b", "", "a b"]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_ids_with_path_parts_are_refused(bad, tmp_path):
    from benchmarks.suite.generate import generate
    from benchmarks.suite.registry import CASES, register_case
    from benchmarks.suite.suites import RunSpec, Suite

    with pytest.raises(ValueError, match="RunSpec.case"):
        RunSpec(bad, "mgn")
    with pytest.raises(ValueError, match="RunSpec.preset"):
        RunSpec("rod_falling", "mgn", bad)
    with pytest.raises(ValueError, match="RunSpec.tag"):
        RunSpec("rod_falling", "mgn", tag=bad or ".")
    with pytest.raises(ValueError, match="RunSpec.integrator"):
        RunSpec("rod_falling", "meshodenet", integrator=bad or ".")
    with pytest.raises(ValueError, match="Suite.name"):
        Suite(bad, "x", ())
    with pytest.raises(ValueError, match="case id"):
        register_case(SimpleNamespace(id=bad))
    with pytest.raises(ValueError, match="case id"):
        generate(SimpleNamespace(id=bad), tmp_path, progress=False)
    assert bad not in CASES and not list(tmp_path.iterdir())


def test_good_ids_are_accepted():
    from benchmarks.suite.registry import safe_id
    from benchmarks.suite.suites import RunSpec

    for ok in ("rod_falling", "a.b-c_1", "X9"):
        assert safe_id(ok, "id") == ok
    assert RunSpec("rod_falling", "mgn", "smoke", tag="lr.2e-3").run_id == \
        "rod_falling-mgn-smoke-lr.2e-3-s0"


def test_cli_refuses_ids_with_path_parts(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--case", "../evil", "--out", str(out)]) == 2
    one_line_error(capsys.readouterr().err, "unknown case id '../evil'")
    assert main(["run", "--suite", "../evil", "--runs-dir", str(tmp_path / "runs")]) == 2
    one_line_error(capsys.readouterr().err, "unknown suite id '../evil'")
    for code, field in (
            ("from benchmarks.suite.suites import Suite, register_suite\n"
             "register_suite(Suite('../../evil', 'x', ()))\n", "Suite.name"),
            ("from types import SimpleNamespace\nfrom benchmarks.suite.registry import register_case\n"
             "register_case(SimpleNamespace(id='../evil'))\n", "case id")):
        plugin = tmp_path / f"p{len(field)}.py"
        plugin.write_text(code)
        assert main(["--plugin", str(plugin), "run", "--suite", "smoke"]) == 2
        one_line_error(capsys.readouterr().err, field, "'../")
    assert not (tmp_path / "runs").exists()
    assert not list(tmp_path.parent.glob("*evil*")) and not list(tmp_path.rglob("*evil*"))


def test_a_received_metrics_file_cannot_name_files_outside(tmp_path):
    from benchmarks.suite.runner import METRICS_FILE, _run_metrics

    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / METRICS_FILE).write_text("run,case,step,rmse\nr,../../evil,0,0.1\n")
    with pytest.raises(ValueError, match="column 'case' is not 'rod'"):
        _run_metrics(tmp_path / "runs", {"run": "r", "case": "rod"})
