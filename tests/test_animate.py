"""``meshbench animate``: the GIF of a run's rollout over the ground truth (frames, size,
determinism), the reuse of a suite's stored test rollout, and bad input (exit 2)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from benchmarks.cli import main

pytest.importorskip("torch")
Image = pytest.importorskip("PIL.Image")


@pytest.fixture(scope="module")
def run(tiny_case, tmp_path_factory):
    """``(case, data_root, run_dir)``: a one-epoch smoke run on the tiny rod case."""
    case, root = tiny_case
    run_dir = tmp_path_factory.mktemp("animate") / "run"
    assert main(["train", "--case", case.id, "--preset", "smoke", "--out", str(run_dir),
                 "--data-dir", str(root), "--threads", "1", "--no-progress",
                 "--epochs", "1"]) == 0
    return case, root, run_dir


def _animate(run_dir, root, out, *extra):
    return main(["animate", str(run_dir), "--data-dir", str(root), "--device", "cpu",
                 "--out", str(out), *map(str, extra)])


def _frames(path) -> list:
    with Image.open(path) as im:
        out = []
        for k in range(im.n_frames):
            im.seek(k)
            out.append(im.convert("RGB"))
        return out


def test_animate_writes_a_deterministic_gif(run, tmp_path, capsys):
    from benchmarks.suite import animate
    from groundtruth import store

    case, root, run_dir = run
    T = store.load_split(case, "test", root)["pos"].shape[1]
    gif = tmp_path / "a.gif"
    assert _animate(run_dir, root, gif, "--split", "test", "--index", 1) == 0
    assert f"wrote {gif}" in capsys.readouterr().out
    frames = _frames(gif)
    assert len(frames) == min(T, animate.MAX_FRAMES)
    assert frames[0].size[0] == round(animate.WIDTH * animate.DPI)
    assert 100 < frames[0].size[1] < 1.2 * frames[0].size[0]
    assert frames[0].tobytes() != frames[-1].tobytes()
    again = tmp_path / "b.gif"
    assert _animate(run_dir, root, again, "--index", 1) == 0
    assert again.read_bytes() == gif.read_bytes()
    assert _animate(run_dir, root, tmp_path / "c.gif", "--frames", 4) == 0
    assert len(_frames(tmp_path / "c.gif")) == 4
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("extra, words", [
    (("--index", 7), ["--index", "7", "[0, 1]"]),
    (("--index", -1), ["--index", "-1"]),
    (("--split", "val"), ["--split", "'val'", "train, test"]),
    (("--frames", 1), ["--frames", "1"]),
    (("--checkpoint", "first"), ["--checkpoint", "'first'"]),
])
def test_bad_input_is_one_line_and_exit_2(run, tmp_path, capsys, extra, words):
    _, root, run_dir = run
    assert _animate(run_dir, root, tmp_path / "x.gif", *extra) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert all(w in err for w in words), err
    assert not (tmp_path / "x.gif").exists()


def test_bad_run_and_out_are_clear(run, tmp_path, capsys):
    _, root, run_dir = run
    assert _animate(tmp_path, root, tmp_path / "x.gif") == 2
    err = capsys.readouterr().err
    assert "RUN" in err and str(tmp_path) in err and "config.json" in err
    assert _animate(run_dir, root, tmp_path / "x.png") == 2
    assert "--out must end in .gif" in capsys.readouterr().err


def test_the_suite_s_stored_test_rollout_is_reused(run, tmp_path):
    """A run of ``meshbench run`` holds its test rollout; animate draws it, not a new one."""
    import shutil

    from benchmarks.commands.animate import _predict
    from benchmarks.suite.runs import PRED_FILE
    from groundtruth import store

    case, root, run_dir = run
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    true = store.load_split(case, "test", root)
    stored = {**true, "pos": true["pos"] + 1.0}
    store.save_npz(copy / PRED_FILE, stored)
    args = argparse.Namespace(index=1, split="test", checkpoint="best", data_dir=str(root),
                              device="cpu")
    np.testing.assert_array_equal(_predict(copy, args, true), stored["pos"][1])
    rolled = _predict(copy, argparse.Namespace(**{**vars(args), "checkpoint": "last"}), true)
    assert rolled.shape == true["pos"][1].shape and not np.array_equal(rolled, stored["pos"][1])


def test_frame_steps_and_units():
    from benchmarks.suite.animate import M_PREFIXES, PA_PREFIXES, frame_steps, si

    k = frame_steps(501, 60)
    assert len(k) == 60 and k[0] == 0 and k[-1] == 500 and (np.diff(k) > 0).all()
    assert list(frame_steps(5, 60)) == [0, 1, 2, 3, 4]
    assert si(5.3e8, "Pa", PA_PREFIXES) == "0.53 GPa"
    assert si(5.0e6, "Pa", PA_PREFIXES) == "5 MPa"
    assert si(1.23e-3, "m", M_PREFIXES) == "1.23 mm"
    assert si(0.5, "m", M_PREFIXES) == "0.5 m"
