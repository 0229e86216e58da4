"""The A/B harness (``benchmarks.ab``, docs/AB.md): the conversion to the authors' layout,
the loss in their units and its relation to our RMSE, resuming a run exactly, the merged table,
and the bad-input errors. The authors' code itself is needed only by the last test, skipped
unless ``MESHBENCH_AUTHORS_REPO`` names a checkout of it."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pandas as pd
import pytest
import torch

from benchmarks.ab import core
from benchmarks.ab.__main__ import main
from benchmarks.ab.convert import authors_stats, authors_velocity, convert, mesh_edges
from tests.conftest import rod_arrays, strip_arrays


def _rows(path):
    df = pd.read_csv(path / core.CSV_FILE)
    return df.drop(columns=list(core.TIMING_COLUMNS))


# --- conversion --------------------------------------------------------------------------------
def test_velocity_rule():
    pos = torch.tensor(np.random.default_rng(0).normal(size=(5, 4, 3)), dtype=torch.float32)
    v = authors_velocity(pos)
    assert torch.equal(v[0], torch.zeros(4, 3))  # frame 0's previous frame is itself
    torch.testing.assert_close(v[1:], (pos[1:] - pos[:-1]) / 0.1)


@pytest.mark.parametrize("make", [strip_arrays, rod_arrays])
def test_convert_layout(make):
    a = make()
    trajs = convert(a)
    B, T, N, _ = a["pos"].shape
    assert len(trajs) == B
    edges = mesh_edges(a)
    if len(a["cells"]):  # the triangles' sides
        tri = {tuple(sorted(e)) for c in a["cells"] for e in ((c[0], c[1]), (c[1], c[2]), (c[2], c[0]))}
        assert {tuple(e) for e in edges} == tri
    else:  # the rod's segments
        assert {tuple(e) for e in edges} == {tuple(sorted(e)) for e in a["edges"]}
    for b, tr in enumerate(trajs):
        assert all(len(v) == T for v in tr.values())  # a leading frame axis everywhere
        ei = tr["edge_index"][0]
        pairs = set(map(tuple, ei.t().tolist()))
        assert ei.shape[1] == 2 * len(edges) and all((j, i) in pairs for i, j in pairs)
        nt = torch.as_tensor(a["node_type"])
        assert torch.equal(tr["one_hot_node_type"][0], torch.nn.functional.one_hot(nt, 2).float())
        assert torch.equal(tr["node_type"][0, :, 0], nt.float())
        torch.testing.assert_close(tr["youngs"][0], torch.full((N, 1), a["youngs"][b] / 1e6,
                                                               dtype=torch.float32))
        m = tr["mesh_edge_attr"][0]
        torch.testing.assert_close(m[:, 3], m[:, :3].norm(dim=1))
        rest = torch.as_tensor(a["rest_pos"], dtype=torch.float32)
        torch.testing.assert_close(m[:, :3], rest[ei[0]] - rest[ei[1]])
        torch.testing.assert_close(tr["velocity"], authors_velocity(tr["world_pos"]))


def test_stats_over_every_frame():
    trajs = convert(strip_arrays(B=3, T=5))
    s = authors_stats(trajs)
    vel = torch.cat([t["velocity"].reshape(-1, 3) for t in trajs])
    torch.testing.assert_close(s["vel_mean"], vel.mean(0))
    torch.testing.assert_close(s["vel_std"], vel.std(0).clamp_min(1e-8))
    assert s["node_size"].item() == 3 and s["edge_size"].item() == 8


# --- units -------------------------------------------------------------------------------------
def test_authors_loss_by_hand_and_rmse():
    from meshodenet.metrics import rmse

    rng = np.random.default_rng(1)
    true = torch.tensor(rng.normal(size=(2, 4, 5, 3)))
    pred = true + torch.tensor(rng.normal(scale=0.1, size=true.shape))
    e = (pred - true).numpy()
    for b in range(2):  # sqrt(mean over frames, coords of sum over nodes of err^2)
        hand = math.sqrt(sum((e[b, k, :, c] ** 2).sum() for k in range(4) for c in range(3)) / 12)
        assert core.authors_loss(pred, true)[b].item() == pytest.approx(hand, rel=1e-12)
        # loss * sqrt(3 / N) = Euclidean RMSE over all frames (frame 0 included) and nodes
        assert core.authors_loss(pred, true)[b].item() * math.sqrt(3 / 5) == pytest.approx(
            float(rmse(pred[b], true[b])), rel=1e-12)
    m = core.test_metrics(pred, true)
    assert m["test_loss"] == pytest.approx(float(core.authors_loss(pred, true).mean()))
    assert m["test_rmse_coord_m"] == pytest.approx(m["test_rmse_m"] / math.sqrt(3))


# --- runs --------------------------------------------------------------------------------------
def _train(tiny_case, out, code="ours", epochs=2, *extra):
    case, root = tiny_case
    return main(["train", "--case", case.id, "--code", code, "--out", str(out), "--data-dir",
                 str(root), "--epochs", str(epochs), "--no-progress", *extra])


def test_ours_resume_is_exact(tiny_case, tmp_path):
    assert _train(tiny_case, tmp_path / "a", "ours", 1) == 0
    assert _train(tiny_case, tmp_path / "a", "ours", 2) == 0  # resumes after epoch 1
    assert _train(tiny_case, tmp_path / "b", "ours", 2) == 0  # uninterrupted
    a, b = _rows(tmp_path / "a"), _rows(tmp_path / "b")
    pd.testing.assert_frame_equal(a, b)
    assert list(b["epoch"]) == [0, 1, 2, 0] and list(b["code"]) == ["ours"] * 3 + ["standing_still"]
    sessions = json.loads((tmp_path / "a" / core.SESSIONS_FILE).read_text())
    assert [(s["first_epoch"], s["device"]) for s in sessions] == [(0, "cpu"), (1, "cpu")]
    assert "torch" in sessions[0]["versions"] and sessions[0]["git_sha"]
    assert b["test_loss"].notna().all() and b["train_loss"].iloc[1:3].notna().all()
    # killed after last.pt but before its row: the next session recomputes the row
    csv = (tmp_path / "b" / core.CSV_FILE).read_text().splitlines()
    (tmp_path / "b" / core.CSV_FILE).write_text("\n".join(csv[:3] + csv[4:]) + "\n")
    assert _train(tiny_case, tmp_path / "b", "ours", 2) == 0
    pd.testing.assert_frame_equal(_rows(tmp_path / "b"), a)
    # another configuration in the same directory is refused
    assert _train(tiny_case, tmp_path / "b", "ours", 2, "--seed", "7") == 2


def test_ours_goes_on_on_another_device(tiny_plate, tmp_path, monkeypatch):
    """A run begun on the CPU goes on on a CUDA device (emulated: ``tests/fakecuda.py``, which
    fails where a real GPU refuses to mix devices), the plate's ``paper`` preset with the
    authors' normaliser; ``sessions.json`` says which device ran which epochs."""
    from tests.fakecuda import FakeCuda

    case, root = tiny_plate
    out = tmp_path / "r"
    argv = ["train", "--case", case.id, "--code", "ours", "--out", str(out), "--data-dir",
            str(root), "--no-progress"]
    assert main([*argv, "--epochs", "1"]) == 0
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with FakeCuda() as mode:
        assert main([*argv, "--epochs", "2", "--device", "cuda"]) == 0
    assert mode.ops > 100
    rows = _rows(out)
    assert list(rows["epoch"]) == [0, 1, 2, 0] and rows["test_loss"].notna().all()
    sessions = json.loads((out / core.SESSIONS_FILE).read_text())
    assert [(s["first_epoch"], s["device"]) for s in sessions] == [(0, "cpu"), (1, "cuda")]
    assert json.loads((out / core.CONFIG_FILE).read_text())["extra"]["model"]["normalizer"] == (
        "authors")


def test_a_run_stored_before_a_field_existed_resumes_at_its_default(tiny_case, tmp_path, capsys):
    """A run whose ``ab_config.json`` predates model fields (the convention fields were added
    after the first A/B runs) was trained with their defaults: it resumes where the settings
    resolve to them, and is refused where they do not."""
    out = tmp_path / "old"
    assert _train(tiny_case, out, "ours", 1) == 0
    cfg = json.loads((out / core.CONFIG_FILE).read_text())
    for field in ("acc_scale", "loss", "layout"):  # the rod's paper preset keeps the defaults
        del cfg["extra"]["model"][field]
    del cfg["extra"]["train"]["budgets_s"]  # a tuple default: stored as a list
    (out / core.CONFIG_FILE).write_text(json.dumps(cfg))
    assert _train(tiny_case, out, "ours", 1, "--set", "model.acc_scale=velocity") == 2
    err = capsys.readouterr().err  # names the field that differs, not a whole section
    assert "extra.model.acc_scale: 'acceleration' -> 'velocity'" in err
    assert _train(tiny_case, out, "ours", 2) == 0
    assert list(_rows(out)["epoch"]) == [0, 1, 2, 0]


def test_merge_table_and_figure(tiny_case, tmp_path):
    assert _train(tiny_case, tmp_path / "ours", "ours", 1) == 0
    auth = tmp_path / "authors"  # an authors' run directory, written by hand
    auth.mkdir()
    cfg = json.loads((tmp_path / "ours" / core.CONFIG_FILE).read_text())
    (auth / core.CONFIG_FILE).write_text(json.dumps({**cfg, "code": "authors"}))
    rows = core.read_csv(tmp_path / "ours")
    for r in rows:
        r["code"] = "authors" if r["code"] == "ours" else r["code"]
    core.write_csv(auth, rows)
    case, _ = tiny_case
    res = tmp_path / "res"
    assert main(["merge", "--case", case.id, "--authors", str(auth), "--ours",
                 str(tmp_path / "ours"), "--results", str(res), "--name", "tiny"]) == 0
    df = pd.read_csv(res / "tiny_ab.csv")  # bare read_csv
    assert list(df.columns) == list(core.COLUMNS)
    assert sorted(set(df["code"])) == ["authors", "ours (paper preset)", "standing_still"]
    assert (res / "figures" / "tiny_ab.png").stat().st_size > 0
    # a bisection step: ours with --set settings, labelled by them; the same one twice refused
    assert _train(tiny_case, tmp_path / "v", "ours", 1, "--set", "model.loss=rms") == 0
    # resumed with settings given another way that resolve to the same: the same run
    assert _train(tiny_case, tmp_path / "v", "ours", 2, "--set", "model.engine=fast",
                  "--set", "model.loss=rms") == 0
    argv = ["merge", "--case", case.id, "--authors", str(auth), "--ours", str(tmp_path / "ours"),
            "--results", str(res), "--name", "tiny", "--variant", str(tmp_path / "v")]
    assert main(argv) == 0
    df = pd.read_csv(res / "tiny_ab.csv")
    assert sorted(set(df["code"])) == ["authors", "ours (paper preset)", "ours, their loss",
                                       "standing_still"]
    v = df[df["code"] == "ours, their loss"]
    assert list(v["epoch"]) == [0, 1, 2] and v["test_loss"].notna().all()
    assert not np.allclose(v["train_loss"].iloc[1],
                           df[df["code"] == "ours (paper preset)"]["train_loss"].iloc[1])
    assert main(argv + ["--variant", str(tmp_path / "v")]) == 2


def test_variant_code_reads_the_resolved_settings():
    """A run's code says how its stored settings differ from the case's ``paper`` preset as it
    is now: the preset reads plainly on either mesh kind, a variant by what it changes (the
    plate's runs of before the preset took the authors' conventions and normaliser), whatever
    ``--set`` list gave the settings; a field a run predates counts as its default."""
    import dataclasses

    from benchmarks.ab.merge import PAPER_PRESET, variant_code
    from meshodenet.gnn.meshodenet import MeshODENetConfig, meshodenet_presets

    def cfg(kind, overrides=(), **fields):
        model = dataclasses.replace(meshodenet_presets("paper", kind)[1], **fields)
        return {"extra": {"model": json.loads(json.dumps(dataclasses.asdict(model))),
                          "overrides": list(overrides)}}

    assert PAPER_PRESET == "ours (paper preset)"
    assert variant_code(cfg("line"), "line") == PAPER_PRESET
    assert variant_code(cfg("triangle"), "triangle") == PAPER_PRESET
    assert variant_code({**cfg("line"), "seed": 42}, "line") == PAPER_PRESET
    assert variant_code({**cfg("triangle"), "seed": 43}, "triangle") == f"{PAPER_PRESET}, seed 43"
    assert variant_code(cfg("triangle", ["model.loss=rms", "train.lr=0.001"]),
                        "triangle") == "ours, lr=0.001"
    old = {"extra": {"model": {"hidden": 128}, "overrides": []}}  # stored before the switches
    assert variant_code(old, "line") == PAPER_PRESET
    assert variant_code(old, "triangle") == "ours, our conventions and normaliser"
    assert variant_code(cfg("triangle", normalizer="ours"), "triangle") == "ours, our normaliser"
    assert variant_code(cfg("triangle", layout="authors_nodes", normalizer="ours"),
                        "triangle") == "ours, our edge features and normaliser"
    assert variant_code(cfg("triangle", loss="mse", layout="ours", normalizer="ours"),
                        "triangle") == "ours, our loss, features and normaliser"
    assert variant_code(cfg("line", acc_scale="velocity", normalizer="authors", hidden=64),
                        "line") == "ours, their output scale and normaliser, hidden=64"
    assert variant_code(cfg("triangle", acc_scale="acceleration", loss="mse", normalizer="ours"),
                        "triangle") == "ours, our output scale, loss and normaliser"
    assert MeshODENetConfig().normalizer == "ours"  # the defaults are our conventions


def test_published_log_excerpt():
    from benchmarks.ab.merge import published_rows

    rows = {r["epoch"]: r["test_loss"] for r in published_rows("plate_cantilever")}
    assert rows[1] == pytest.approx(0.384, abs=5e-4) and rows[199] == pytest.approx(0.015, abs=5e-4)
    assert min(rows.values()) == pytest.approx(0.00997, abs=5e-6)


@pytest.mark.parametrize("repo", ["missing", "empty"])
def test_bad_checkout_exits_2(tmp_path, capsys, repo):
    path = tmp_path / repo
    if repo == "empty":
        path.mkdir()
    code = main(["train", "--case", "plate_cantilever", "--code", "authors", "--authors-repo",
                 str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and str(path) in err and len(err.strip().splitlines()) == 1
    assert ("no such directory" if repo == "missing" else "Train.py") in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, word", [(["--code", "theirs"], "--code"),
                                        (["--code", "ours", "--epochs", "0"], "--epochs"),
                                        (["--code", "authors"], "--authors-repo"),
                                        (["--code", "ours", "--case", "nope"], "nope"),
                                        (["--code", "ours", "--device", "tpu"], "--device"),
                                        (["--code", "authors", "--device", "cuda"], "--device")]
                         + ([] if torch.cuda.is_available() else
                            [(["--code", "ours", "--device", "cuda"], "no CUDA device")]))
def test_bad_arguments_exit_2(tmp_path, capsys, args, word):
    argv = ["train", "--case", "plate_cantilever", "--out", str(tmp_path / "o"), *args]
    assert main(argv) == 2
    assert word in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(not os.environ.get("MESHBENCH_AUTHORS_REPO"),
                    reason="set MESHBENCH_AUTHORS_REPO to a checkout of leixinma/MeshODENet")
def test_authors_resume_is_exact(tiny_case, tmp_path):
    repo = ["--authors-repo", os.environ["MESHBENCH_AUTHORS_REPO"]]
    assert _train(tiny_case, tmp_path / "a", "authors", 1, *repo) == 0
    assert _train(tiny_case, tmp_path / "a", "authors", 2, *repo) == 0
    assert _train(tiny_case, tmp_path / "b", "authors", 2, *repo) == 0
    pd.testing.assert_frame_equal(_rows(tmp_path / "a"), _rows(tmp_path / "b"))


# --- equiv: the same weights in both codes ------------------------------------------------------
def _fake_checkout(path):
    from benchmarks.ab.authors import REQUIRED

    for f in REQUIRED:
        (path / f).parent.mkdir(parents=True, exist_ok=True)
        (path / f).write_text("raise SystemExit('their code must not run in this test')\n")
    return path


@pytest.mark.parametrize("extra, word", [(["--set", "model.layout=ours"], "model.layout"),
                                         (["--trajectory", "7"], "--trajectory"),
                                         (["--steps", "-1"], "--steps"),
                                         (["--set", "model.loss=mse"], "model.loss")])
def test_equiv_bad_input_exits_2_before_their_code_runs(tiny_plate, tmp_path, capsys, extra, word):
    case, root = tiny_plate
    repo = _fake_checkout(tmp_path / "repo")
    argv = ["equiv", "--case", case.id, "--data-dir", str(root), "--authors-repo", str(repo),
            *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert word in err and len(err.strip().splitlines()) == 1


def test_equiv_needs_a_triangle_mesh(tiny_case, tmp_path, capsys):
    case, root = tiny_case
    repo = _fake_checkout(tmp_path / "repo")
    assert main(["equiv", "--case", case.id, "--data-dir", str(root), "--authors-repo",
                 str(repo)]) == 2
    assert "triangle" in capsys.readouterr().err


@pytest.mark.skipif(not os.environ.get("MESHBENCH_AUTHORS_REPO"),
                    reason="set MESHBENCH_AUTHORS_REPO to a checkout of leixinma/MeshODENet")
def test_equiv_with_their_normaliser_is_their_code(tiny_plate, tmp_path):
    """Their weights in our model: with ``normalizer="authors"`` the field, the loss, every
    gradient and two optimizer steps agree to float32 round-off; with ours the gradients do not
    (their live out-of-plane direction, docs/AB.md)."""
    from benchmarks.ab import equiv

    case, root = tiny_plate
    repo = os.environ["MESHBENCH_AUTHORS_REPO"]
    rows = {}
    for n in ("authors", "ours"):
        rows[n] = pd.DataFrame(equiv.run(case.id, repo, root, [f"model.normalizer={n}"],
                                         steps=2, out=tmp_path / f"{n}.csv", echo=lambda s: None))
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / f"{n}.csv")[["what", "step"]],
                                      rows[n][["what", "step"]])
    a, o = rows["authors"], rows["ours"]
    assert a.rel_diff.max() < 1e-4
    grad = lambda df: df[df.what == "gradient"].rel_diff.max()
    assert grad(o) > 100 * grad(a)
