"""Every committed result names its code: ``store.git_sha`` carries a hash of the uncommitted
diff (``SHA-dirty-HASH``), and the commands that write results refuse to write where git would
commit them from a modified checkout unless ``--allow-dirty`` (``benchmarks.suite.provenance``,
docs/SUITE.md, "Reproducing a row from its sha")."""

from __future__ import annotations

import hashlib
import re
import subprocess

import pytest

from benchmarks.cli import main
from benchmarks.suite import provenance
from groundtruth import store


def git(repo, *args) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@example.org",
                           "-c", "commit.gpgsign=false", *args], cwd=repo, check=True,
                          capture_output=True, text=True).stdout


@pytest.fixture
def repo(tmp_path):
    """A one-commit checkout: a tracked file, a committed results/ and an ignored build/."""
    r = tmp_path / "repo"
    r.mkdir()
    git(r, "init", "-q")
    (r / "code.py").write_text("x = 1\n")
    (r / ".gitignore").write_text("/build/\n")
    (r / "results").mkdir()
    (r / "results" / "table.csv").write_text("a\n1\n")
    git(r, "add", ".")
    git(r, "commit", "-q", "-m", "first")
    return r


def test_git_sha_names_the_diff(repo, tmp_path):
    head = git(repo, "rev-parse", "HEAD").strip()
    assert store.git_sha(repo) == head and store.git_state(repo) == (head, [])
    (repo / "new.py").write_text("untracked\n")  # untracked files do not count
    assert store.git_sha(repo) == head
    (repo / "code.py").write_text("x = 2\n")
    sha = store.git_sha(repo)
    diff = subprocess.run(["git", "diff", "--binary", "HEAD"], cwd=repo, capture_output=True,
                          check=True).stdout
    assert sha == f"{head}-dirty-{hashlib.sha256(diff).hexdigest()[:12]}"
    assert re.fullmatch(r"[0-9a-f]{40}-dirty-[0-9a-f]{12}", sha)
    assert store.git_state(repo) == (head, ["code.py"])
    (repo / "code.py").write_text("x = 3\n")
    other = store.git_sha(repo)
    assert other != sha and other.startswith(f"{head}-dirty-")
    git(repo, "add", "code.py")  # staged changes are in the diff too
    assert store.git_sha(repo) == other
    (repo / "code.py").write_text("x = 2\n")
    assert store.git_sha(repo) == sha  # the same diff, the same name
    plain = tmp_path / "plain"
    plain.mkdir()
    assert store.git_sha(plain) == "unknown" and store.git_state(plain) is None


def test_git_sha_leaves_out_a_commands_own_outputs(repo):
    """Committed files under ``exclude`` (a command's own output directory, rewritten by it or
    by an earlier run into it) neither make the tree dirty nor enter the diff's hash."""
    head = git(repo, "rev-parse", "HEAD").strip()
    (repo / "results" / "table.csv").write_text("a\n2\n")
    assert store.git_sha(repo).startswith(f"{head}-dirty-")
    assert store.git_sha(repo, exclude=[repo / "results"]) == head
    assert store.git_state(repo, exclude=[repo / "results"]) == (head, [])
    (repo / "code.py").write_text("x = 2\n")  # a change of the code still counts, alone
    code_only = store.git_sha(repo, exclude=[repo / "results"])
    (repo / "results" / "table.csv").write_text("a\n1\n")
    assert code_only == store.git_sha(repo) != head
    assert store.git_sha(repo, exclude=["/somewhere/else"]) == code_only


def test_refusal_rule(repo, tmp_path):
    out = repo / "results"
    provenance.refuse_dirty(out, repo=repo)  # clean: passes
    (repo / "code.py").write_text("x = 2\n")
    with pytest.raises(provenance.DirtyTree) as e:
        provenance.refuse_dirty(out, repo=repo)
    msg = str(e.value)
    assert "\n" not in msg and "1 tracked file (code.py)" in msg
    assert "commit them, or pass --allow-dirty" in msg
    with pytest.raises(provenance.DirtyTree):  # a new directory that could be committed
        provenance.refuse_dirty(repo / "results" / "new_suite", repo=repo)
    with pytest.raises(provenance.DirtyTree):
        provenance.refuse_dirty(repo / "results" / "b.json", file=True, repo=repo)
    provenance.refuse_dirty(out, allow_dirty=True, repo=repo)
    with pytest.raises(provenance.DirtyTree):  # any of several outputs
        provenance.refuse_dirty([tmp_path / "elsewhere", out], repo=repo)
    provenance.refuse_dirty(repo / "build" / "bench-results", repo=repo)  # git-ignored
    provenance.refuse_dirty(tmp_path / "elsewhere" / "res", repo=repo)  # in no work tree
    # the outputs' own tracked files (a committed run being resumed) do not count
    (repo / "results" / "table.csv").write_text("a\n2\n")
    with pytest.raises(provenance.DirtyTree, match=r"1 tracked file \(code.py\)"):
        provenance.refuse_dirty(out, repo=repo)
    git(repo, "checkout", "code.py")
    provenance.refuse_dirty(out, repo=repo)
    with pytest.raises(provenance.DirtyTree, match=r"1 tracked file \(results/table.csv\)"):
        provenance.refuse_dirty(repo / "results" / "other", repo=repo)
    for i in range(5):
        (repo / f"m{i}.py").write_text("")
    git(repo, "add", ".")
    (repo / "code.py").write_text("x = 2\n")
    with pytest.raises(provenance.DirtyTree, match=r"6 tracked files \(code.py, m0.py, m1.py, "
                       r"\.\.\.\)"):
        provenance.refuse_dirty(out, repo=repo)


class Reached(ValueError):
    pass


def _reached(*a, **k):
    raise Reached("the command's work started")


# each command with its output inside the checkout and its first step of work faked
COMMANDS = {
    "run": (["run", "--suite", "smoke", "--results", "{repo}/results", "--runs-dir",
             "{tmp}/runs"], "benchmarks.suite.runner.run_suite"),
    "run, runs in the checkout": (["run", "--suite", "smoke", "--results", "{tmp}/res",
                                   "--runs-dir", "{repo}/results/runs"],
                                  "benchmarks.suite.runner.run_suite"),
    "run --tables-only": (["run", "--suite", "smoke", "--tables-only", "--results",
                           "{repo}/results"], "benchmarks.suite.runner.rewrite_tables"),
    "curves": (["curves", "--suite", "smoke", "--results", "{repo}/results", "--runs-dir",
                "{tmp}/runs"], "benchmarks.suite.curves.build_curves"),
    "tolerance": (["tolerance", "--suite", "smoke", "--results", "{repo}/results"],
                  "benchmarks.suite.compare.read_csv"),
    "crosscheck": (["crosscheck", "rod_cantilever", "--out-dir", "{repo}/results/crosscheck"],
                   "benchmarks.validation.crosscheck.run_crosscheck"),
    "plate-fidelity": (["plate-fidelity", "--out-dir", "{repo}/results/plate_fidelity"],
                       "benchmarks.validation.plate_fidelity.run_fidelity"),
    "bench train": (["bench", "train", "--device", "cpu", "--json", "{repo}/results/b.json"],
                    "benchmarks.commands.bench.mp.get_context"),
}


@pytest.mark.parametrize("name", COMMANDS)
def test_commands_refuse_a_dirty_checkout(name, repo, tmp_path, monkeypatch, capsys):
    """Through the CLI, with the package's checkout pointed at a modified tiny repository: exit
    2 and one line before any work, the work with --allow-dirty, no refusal when clean."""
    argv, work = COMMANDS[name]
    argv = [a.format(repo=repo, tmp=tmp_path) for a in argv]
    monkeypatch.setattr(store, "REPO", repo)
    monkeypatch.setattr(work, _reached)
    (repo / "results" / "smoke").mkdir()
    (repo / "results" / "smoke" / "rmse_at_step.csv").write_text("")  # tolerance's input
    git(repo, "add", ".")
    git(repo, "commit", "-q", "-m", "smoke")
    assert main(argv) == 2
    assert "work started" in capsys.readouterr().err  # clean: not refused
    (repo / "code.py").write_text("x = 2\n")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"meshbench {argv[0]}: error: ")
    assert "uncommitted changes to 1 tracked file (code.py)" in err and "--allow-dirty" in err
    assert main(argv + ["--allow-dirty"]) == 2
    assert "work started" in capsys.readouterr().err


def test_crosscheck_records_the_code_as_it_was_before_its_own_outputs(tmp_path, monkeypatch):
    """A command that rewrites committed files as it goes (``crosscheck``'s CSV and summary,
    ``curves``' curves.csv) records the code's state without its own output directory: its
    outputs, also those of an earlier run into it, never make the record say ``-dirty`` (as
    they never make it refused)."""
    import dataclasses
    import json

    from benchmarks.suite.registry import get_case
    from benchmarks.validation import crosscheck as cc

    calls = []

    def sha_now(repo=None, exclude=()):  # dirty once outputs exist, unless left out
        calls.append(any(tmp_path.iterdir()))
        own = any(tmp_path.resolve() == type(tmp_path)(d).resolve() for d in exclude)
        return "abc-dirty-0123" if calls[-1] and not own else "abc"

    monkeypatch.setattr(store, "git_sha", sha_now)
    tiny = dataclasses.replace(get_case("rod_cantilever"), t_end=0.03)
    monkeypatch.setitem(cc.CROSSCHECKS, "tiny", lambda youngs=None: dataclasses.replace(
        cc.rod_crosscheck(tiny, youngs, [cc.Resolution("default", 11, 10)]), case_id="tiny"))
    for _ in range(2):  # the second run starts with the first one's outputs in place
        assert main(["crosscheck", "tiny", "--out-dir", str(tmp_path), "--no-progress"]) == 0
        assert json.loads((tmp_path / "tiny.json").read_text())["git_sha"] == "abc"
    assert calls[-1]


def test_curves_evaluation_records_the_code_as_it_was_before_its_own_outputs(tmp_path):
    import json

    from benchmarks.suite import curves

    path = tmp_path / "evaluation.json"
    curves.write_evaluation(path, "cpu", "abc")
    assert json.loads(path.read_text())["git_sha"] == "abc"
