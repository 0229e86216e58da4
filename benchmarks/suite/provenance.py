"""Results that can be committed come from a named commit.

A command that writes results (``meshbench run``, ``curves``, ``tolerance``, ``crosscheck``,
``plate-fidelity``, ``bench --json``) calls :func:`refuse_dirty` with its output path before
any work starts. The rule: when the output lies where git would commit it (inside a git work
tree and not ignored, e.g. the committed ``results/``) and the code's checkout has modified
tracked files (untracked files do not count), the command stops with exit code 2 unless
``--allow-dirty`` is given. Outputs elsewhere (a temporary directory, the git-ignored
``build/`` of ``tox -e bench``) are never refused; every record still names its code by
``store.git_sha()``, ``SHA-dirty-HASH`` for a modified tree (docs/SUITE.md, "Reproducing a row
from its sha")."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

#: how many modified paths the refusal names
SHOWN_PATHS = 3


class DirtyTree(ValueError):
    """Results would be written where they can be committed, from uncommitted code."""


def add_allow_dirty(parser) -> None:
    parser.add_argument("--allow-dirty", action="store_true",
                        help="write results into a git work tree even though the code has "
                             "uncommitted changes (recorded as SHA-dirty-HASH of the diff)")


def committable(path: str | os.PathLike, file: bool = False) -> bool:
    """True when ``path`` (a directory, or a file with ``file``; existing or not) lies inside a
    git work tree and is not ignored there, i.e. what is written there can be committed."""
    path = Path(path).resolve()
    probe = path
    while not probe.is_dir() and probe != probe.parent:
        probe = probe.parent
    # the trailing slash lets a directory pattern (/build/) match a directory not made yet
    target = str(path) if file else str(path).rstrip("/") + "/"
    try:
        out = subprocess.run(["git", "check-ignore", "-q", target], capture_output=True,
                             cwd=probe, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return False
    return out.returncode == 1  # 0: ignored, 128: not in a work tree (or no git)


def refuse_dirty(outs, allow_dirty: bool = False, file: bool = False,
                 repo: str | os.PathLike | None = None) -> None:
    """Raise :class:`DirtyTree` (exit 2 through the CLI) when an output directory of ``outs``
    (one path or several; files with ``file``) can be committed and the checkout ``repo``
    (default: the package's own, ``store.REPO``) has modified tracked files, unless
    ``allow_dirty``. Files modified inside the outputs themselves (a committed run being
    resumed) do not count."""
    if allow_dirty:
        return
    from groundtruth import store  # numpy: not while the commands register (benchmarks.cli)

    outs = [outs] if isinstance(outs, (str, os.PathLike)) else list(outs)
    state = store.git_state(repo)
    if state is None or not state[1]:
        return
    targets = [o for o in outs if committable(o, file)]
    if not targets:
        return
    state = store.git_state(repo, exclude=targets)
    if state is None or not state[1]:
        return
    sha, paths = state
    n = len(paths)
    shown = ", ".join(paths[:SHOWN_PATHS]) + (", ..." if n > SHOWN_PATHS else "")
    files = f"{n} tracked file{'s' if n != 1 else ''}"
    where = str(targets[0]) if file else str(targets[0]).rstrip("/") + "/"
    raise DirtyTree(f"{where} is in a git work tree, where results are committed, but the code "
                    f"has uncommitted changes to {files} ({shown}); commit them, or pass "
                    f"--allow-dirty to record the results as {sha[:7]}-dirty-<hash of the diff>")
