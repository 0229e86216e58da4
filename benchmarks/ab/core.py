"""What both codes of the A/B share: the columns of ``ab.csv``, the authors' loss, the test
metrics, the data both are fed, the run configuration and the state files.

Units. The authors' loss of one trajectory (their ``MeshODENet.loss``; docs/SOURCES.md) is
``sqrt(mean over frames k and coordinates c of sum over nodes i of (x_pred - x_true)^2)``, m,
frame 0 included; a split's loss is its mean over trajectories (their ``test``). With ``N``
nodes, ``loss * sqrt(3 / N)`` is the Euclidean RMSE of that trajectory over all its frames
(frame 0 included) and nodes. ``test_rmse_m`` is our metric, ``meshodenet.metrics.position_rmse``
(over trajectories, frames ``k >= 1`` and nodes), and ``test_rmse_coord_m`` that over ``sqrt(3)``
(the authors' per-coordinate "position RMSE").
"""

from __future__ import annotations

import csv
import json
import math
import resource
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

#: ``ab.csv``: one row per (code, epoch). ``epoch`` counts finished training epochs (0: the
#: untrained model, and the ``standing_still`` row, the prediction x(t) = x(0)); the authors'
#: logs count from 0, so their epoch e is our e + 1. Losses in the authors' units (module
#: docstring), RMSEs in m; ``val_rmse_m`` our validation RMSE (``ours`` only); ``wall_s`` /
#: ``cpu_s`` the epoch's training (ours: with its validation), ``test_wall_s`` / ``test_cpu_s``
#: the test evaluation; ``peak_rss_mb`` the process's peak resident memory so far.
COLUMNS = ("case", "code", "epoch", "train_loss", "test_loss", "test_rmse_m", "test_rmse_coord_m",
           "val_rmse_m", "lr", "wall_s", "cpu_s", "test_wall_s", "test_cpu_s", "peak_rss_mb")
#: Columns that depend on the machine, not on the computation (left out of equality checks).
TIMING_COLUMNS = ("wall_s", "cpu_s", "test_wall_s", "test_cpu_s", "peak_rss_mb")
CODES = ("authors", "ours")
CSV_FILE = "ab.csv"
CONFIG_FILE = "ab_config.json"
#: One entry per invocation of ``train`` on a run directory: when, the epoch it started from,
#: device, threads, library versions and git commit (a run may go on on another machine).
SESSIONS_FILE = "sessions.json"
#: The authors' time per frame (their ``--time_step`` and rk4 ``step_size``; their velocity
#: is a difference of positions over it).
FRAME_TIME = 0.1
#: The authors' preprocessing keeps at most this many frames of a trajectory.
AUTHORS_MAX_FRAMES = 400
#: The authors' seed (their training script's), the default of both codes here.
AUTHORS_SEED = 42
#: Default epochs by mesh kind: the plate's (triangles) and the rod's (line) A/B (docs/AB.md).
DEFAULT_EPOCHS = {"triangle": 25, "line": 50}


class ABError(ValueError):
    """A bad argument, checkout, data file or run directory: one line naming it (exit 2)."""


def authors_loss(pred, true):
    """``(B,)`` float64: the authors' loss of each trajectory; ``pred, true (B, T, N, 3)``
    torch tensors."""
    err = (pred.double() - true.double()) ** 2
    return err.sum(2).mean((1, 2)).sqrt()


def test_metrics(pred, true) -> dict:
    """``test_loss`` (mean over trajectories of ``authors_loss``), ``test_rmse_m``
    (``position_rmse``) and ``test_rmse_coord_m`` (that / sqrt 3) of ``pred`` against
    ``true (B, T, N, 3)``; NaN where the rollout is not finite."""
    from meshodenet.metrics import position_rmse

    loss = float(authors_loss(pred, true).mean())
    rmse = position_rmse(pred, true)
    loss, rmse = (v if math.isfinite(v) else math.nan for v in (loss, rmse))
    return {"test_loss": loss, "test_rmse_m": rmse, "test_rmse_coord_m": rmse / math.sqrt(3)}


def empty_row(case: str, code: str, epoch: int) -> dict:
    row = dict.fromkeys(COLUMNS, math.nan)
    row.update(case=case, code=code, epoch=epoch)
    return row


def standing_still_row(case: str, true) -> dict:
    """The test metrics of x(t) = x(0) for ``true (B, T, N, 3)`` (code ``standing_still``)."""
    from meshodenet.metrics import no_motion

    row = empty_row(case, "standing_still", 0)
    row.update(test_metrics(no_motion(true), true))
    return row


class Clock:
    """Wall and CPU seconds since construction (``seconds()``)."""

    def __init__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def seconds(self) -> tuple[float, float]:
        return time.perf_counter() - self.wall, time.process_time() - self.cpu


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, MB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# --- the data both codes see -------------------------------------------------------------------
def check_count(name: str, value, lo: int = 1) -> None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < lo):
        raise ABError(f"{name} must be an integer >= {lo}, got {value!r}")


def load_arrays(case_id: str, split: str, data_dir, max_n: int | None, frames: int | None,
                flag: str) -> dict:
    """The store's arrays of ``case_id``'s ``split`` (``groundtruth.store.load_split``), the first
    ``max_n`` trajectories (all: None) and the first ``frames`` frames (None: the authors' rule,
    at most ``AUTHORS_MAX_FRAMES``). ``flag`` names the option that set ``max_n`` in errors."""
    from benchmarks.suite.registry import get_case
    from groundtruth import store

    check_count(flag, max_n)
    check_count("--frames", frames, 2)
    try:
        arrays = dict(store.load_split(get_case(case_id), split, data_dir))
    except store.StoreError as e:
        raise ABError(f"--data-dir {data_dir or store.data_dir()}: {e}") from None
    B, T = arrays["pos"].shape[:2]
    if frames is not None and frames > T:
        raise ABError(f"--frames {frames}: the {split} split of {case_id} has only {T} frames")
    keep = min(T, AUTHORS_MAX_FRAMES) if frames is None else frames
    n = B if max_n is None else min(max_n, B)
    arrays["pos"], arrays["vel"] = arrays["pos"][:n, :keep], arrays["vel"][:n, :keep]
    arrays["t"], arrays["youngs"] = arrays["t"][:keep], arrays["youngs"][:n]
    return arrays


# --- the run's configuration -------------------------------------------------------------------
@dataclass(frozen=True)
class Setup:
    """What one A/B run is determined by (``ab_config.json``); ``epochs`` may grow on resume.
    ``max_train`` / ``max_test`` (smoke checks only) keep the first trajectories of a split;
    ``frames`` the first frames (None: the authors' rule, at most 400); ``seed`` seeds both
    codes (the authors' code: 42); ``extra`` what the code adds (the authors' file hashes, our
    preset and overrides)."""

    case: str
    code: str
    epochs: int
    frames: int | None = None
    seed: int = AUTHORS_SEED
    threads: int = 1
    max_train: int | None = None
    max_test: int | None = None
    extra: tuple = ()

    def __post_init__(self):
        if self.code not in CODES:
            raise ABError(f"--code {self.code!r} is not a code; valid: {', '.join(CODES)}")
        check_count("--epochs", self.epochs)
        check_count("--threads", self.threads)
        check_count("--seed", self.seed, 0)
        check_count("--max-train", self.max_train)
        check_count("--max-test", self.max_test)
        check_count("--frames", self.frames, 2)

    def to_json(self) -> dict:
        d = asdict(self)
        d["extra"] = dict(self.extra)
        return json.loads(json.dumps(d))

    def with_extra(self, **extra) -> Setup:
        return replace(self, extra=tuple(sorted(extra.items())))

    @property
    def is_smoke(self) -> bool:
        return self.max_train is not None or self.max_test is not None


def check_resume(out: Path, setup: Setup, data: dict, defaults: dict | None = None) -> None:
    """Write ``out/ab_config.json`` for a new run, or refuse (``ABError``) to continue a run
    stored with another configuration (anything but ``epochs`` and how the settings were given,
    ``_settings``) or other data (``data``: what identifies it, e.g. the case hash).
    ``defaults`` (``{section of extra: {field: default}}``): a field that a stored run predates
    has its default there (the run was trained with it)."""
    path = out / CONFIG_FILE
    new = {**setup.to_json(), "data": data}
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ABError(f"{path}: unreadable ({e}); choose another --out") from None
        from benchmarks.suite.runs import config_diff

        diff = [d for d in config_diff(_settings(_with_defaults(old, defaults or {})),
                                       _settings(new)) if not d.startswith("epochs:")]
        if diff:
            more = f"; {len(diff) - 4} more" if len(diff) > 4 else ""
            raise ABError(f"{out} holds a run with another configuration (stored -> now: "
                          f"{'; '.join(diff[:4])[:300]}{more}); resume with the same options "
                          "or choose another --out")
        if old.get("epochs") != new["epochs"]:
            _atomic_text(path, json.dumps(new, indent=2, sort_keys=True) + "\n")
        return
    out.mkdir(parents=True, exist_ok=True)
    _atomic_text(path, json.dumps(new, indent=2, sort_keys=True) + "\n")


def jsonable(cfg, *leave_out: str) -> dict:
    """A settings dataclass as ``ab_config.json`` stores it (JSON types: tuples are lists),
    without the fields ``leave_out``."""
    return json.loads(json.dumps({k: v for k, v in asdict(cfg).items() if k not in leave_out}))


def _with_defaults(config: dict, defaults: dict) -> dict:
    """``config`` with the fields its ``extra`` sections lack taken from ``defaults``."""
    extra = dict(config.get("extra") or {})
    for section, fields in defaults.items():
        if isinstance(extra.get(section), dict):
            extra[section] = {**fields, **extra[section]}
    return {**config, "extra": extra}


def _settings(config: dict) -> dict:
    """``config`` without how its settings were given (``--set``'s ``overrides``): a run resumes
    under any options that resolve to the settings it was stored with."""
    extra = {k: v for k, v in (config.get("extra") or {}).items() if k != "overrides"}
    return {**config, "extra": extra}


def record_session(out: Path, first_epoch: int, device="cpu") -> None:
    """Append this invocation to ``out/sessions.json`` (``SESSIONS_FILE``), atomically: the
    provenance ``meshbench train`` records (``benchmarks.suite.runs.session_info``) and the
    epoch it started from."""
    from benchmarks.suite.runs import session_info
    from groundtruth import store

    path = out / SESSIONS_FILE
    try:
        sessions = json.loads(path.read_text()) if path.exists() else []
    except (OSError, json.JSONDecodeError) as e:
        raise ABError(f"{path}: unreadable ({e}); choose another --out") from None
    if not isinstance(sessions, list):
        raise ABError(f"{path}: not a list of sessions; choose another --out")
    sessions.append({**session_info(device, time.time()), "first_epoch": int(first_epoch)})
    store.save_json(path, sessions)


def _atomic_text(path: Path, text: str) -> None:
    from groundtruth.store import atomic_write

    atomic_write(path, lambda f: f.write(text), "w")


# --- rows and state files ----------------------------------------------------------------------
def write_csv(out: Path, rows: list) -> None:
    """``out/ab.csv`` from ``rows`` (sorted by code and epoch), floats ``%.6g``, atomically."""
    from meshodenet.training.train import write_rows

    write_rows(out / CSV_FILE, sorted(rows, key=lambda r: (r["code"], r["epoch"])), COLUMNS)


def read_csv(out: Path) -> list:
    """The rows of ``out/ab.csv`` as written (numbers back as int / float)."""
    path = out / CSV_FILE
    if not path.exists():
        return []
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if rows and list(rows[0]) != list(COLUMNS):
        raise ABError(f"{path}: not an A/B table (columns {list(rows[0])}); choose another --out")
    return [{k: _number(k, v) for k, v in r.items()} for r in rows]


def _number(key: str, text: str):
    if key in ("case", "code"):
        return text
    return int(text) if key == "epoch" else float(text)


def save_state(path: Path, state: dict) -> None:
    """Atomically ``torch.save`` a dict of tensors and plain values (``meshodenet.training.train``'s
    ``save_checkpoint``: it refuses anything ``weights_only=True`` could not load)."""
    from meshodenet.training.train import save_checkpoint

    save_checkpoint(path, state)


def load_state(path: Path) -> dict:
    """``torch.load(path, weights_only=True)``: nothing in the file is executed; ``ABError``
    naming the file when it is unreadable."""
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a bad file
        first = str(e).strip().splitlines()[0][:160] if str(e).strip() else type(e).__name__
        raise ABError(f"{path}: not a readable A/B state ({first}); choose another --out") from None
    if not isinstance(state, dict) or "epoch" not in state:
        raise ABError(f"{path}: not an A/B state file; choose another --out")
    return state


def numpy_rng_state() -> list:
    """``numpy.random.get_state()`` as plain values (the authors' code seeds numpy)."""
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    return [name, keys.tolist(), int(pos), int(has_gauss), float(gauss)]


def set_numpy_rng_state(state: list) -> None:
    name, keys, pos, has_gauss, gauss = state
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, gauss))


def progress_line(row: dict, epochs: int, n_nodes: int) -> str:
    """One line per epoch: losses, the test RMSE in mm, seconds."""
    return (f"{row['code']} {row['case']} epoch {row['epoch']}/{epochs}: train loss "
            f"{row['train_loss']:.4g} test loss {row['test_loss']:.4g} (RMSE "
            f"{1e3 * row['test_rmse_m']:.3g} mm over {n_nodes} nodes) wall {row['wall_s']:.0f} s "
            f"cpu {row['cpu_s']:.0f} s test {row['test_wall_s']:.0f} s peak "
            f"{row['peak_rss_mb']:.0f} MB")


def data_id(train: dict, test: dict) -> dict:
    """What identifies the data a run is fed (the ``data`` of its ``ab_config.json``)."""
    return {"case_hash": str(train["case_hash"]), "n_train": int(train["pos"].shape[0]),
            "n_test": int(test["pos"].shape[0]), "frames": int(train["pos"].shape[1]),
            "nodes": int(train["pos"].shape[2])}
