"""The trajectory store: atomic npz/json files, one directory per case (see docs/FORMAT.md)."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
REQUIRED_KEYS = ("t", "pos", "vel", "youngs", "edges", "cells", "node_type", "rest_pos",
                 "mass", "force", "damping", "case", "split", "case_hash", "format_version")


class StoreError(RuntimeError):
    """A stored file is missing, corrupt, foreign or of another format version."""


def data_dir(override: str | os.PathLike | None = None) -> Path:
    """``override``, else ``$MESHBENCH_DATA``, else ``./data``."""
    return Path(override or os.environ.get("MESHBENCH_DATA") or "data")


def regenerate_hint(case_id: str, root: Path | None = None) -> str:
    extra = f" --data-dir {root}" if root is not None else ""
    return f"meshbench generate {case_id} --force{extra}"


def atomic_write(path: Path, write: Callable[[object], None], mode: str = "wb") -> None:
    """Write ``path`` through ``write(fileobj)`` into a temporary file, fsync, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_npz(path: Path, arrays: dict) -> None:
    atomic_write(path, lambda f: np.savez(f, **arrays))


def save_json(path: Path, obj: dict) -> None:
    text = json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n"
    atomic_write(path, lambda f: f.write(text), mode="w")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def trajectory_arrays(case, t, pos, vel, youngs, split: str) -> dict:
    """Assemble the arrays of one split file in the documented layout."""
    edges, cells, node_type = case.mesh()
    loads = case.loads()
    return {
        "t": np.asarray(t, float), "pos": np.asarray(pos, float), "vel": np.asarray(vel, float),
        "youngs": np.asarray(youngs, float), "edges": np.asarray(edges, np.int64),
        "cells": np.asarray(cells, np.int64), "node_type": np.asarray(node_type, np.int64),
        "rest_pos": case.rest_positions(), "mass": loads["mass"], "force": loads["force"],
        "damping": loads["damping"], "case": np.array(case.id), "split": np.array(split),
        "case_hash": np.array(case.hash()), "format_version": np.array(FORMAT_VERSION),
    }


def load_npz(path: Path, case_id: str | None = None, case_hash: str | None = None,
             root: Path | None = None) -> dict:
    """Load and validate a trajectory file; errors name the file and how to regenerate it."""
    path = Path(path)
    cid = case_id or "CASE"
    hint = regenerate_hint(cid, root)
    if not path.exists():
        raise StoreError(f"{path}: no such trajectory file; create it with `{hint}`")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise StoreError(f"{path}: not a readable trajectory file ({e}); "
                         f"regenerate it with `{hint}`") from None
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise StoreError(f"{path}: not a meshbench trajectory file (missing {missing}); "
                         f"regenerate it with `{hint}`")
    if int(data["format_version"]) != FORMAT_VERSION:
        raise StoreError(f"{path}: format_version {int(data['format_version'])} but this meshbench "
                         f"reads {FORMAT_VERSION}; regenerate it with `{hint}`")
    if case_id is not None and str(data["case"]) != case_id:
        raise StoreError(f"{path}: holds case {str(data['case'])!r}, expected {case_id!r}; "
                         f"regenerate it with `{hint}`")
    if case_hash is not None and str(data["case_hash"]) != case_hash:
        raise StoreError(f"{path}: made from other parameters of case {cid!r} (hash "
                         f"{str(data['case_hash'])[:12]} != {case_hash[:12]}); "
                         f"regenerate it with `{hint}`")
    check_shapes(data, path)
    return data


def check_shapes(d: dict, path: Path | str = "<arrays>") -> None:
    """Raise ``StoreError`` unless the arrays have the documented, mutually consistent shapes."""
    pos = d["pos"]
    problems = []
    if pos.ndim != 4 or pos.shape[-1] != 3:
        problems.append(f"pos has shape {pos.shape}, expected (B, T, N, 3)")
    else:
        B, T, N, _ = pos.shape
        want = {"vel": (B, T, N, 3), "t": (T,), "youngs": (B,), "node_type": (N,),
                "rest_pos": (N, 3), "mass": (N,), "force": (N, 3), "damping": (N,)}
        for k, shape in want.items():
            if d[k].shape != shape:
                problems.append(f"{k} has shape {d[k].shape}, expected {shape}")
        for k in ("edges", "cells"):
            a = d[k]
            width = 2 if k == "edges" else 3
            if a.ndim != 2 or a.shape[1] != width:
                problems.append(f"{k} has shape {a.shape}, expected (*, {width})")
            elif a.size and (a.min() < 0 or a.max() >= N):
                problems.append(f"{k} refers to nodes outside [0, {N})")
    if problems:
        raise StoreError(f"{path}: inconsistent trajectory file: " + "; ".join(problems))


#: the checkout whose commit the records name (the package's own; tests point it elsewhere)
REPO = Path(__file__).resolve().parent
#: how many hex digits of sha256(``git diff --binary HEAD``) a dirty tree's sha carries
DIFF_HASH_LEN = 12


def _git(repo: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], capture_output=True, cwd=repo, timeout=30)


def _toplevel(repo: Path) -> Path | None:
    """The root of the work tree ``repo`` lies in (resolved), or None outside one."""
    out = _git(repo, "rev-parse", "--show-toplevel")
    top = out.stdout.decode().strip()
    return Path(top).resolve() if out.returncode == 0 and top else None


def _excludes(repo: Path, exclude) -> list[str]:
    """git pathspecs leaving out the paths ``exclude`` (those inside ``repo``'s work tree;
    others are ignored), after a ``--``; none for none."""
    top = _toplevel(repo) if exclude else None
    if top is None:
        return []
    paths = [Path(d).resolve() for d in exclude]
    specs = [f":(exclude,top){d.relative_to(top).as_posix()}" for d in paths
             if d.is_relative_to(top)]
    return ["--", ":/", *specs] if specs else []


def git_state(repo: str | os.PathLike | None = None,
              exclude=()) -> tuple[str, list[str]] | None:
    """``(HEAD sha, paths of modified tracked files)`` of ``repo`` (default: the package's
    checkout), or None without git or a commit. Untracked files do not count, nor files
    under the paths ``exclude`` (a command's own outputs)."""
    repo = Path(REPO if repo is None else repo)
    try:
        out = _git(repo, "rev-parse", "HEAD")
        sha = out.stdout.decode().strip()
        if out.returncode != 0 or not sha:
            return None
        status = _git(repo, "status", "--porcelain", "--untracked-files=no",
                      *_excludes(repo, exclude))
        if status.returncode != 0:
            return None
        # "XY path" or "XY old -> new" (a rename); the path after the arrow is the one now
        paths = [line[3:].split(" -> ")[-1]
                 for line in status.stdout.decode(errors="replace").splitlines() if line.strip()]
        return sha, paths
    except (OSError, subprocess.SubprocessError):
        return None


def git_sha(repo: str | os.PathLike | None = None, exclude=()) -> str:
    """``SHA`` of ``repo``'s HEAD (default: the package's checkout); ``SHA-dirty-HASH`` when
    tracked files are modified, HASH the first 12 hex digits of the sha256 of
    ``git diff --binary HEAD`` (the uncommitted change itself, staged or not); "unknown"
    without git. ``SHA-dirty`` alone when the diff could not be read. Files under the
    directories ``exclude`` (the calling command's own outputs, committed files it rewrites)
    count neither as modified nor in the diff."""
    state = git_state(repo, exclude)
    if state is None:
        return "unknown"
    sha, dirty = state
    if not dirty:
        return sha
    try:
        repo = Path(REPO if repo is None else repo)
        diff = _git(repo, "diff", "--binary", "--no-color", "--no-ext-diff", "--no-textconv",
                    "HEAD", *_excludes(repo, exclude))
    except (OSError, subprocess.SubprocessError):
        return f"{sha}-dirty"
    if diff.returncode != 0:
        return f"{sha}-dirty"
    return f"{sha}-dirty-{hashlib.sha256(diff.stdout).hexdigest()[:DIFF_HASH_LEN]}"


def library_versions() -> dict:
    """Versions of the libraries that shape the results (those importable)."""
    import importlib.metadata as md

    out = {"python": platform.python_version(), "platform": platform.platform()}
    for name in ("meshbench", "numpy", "scipy", "scikit-fem", "meshio", "torch",
                 "torch-geometric", "torchdiffeq", "pandas"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


def read_meta(case_dir: Path) -> dict | None:
    path = Path(case_dir) / "meta.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        root = Path(case_dir).parent
        raise StoreError(f"{path}: unreadable metadata ({e}); repair it with `"
                         + regenerate_hint(Path(case_dir).name, None if root == Path("data")
                                           else root).replace(" --force", "") + "`") from None


def is_current(case_dir: Path, case_hash: str, verify: bool = True) -> bool:
    """True when ``meta.json`` matches ``case_hash`` and every split file matches its sha256."""
    meta = read_meta(case_dir)
    if not meta or meta.get("case_hash") != case_hash or meta.get("format_version") != FORMAT_VERSION:
        return False
    for split in meta.get("splits", {}).values():
        f = Path(case_dir) / split["file"]
        if not f.exists() or (verify and sha256_file(f) != split.get("sha256")):
            return False
    return bool(meta.get("splits"))


def load_split(case, split: str, root: str | os.PathLike | None = None) -> dict:
    """Load ``ROOT/CASE/SPLIT.npz`` checking it belongs to ``case`` as registered now."""
    root = data_dir(root)
    return load_npz(root / case.id / f"{split}.npz", case.id, case.hash(),
                    root if root != Path("data") else None)
