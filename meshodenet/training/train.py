"""The training engine shared by every ``TrajectoryModel``.

``fit`` runs epochs of shuffled mini-batches of ``model.training_loss`` with Adam (coupled
weight decay, as ``torch.optim.Adam``) and a step learning-rate schedule, validates by
rolling out the validation trajectories from their initial states (position RMSE), keeps the
best model by that validation RMSE (never by the test split), and after every epoch writes,
atomically, ``last.pt`` (everything needed to continue exactly: model, optimizer, scheduler,
RNG states, epoch, best score, history), ``best.pt`` when the validation RMSE improved, and
``history.csv``. ``fit(..., resume=True)`` continues from ``last.pt``.

Budget checkpoints (``TrainConfig.budgets_s``): at the end of the first epoch at which the
training process has spent a budget's CPU seconds, ``best.pt`` (the best-so-far model on
validation) is copied to ``budgets/best_{budget}s.pt`` and a row appended to ``budgets.csv``
(``BUDGET_FIELDS``). Budgets count CPU time (``time.process_time``), not wall time: the
machines are shared, so a run's wall time depends on what else runs beside it while its CPU
time does not (much). With TensorBoard installed (the ``tensorboard`` extra), ``fit`` also
writes event files beside ``history.csv``; set ``MESHBENCH_TENSORBOARD=0`` to switch them off.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import io
import math
import os
import pickle
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import Trajectories
from meshodenet.metrics import position_rmse
from meshodenet.training.distributed import (  # noqa: F401  (re-exported: the engine's public names)
    broadcast_parameters,
    distributed_backward,
    distributed_rank,
)

HISTORY_FIELDS = ("epoch", "train_loss", "val_rmse", "best_val_rmse", "lr", "skipped_steps",
                  "epoch_time_s", "wall_time_s")
#: ``budgets.csv``: one row per budget crossed (CPU seconds of training, summed over sessions;
#: wall seconds of the epochs; the epoch that crossed it; the best validation RMSE so far, m;
#: the machine's 1-minute load average then, which says how shared the wall time was).
BUDGET_FIELDS = ("budget_s", "cpu_s", "wall_s", "epoch", "best_epoch", "best_val_rmse",
                 "load_1m")
BUDGETS_FILE = "budgets.csv"
BUDGET_DIR = "budgets"
#: The training budget's clock (CPU seconds of this process, every thread); a module
#: attribute so that a test can replace it for a run started through the suite.
CPU_CLOCK = time.process_time


def budget_checkpoint(run_dir, budget: int) -> Path:
    """Where ``fit`` stores the best-so-far checkpoint of ``budget`` CPU seconds."""
    return Path(run_dir) / BUDGET_DIR / f"best_{int(budget)}s.pt"


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings, identical in meaning for every model.

    ``lr`` is multiplied by ``lr_gamma`` at each epoch in ``lr_milestones`` (paper: 1e-4, / 10
    every 100 epochs for the rod, at 200 and 400 for the plate). ``batch_size`` counts
    training samples (see ``TrajectoryModel.n_training_samples``) per optimizer step.
    ``val_fraction`` of the training trajectories form the validation split, carved by
    ``val_split`` (``meshodenet.mesh.data.VAL_SPLITS``): ``stratified``, evenly over the sorted
    Young's moduli (no seed), or ``random``, drawn with ``split_seed`` (the only method
    before ``val_split`` existed); ``seed`` seeds the model's initialisation and the shuffling.
    ``grad_clip`` (max global norm) 0 disables clipping. ``eval_batch_size`` trajectories are
    rolled out together during validation. ``max_batches`` > 0 caps the optimizer steps per
    epoch (a fresh random subset of samples each epoch); 0 uses every sample.
    ``budgets_s`` (increasing CPU seconds) are the budget checkpoints of the module docstring;
    ``max_cpu_s`` > 0 ends training at the end of the epoch that spends that many CPU seconds
    (and is a budget checkpoint itself); 0 trains for ``epochs``.
    ``patch_nodes`` > 0 trains on patches of the mesh of about that many nodes plus a halo
    (``meshodenet.subdomain.PatchTraining``, wrapped around the model by the runner; a sample
    is then a (sample, patch) pair); 0 trains on the whole mesh. ``patch_budget``: what
    ``patch_nodes`` counts, ``inner`` (a part's nodes, the halo on top) or ``total`` (the
    whole patch: a step's memory then bounded whatever the halo).
    """

    epochs: int = 400
    lr: float = 1e-4
    lr_milestones: tuple = (100, 200, 300)
    lr_gamma: float = 0.1
    weight_decay: float = 5e-4
    batch_size: int = 1
    val_fraction: float = 0.1
    val_every: int = 1
    val_split: str = "stratified"
    split_seed: int = 0
    seed: int = 0
    grad_clip: float = 0.0
    eval_batch_size: int = 16
    max_batches: int = 0
    budgets_s: tuple = ()
    max_cpu_s: int = 0
    patch_nodes: int = 0
    patch_budget: str = "inner"

    def __post_init__(self):
        for name, lo in (("epochs", 1), ("batch_size", 1), ("val_every", 1),
                         ("eval_batch_size", 1), ("split_seed", 0), ("seed", 0),
                         ("max_batches", 0), ("max_cpu_s", 0), ("patch_nodes", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"TrainConfig.{name} must be an int >= {lo}, got {v!r}")
        for name, ok in (("lr", lambda v: v > 0), ("lr_gamma", lambda v: 0 < v <= 1),
                         ("weight_decay", lambda v: v >= 0), ("grad_clip", lambda v: v >= 0),
                         ("val_fraction", lambda v: 0 <= v < 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or not ok(v):
                raise ValueError(f"TrainConfig.{name} has an invalid value {v!r}")
        from meshodenet.mesh.data import VAL_SPLITS

        if self.patch_budget not in ("inner", "total"):
            raise ValueError("TrainConfig.patch_budget must be one of inner, total, got "
                             f"{self.patch_budget!r}")
        if self.val_split not in VAL_SPLITS:
            raise ValueError(f"TrainConfig.val_split must be one of {', '.join(VAL_SPLITS)}, "
                             f"got {self.val_split!r}")
        ms = tuple(self.lr_milestones)
        if any(isinstance(m, bool) or not isinstance(m, int) or m < 1 for m in ms) \
                or list(ms) != sorted(set(ms)):
            raise ValueError("TrainConfig.lr_milestones must be increasing positive epochs, "
                             f"got {self.lr_milestones!r}")
        object.__setattr__(self, "lr_milestones", ms)
        bs = tuple(self.budgets_s) if isinstance(self.budgets_s, (tuple, list)) else None
        if bs is None or any(isinstance(b, bool) or not isinstance(b, int) or b < 1 for b in bs) \
                or list(bs) != sorted(set(bs)):
            raise ValueError("TrainConfig.budgets_s must be increasing positive CPU seconds "
                             f"(ints), got {self.budgets_s!r}")
        object.__setattr__(self, "budgets_s", bs)

    @property
    def budget_points(self) -> tuple:
        """Every budget checkpoint, CPU s: ``budgets_s`` and ``max_cpu_s`` when set."""
        return tuple(sorted(set(self.budgets_s) | ({self.max_cpu_s} if self.max_cpu_s else set())))


@dataclass
class FitResult:
    best_epoch: int
    best_val_rmse: float
    epochs_run: int
    wall_time_s: float
    history: list


def make_optimizer(model: TrajectoryModel, cfg: TrainConfig):
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, list(cfg.lr_milestones), cfg.lr_gamma)
    return opt, sched


def _step_loss(model: TrajectoryModel, data: Trajectories, idx, generator) -> torch.Tensor:
    """``model.training_loss``, or NaN (a skipped step) where the model's implicit solve of a
    training window does not converge (``NewtonError``): such a window has no rollout to
    learn from, like one that diverged."""
    from meshodenet.integrators.implicit import NewtonError

    try:
        return model.training_loss(data, idx, generator)
    except NewtonError:
        return torch.tensor(math.nan)


def train_epoch(model: TrajectoryModel, opt, data: Trajectories, cfg: TrainConfig,
                generator: torch.Generator, max_batches: int | None = None,
                bar: tqdm | None = None) -> tuple[float, int]:
    """One pass over shuffled training samples: ``(mean loss, skipped steps)``.

    A step whose loss or gradient is not finite (a rollout that diverged, or an implicit
    solve that did not converge: ``_step_loss``) is skipped rather than applied; an epoch in
    which every step is skipped raises ``FloatingPointError``.
    """
    model.train()
    rank, world = distributed_rank()
    n = model.n_training_samples(data)
    order = torch.randperm(n, generator=generator)
    if world > 1:  # a seed for the ranks' loss noise, without drawing from ``generator``
        epoch_seed = int(torch.randint(0, 2 ** 40, (1,), generator=torch.Generator().set_state(
            generator.get_state()))) * 4096
    total, count, skipped, steps = 0.0, 0, 0, 0
    max_norm = cfg.grad_clip if cfg.grad_clip > 0 else math.inf
    for k, s in enumerate(range(0, n, cfg.batch_size)):
        if max_batches is not None and k >= max_batches:
            break
        steps += 1
        idx = order[s:s + cfg.batch_size]
        opt.zero_grad(set_to_none=True)
        if world > 1:  # torchrun: this rank's share of the batch, gradients all-reduced
            value, norm = distributed_backward(lambda i, g: _step_loss(model, data, i, g), model,
                                               idx, (epoch_seed + k) % 2 ** 40, rank, world,
                                               max_norm)
        else:
            loss = _step_loss(model, data, idx, generator)
            value = float(loss.detach())
            if math.isfinite(value):
                loss.backward()
                norm = torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm)
        if not math.isfinite(value) or not torch.isfinite(norm):
            skipped += 1
            continue
        opt.step()
        total += value * len(idx)
        count += len(idx)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"loss {value:.4g}", refresh=False)
    if steps and skipped == steps:
        raise FloatingPointError(f"every training step of this epoch diverged (loss {value}); "
                                 "lower the learning rate or set a grad_clip (last.pt keeps "
                                 "the last finished epoch)")
    return total / max(count, 1), skipped


def validate(model: TrajectoryModel, data: Trajectories, cfg: TrainConfig) -> float:
    """Position RMSE (m) of rollouts from the initial states of ``data``; ``inf`` when a
    rollout diverges (non-finite) or its implicit solve does not converge (``NewtonError``),
    so that such an epoch is never selected."""
    from meshodenet.integrators.implicit import NewtonError

    model.eval()
    try:
        pos, _ = model.rollout_all(data, cfg.eval_batch_size)
    except NewtonError:
        return math.inf
    rmse = position_rmse(pos, data.pos)
    return rmse if math.isfinite(rmse) else math.inf


def fit(model: TrajectoryModel, train: Trajectories, val: Trajectories, cfg: TrainConfig,
        run_dir, *, resume: bool = False, progress: bool = True, on_epoch_end=None,
        extra_state: dict | None = None, clock=None) -> FitResult:
    """Train ``model`` into ``run_dir`` (see the module docstring).

    ``val`` may be empty (then the best model is the one of lowest training loss; meant for
    tiny tests only). ``on_epoch_end(epoch, row)`` is called after the epoch's files are
    written. ``extra_state`` (JSON-able) is stored in every checkpoint, for the caller.
    ``clock()`` (default ``CPU_CLOCK``: CPU seconds of this process) measures the training
    budget: everything ``fit`` does (training, validation, checkpoints) counts, summed over
    resumed sessions through ``last.pt``; tests inject a fake clock here or in ``CPU_CLOCK``.
    """
    if not model.trainable:
        raise ValueError(f"model {model.name!r} has nothing to train (trainable = False)")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    opt, sched = make_optimizer(model, cfg)
    gen = torch.Generator().manual_seed(cfg.seed)
    state = {"epoch": 0, "best_val_rmse": math.inf, "best_epoch": -1, "history": [],
             "wall_time_s": 0.0, "cpu_time_s": 0.0, "budgets": []}
    if resume:
        state = _restore(run_dir / "last.pt", model, opt, sched, gen, state)
    start = state["epoch"]
    clock = clock or CPU_CLOCK
    cpu_base, cpu0 = state["cpu_time_s"], clock()
    lead = distributed_rank()[0] == 0  # with torchrun: only rank 0 validates and writes
    progress = progress and lead
    no_val = val if lead else val.subset(torch.zeros(0, dtype=torch.long))
    # with a CPU budget the epoch count is only a cap: no bar total, the postfix tells the time
    bar = tqdm(total=None if cfg.max_cpu_s else cfg.epochs, initial=start,
               desc=f"train {model.name}", unit="epoch",
               disable=not progress, file=sys.stderr, dynamic_ncols=True)
    board = open_tensorboard(run_dir, start) if lead else None
    try:
        for epoch in range(start, cfg.epochs):
            if _cpu_spent(cfg, state, model.device):
                break
            row, improved = _epoch(model, opt, sched, gen, train, val if lead else no_val,
                                   cfg, epoch, state, progress)
            state["cpu_time_s"] = cpu_base + clock() - cpu0
            if not lead:
                continue
            state_dicts = (model, opt, sched, gen, extra_state)
            if improved:
                save_checkpoint(run_dir / "best.pt", _checkpoint(*state_dicts, state))
            write_budgets(run_dir, cfg, state)
            save_checkpoint(run_dir / "last.pt", _checkpoint(*state_dicts, state))
            write_history(run_dir / "history.csv", state["history"])
            if board is not None:
                log_tensorboard(board, row, state)
            bar.update(1)
            bar.set_postfix_str(progress_text(row, state, cfg), refresh=True)
            if on_epoch_end is not None:
                on_epoch_end(epoch + 1, row)
    finally:
        bar.close()
        if board is not None:
            board.close()
    return FitResult(state["best_epoch"], state["best_val_rmse"], state["epoch"] - start,
                     state["wall_time_s"], state["history"])


def _checkpoint(model, opt, sched, gen, extra_state, state) -> dict:
    return {"model": model.state_dict(), "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(), "generator": gen.get_state(),
            "torch_rng": torch.get_rng_state(), **state, "extra": extra_state or {},
            "model_info": model_info(model)}


def _cpu_spent(cfg: TrainConfig, state: dict, device) -> bool:
    """Whether ``cfg.max_cpu_s`` is spent; under torchrun rank 0's answer, so that every rank
    stops at the same epoch."""
    if not cfg.max_cpu_s:
        return False
    stop = state["cpu_time_s"] >= cfg.max_cpu_s
    if distributed_rank()[1] > 1:
        flag = torch.tensor([float(stop)], device=device)
        torch.distributed.broadcast(flag, 0)
        stop = bool(flag.item())
    return stop


def write_budgets(run_dir: Path, cfg: TrainConfig, state: dict) -> list:
    """For every budget of ``cfg.budget_points`` that ``state["cpu_time_s"]`` has reached and
    ``state["budgets"]`` does not hold yet: copy ``best.pt`` (when there is one) to
    ``budget_checkpoint``, append the budget's row to ``state["budgets"]`` and rewrite
    ``budgets.csv``. Returns the budgets written."""
    done = {r["budget_s"] for r in state["budgets"]}
    due = [b for b in cfg.budget_points if b not in done and state["cpu_time_s"] >= b]
    if not due:
        return []
    best = run_dir / "best.pt"
    data = best.read_bytes() if best.exists() else None  # already in the safe format
    for b in due:
        if data is not None:
            _atomic_bytes(budget_checkpoint(run_dir, b), data)
        state["budgets"].append({"budget_s": b, "cpu_s": state["cpu_time_s"],
                                 "wall_s": state["wall_time_s"], "epoch": state["epoch"],
                                 "best_epoch": state["best_epoch"],
                                 "best_val_rmse": state["best_val_rmse"], "load_1m": _load()})
    write_rows(run_dir / BUDGETS_FILE, state["budgets"], BUDGET_FIELDS)
    return due


def _load() -> float:
    try:
        return float(os.getloadavg()[0])
    except (OSError, AttributeError):  # not on every platform
        return math.nan


def open_tensorboard(run_dir: Path, start: int):
    """A ``SummaryWriter`` on ``run_dir`` (events after epoch ``start`` of an earlier session
    are dropped, so a resumed run shows one curve), or None when TensorBoard cannot be
    imported or ``MESHBENCH_TENSORBOARD=0``."""
    if os.environ.get("MESHBENCH_TENSORBOARD", "1") == "0":
        return None
    try:
        from torch.utils.tensorboard import SummaryWriter
    except Exception:  # noqa: BLE001 - an optional extra that fails to import is absent
        return None
    return SummaryWriter(log_dir=str(run_dir), purge_step=start or None)


def log_tensorboard(board, row: dict, state: dict) -> None:
    """One epoch's scalars, by epoch: training loss, validation RMSE (m; when validated),
    best validation RMSE, learning rate, seconds per epoch and CPU seconds so far."""
    e = row["epoch"]
    values = {"train/loss": row["train_loss"], "val/rmse_m": row["val_rmse"],
              "val/best_rmse_m": row["best_val_rmse"], "train/lr": row["lr"],
              "time/epoch_s": row["epoch_time_s"], "time/cpu_s": state["cpu_time_s"]}
    for tag, v in values.items():
        if math.isfinite(v):
            board.add_scalar(tag, v, e)
    board.flush()  # live: TensorBoard reads the file while training runs


def time_left(cfg: TrainConfig, state: dict) -> float:
    """Estimated wall seconds left: the remaining epochs (or, when ``max_cpu_s`` is closer,
    the epochs the remaining CPU budget buys at the mean CPU time per epoch) times the mean
    wall time per epoch; NaN before the first epoch."""
    n = state["epoch"]
    if n == 0 or state["wall_time_s"] <= 0:
        return math.nan
    left = cfg.epochs - n
    if cfg.max_cpu_s and state["cpu_time_s"] > 0:
        per_epoch = state["cpu_time_s"] / n
        left = min(left, math.ceil(max(cfg.max_cpu_s - state["cpu_time_s"], 0) / per_epoch))
    return left * state["wall_time_s"] / n


def _duration(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def progress_text(row: dict, state: dict, cfg: TrainConfig) -> str:
    """The progress bar's postfix: epoch, loss, validation and best validation RMSE, time
    left."""
    return (f"epoch {row['epoch']} loss {row['train_loss']:.4g} val {row['val_rmse']:.4g} m "
            f"best {state['best_val_rmse']:.4g} m left {_duration(time_left(cfg, state))}")


def _restore(path: Path, model, opt, sched, gen, defaults: dict) -> dict:
    """Load ``last.pt`` into the model, optimizer, scheduler and RNGs; return the run state
    (``defaults`` for what an older checkpoint lacks: CPU time and budgets)."""
    # read onto the CPU: load_state_dict copies onto the model's (and optimizer's) device, so a
    # run goes on on another device than it was saved from
    ck = load_checkpoint(path)
    try:
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        gen.set_state(ck["generator"].cpu())  # RNG states are CPU byte tensors
        torch.set_rng_state(ck["torch_rng"].cpu())
    except (RuntimeError, ValueError, KeyError, TypeError, AttributeError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: does not fit this run's model or optimizer "
                              f"({msg[:120]})") from None
    return {k: ck[k] if k in ck else v for k, v in defaults.items()}


def _epoch(model, opt, sched, gen, train, val, cfg: TrainConfig, epoch: int, state: dict,
           progress: bool) -> tuple[dict, bool]:
    """Train and validate one epoch, update ``state``; ``(history row, improved)``."""
    t0 = time.perf_counter()
    lr = opt.param_groups[0]["lr"]
    model.start_epoch(epoch)
    n_steps = -(-model.n_training_samples(train) // cfg.batch_size)
    if cfg.max_batches:
        n_steps = min(n_steps, cfg.max_batches)
    with tqdm(total=n_steps, desc=f"epoch {epoch + 1}", unit="step", leave=False,
              disable=not progress, file=sys.stderr, dynamic_ncols=True) as steps:
        loss, skipped = train_epoch(model, opt, train, cfg, gen, cfg.max_batches or None,
                                    bar=steps)
    sched.step()
    score = loss  # selection by training loss only when there is no validation split
    if len(val):
        due = (epoch + 1) % cfg.val_every == 0 or epoch + 1 == cfg.epochs
        score = validate(model, val, cfg) if due else math.nan
    # the first validated epoch is the best so far even when its rollouts diverged (inf):
    # a run whose every validation diverges still leaves a best.pt, its inf score says so
    improved = not math.isnan(score) and (score < state["best_val_rmse"]
                                          or state["best_epoch"] < 1)
    if improved:
        state["best_val_rmse"], state["best_epoch"] = score, epoch + 1
    dt = time.perf_counter() - t0
    state["wall_time_s"] += dt
    state["epoch"] = epoch + 1
    row = {"epoch": epoch + 1, "train_loss": loss, "val_rmse": score if len(val) else math.nan,
           "best_val_rmse": state["best_val_rmse"], "lr": lr, "skipped_steps": skipped,
           "epoch_time_s": dt, "wall_time_s": state["wall_time_s"]}
    state["history"].append(row)
    return row, improved


def _atomic_bytes(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


#: What a checkpoint may hold: tensors and plain containers of plain values, exactly what
#: ``torch.load(..., weights_only=True)`` rebuilds without running code from the file.
#: ``OrderedDict`` (state dicts) and ``Counter`` (``MultiStepLR``'s milestones) keep their type.
PLAIN_SCALARS = (bool, int, float, str, type(None))
PLAIN_CONTAINERS = (collections.OrderedDict, collections.Counter, dict, list, tuple)
TORCH_VALUES = (torch.Size, torch.dtype, torch.device)


def plain(obj, where: str = "checkpoint", convert: bool = False):
    """``obj`` with numpy scalars turned into Python numbers (exactly), every container
    rebuilt as its plain type; ``TypeError`` naming ``where[key]...`` for any other object.
    ``convert=True`` (``meshbench convert-checkpoint`` only) also turns numpy arrays into
    lists, dataclasses into dicts and paths into strings."""
    if isinstance(obj, torch.Tensor):
        return obj.detach() if isinstance(obj, torch.nn.Parameter) else obj
    if type(obj) in PLAIN_SCALARS or type(obj) in TORCH_VALUES:
        return obj
    if isinstance(obj, np.generic) and isinstance(obj.item(), PLAIN_SCALARS):
        return obj.item()
    for t in PLAIN_CONTAINERS:
        if isinstance(obj, t):
            return _plain_container(obj, t, where, convert)
    if convert:
        if isinstance(obj, np.ndarray):
            return plain(obj.tolist(), where, convert)
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            return plain(dataclasses.asdict(obj), where, convert)
        if isinstance(obj, os.PathLike):
            return os.fspath(obj)
    raise TypeError(f"{where}: a {type(obj).__module__}.{type(obj).__qualname__} cannot be "
                    "stored in a checkpoint (tensors and plain containers only)")


def _plain_container(obj, kind: type, where: str, convert: bool):
    if kind in (list, tuple):
        return kind(plain(v, f"{where}[{i}]", convert) for i, v in enumerate(obj))
    out = {}
    for k, v in obj.items():
        key = plain(k, f"{where} key {k!r}", convert)
        if type(key) not in (str, int):
            raise TypeError(f"{where}: key {k!r} is not a str or int")
        out[key] = plain(v, f"{where}[{k!r}]", convert)
    if kind is dict:
        return out
    out = kind(out)
    meta = getattr(obj, "_metadata", None)  # a state dict's module versions (load_state_dict)
    if meta is not None:
        out._metadata = plain(meta, f"{where}._metadata", convert)
    return out


def save_checkpoint(path: Path, obj: dict) -> None:
    """``torch.save`` of ``plain(obj)`` to a temporary file in the same directory, fsync,
    then rename. The file loads with ``weights_only=True`` (``load_checkpoint``)."""
    buf = io.BytesIO()
    torch.save(plain(obj, str(path)), buf)
    _atomic_bytes(Path(path), buf.getvalue())


class CheckpointError(ValueError):
    """A checkpoint file is truncated, corrupt or not one of ours."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint holds objects whose unpickling could run code (an old-format or foreign
    file); it is never loaded unless the user converts it explicitly."""


CHECKPOINT_KEYS = ("model", "optimizer", "scheduler", "generator", "torch_rng", "epoch",
                   "best_val_rmse", "best_epoch", "history", "model_info")


def convert_hint(path: Path) -> str:
    return (f"if you trust where it came from, convert it with `meshbench convert-checkpoint "
            f"{path} --i-trust-this-file` (that loads it with full unpickling, once)")


def load_checkpoint(path: Path, device="cpu") -> dict:
    """``torch.load(..., weights_only=True)`` a checkpoint written by ``fit``: tensors and
    plain containers only, nothing in the file is executed. ``UnsafeCheckpointError`` for a
    file that holds other objects, ``CheckpointError`` (one line, naming the file) when it is
    truncated, corrupt or foreign."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no checkpoint here; train first (meshbench train)")
    try:
        ck = torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as e:
        if not any(w in str(e) for w in REFUSALS):
            raise CheckpointError(f"{path}: not a readable checkpoint (truncated, corrupt or "
                                  f"not written by torch.save: {_first_line(e)[:120]})") from None
        raise UnsafeCheckpointError(f"{path}: refused: it holds objects other than tensors "
                                    f"and plain containers ({_first_line(e)[:100]}); "
                                    f"{convert_hint(path)}") from None
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a bad file
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt: "
                              f"{_first_line(e)[:120]})") from None
    return check_keys(path, ck)


def check_keys(path: Path, ck) -> dict:
    """``ck`` if it is a dict with every key ``fit`` writes, else ``CheckpointError``."""
    missing = [k for k in CHECKPOINT_KEYS if k not in ck] if isinstance(ck, dict) else ["all"]
    if missing:
        raise CheckpointError(f"{path}: not a meshbench checkpoint (missing {missing})")
    return ck


#: Words of torch's restricted unpickler when it meets an object it does not rebuild (other
#: errors of it, such as an unknown opcode, mean a damaged or non-torch file).
REFUSALS = ("GLOBAL", "allowlisted", "Can only", "must be imported", "unrecognized function")


def _first_line(e: BaseException) -> str:
    """The reason in an exception's message: its first line, or for torch's weights-only
    errors the line between its generic advice and its pointer to the documentation."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    if lines and lines[0].startswith("Weights only load failed"):
        lines = [ln for ln in lines[1:] if not ln.startswith(
            ("Please file an issue", "Check the documentation"))] or lines
    return lines[0] if lines else type(e).__name__


def convert_checkpoint(path: Path) -> bool:
    """Rewrite a trusted old-format checkpoint as one ``load_checkpoint`` accepts: load it
    with full unpickling (``weights_only=False``: THIS RUNS ANY CODE THE FILE CARRIES, so only
    for a file the user vouches for), turn numpy values, dataclasses and paths into plain
    values (``plain(..., convert=True)``) and save it atomically in place. Returns False,
    writing nothing, when the file already loads safely."""
    path = Path(path)
    try:
        load_checkpoint(path)
        return False
    except UnsafeCheckpointError:
        try:
            ck = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001 - torch raises many kinds for a bad file
            raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt: "
                                  f"{_first_line(e)[:120]})") from None
        check_keys(path, ck)
    try:
        ck = plain(ck, str(path), convert=True)
    except TypeError as e:
        raise CheckpointError(f"{e}; this file cannot be converted") from None
    save_checkpoint(path, ck)
    load_checkpoint(path)  # what was written loads safely
    return True


def write_history(path: Path, rows: list) -> None:
    write_rows(path, rows, HISTORY_FIELDS)


def write_rows(path: Path, rows: list, fields: tuple) -> None:
    """A CSV of ``rows`` (dicts) with columns ``fields``, floats as ``%.6g``, atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in fields})
    _atomic_bytes(Path(path), buf.getvalue().encode())


def model_info(model: TrajectoryModel) -> dict:
    """What ``meshodenet.registry.load_model`` needs to rebuild ``model`` without the data."""
    return {"name": model.name, "config": asdict(model.config), "mesh": model.mesh.to_dict()}
