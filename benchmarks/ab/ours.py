"""``--code ours``: our MeshODENet with its ``paper`` preset (``meshodenet.gnn.meshodenet``:
hidden 128, one layer, rk4 at the sampling interval, whole rollouts, Adam 1e-4, weight decay
5e-4, one trajectory per step), trained by ``meshodenet.training.train.fit`` on the same frames and
trajectories as the authors' code, with an ``on_epoch_end`` hook that rolls the current model
out on the test split and writes the epoch's row. The test split is only monitored: ``fit``
keeps selecting ``best.pt`` on its validation split (the preset's 10 % of the training file,
stratified by modulus), so ours trains on 90 % of the trajectories the authors' code trains on.

Resuming is ``fit``'s (``last.pt``: model, optimizer, scheduler, RNG states). The hook runs after
``last.pt`` is written; a run killed between the two lacks its last row, which the next session
recomputes from ``last.pt`` before training on (its CPU seconds are then unknown: NaN).

Training loss in the authors' units: ``fit`` minimises the mean square error over frames
``k >= 1`` and nodes divided by that of standing still on the training split (``s``); for a
whole trajectory of ``T`` frames and ``N`` nodes the authors' loss is
``sqrt(loss * s * N (T - 1) / (3 T))`` (frame 0's error is zero); with ``--set model.loss=rms``
(the root of that ratio) the same with ``loss**2``. Each step's value is recorded (exact for one
trajectory per step, the ``paper`` preset) and the row holds their mean.

``--set`` also runs the bisection steps of docs/AB.md ("What differs"): ``model.acc_scale``,
``model.loss`` and ``model.layout`` switch our model to the authors' code's conventions one by
one (the ``paper`` preset takes all three on triangle meshes: ``meshodenet.gnn.meshodenet.
PAPER``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from benchmarks.ab import core

EXTRA_KEY = "ab_train_losses"


class Recorder:
    """Wraps the model's ``training_loss`` and ``start_epoch`` to record each step's loss in
    the authors' units (into ``extra``, which ``fit`` stores in every checkpoint) and the
    epoch's clock."""

    def __init__(self, model):
        self.model, self.extra, self.clock = model, {EXTRA_KEY: []}, core.Clock()
        loss, start = model.training_loss, model.start_epoch

        def training_loss(data, samples, generator=None):
            value = loss(data, samples, generator)
            v = float(value.detach())
            if math.isfinite(v):
                self.extra[EXTRA_KEY].append(authors_units(model, data, v))
            return value

        def start_epoch(epoch):
            self.extra[EXTRA_KEY], self.clock = [], core.Clock()
            start(epoch)

        model.training_loss, model.start_epoch = training_loss, start_epoch

    def train_loss(self, extra: dict | None = None) -> float:
        steps = (self.extra if extra is None else extra).get(EXTRA_KEY, [])
        return sum(steps) / len(steps) if steps else math.nan


def authors_units(model, data, loss: float) -> float:
    """A whole-trajectory training loss of ``fit`` in the authors' units (module docstring)."""
    T, N = data.n_frames, data.pos.shape[2]
    scale = model._loss_scale(data, model.horizon(T - 1))
    if model.config.loss == "rms":  # one whole trajectory per step: the root of the mse one
        loss = loss * loss
    return math.sqrt(loss * scale * N * (T - 1) / (3 * T))


def configs(setup: core.Setup, kind: str, overrides=()):
    """The ``paper`` preset for a mesh of ``kind`` with ``overrides`` (``train.F=V`` /
    ``model.F=V``), ``setup.epochs`` and ``setup.seed``; ``ABError`` for a setting whose
    training loss has no authors'-units reading (windows, frame or release weights)."""
    from benchmarks.suite.runs import apply_overrides, get_model_spec

    spec = get_model_spec("meshodenet")
    train_cfg, model_cfg = spec.presets("paper", kind)
    try:
        train_cfg, model_cfg = apply_overrides(train_cfg, model_cfg, overrides)
        train_cfg = dataclasses.replace(train_cfg, epochs=setup.epochs, seed=setup.seed)
    except ValueError as e:
        raise core.ABError(str(e)) from None
    for name in ("shooting", "frame_weight", "release_weight"):
        if getattr(model_cfg, name):
            raise core.ABError(f"--set model.{name}={getattr(model_cfg, name)!r}: the A/B reads "
                               "the training loss in the authors' units, which needs the paper's "
                               "whole-trajectory loss (leave it 0)")
    return spec, train_cfg, model_cfg


def evaluate(model, test, true, case: str, epoch: int, batch: int) -> dict:
    """The row of ``epoch`` with the test metrics of the current model."""
    clock = core.Clock()
    pred, _ = model.rollout_all(test, batch)
    row = core.empty_row(case, "ours", epoch)
    row.update(core.test_metrics(pred, true))
    row["test_wall_s"], row["test_cpu_s"] = clock.seconds()
    row["peak_rss_mb"] = core.peak_rss_mb()
    return row


def run(setup: core.Setup, out: Path, data_dir=None, overrides=(), progress: bool = True,
        device="cpu") -> list:
    """Train ``paper`` MeshODENet on ``setup.case`` into ``out`` up to ``setup.epochs``
    (continuing ``out/last.pt`` when it is there) on ``device`` (``cpu``, ``cuda``,
    ``cuda:K``: a run may go on on another device than it started on; ``sessions.json`` says
    which ran which epochs); returns the rows of ``ab.csv``."""
    import torch

    from benchmarks.suite.runs import pick_device
    from meshodenet.mesh.data import Mesh, Trajectories, validation_split
    from meshodenet.training.train import fit

    dev = pick_device(device)
    torch.set_num_threads(setup.threads)
    tr = core.load_arrays(setup.case, "train", data_dir, setup.max_train, setup.frames, "--max-train")
    te = core.load_arrays(setup.case, "test", data_dir, setup.max_test, setup.frames, "--max-test")
    mesh = Mesh.from_arrays(tr, f"{setup.case}/train.npz")
    spec, train_cfg, model_cfg = configs(setup, mesh.kind, overrides)
    tr_idx, val_idx = validation_split(tr["youngs"], train_cfg.val_fraction, train_cfg.val_split,
                                       train_cfg.split_seed)
    setup = setup.with_extra(preset="paper", overrides=list(overrides),
                             train=core.jsonable(train_cfg, "epochs"), model=core.jsonable(model_cfg),
                             train_idx=tr_idx.tolist(), val_idx=val_idx.tolist())
    core.check_resume(out, setup, core.data_id(tr, te),  # fields a stored run predates
                      {"train": core.jsonable(type(train_cfg)(), "epochs"),
                       "model": core.jsonable(type(model_cfg)())})
    full = Trajectories.from_arrays(tr, device=dev, name=f"{setup.case}/train.npz")
    train, val = full.subset(torch.as_tensor(tr_idx)), full.subset(torch.as_tensor(val_idx))
    test = Trajectories.from_arrays(te, device=dev, name=f"{setup.case}/test.npz")
    torch.manual_seed(train_cfg.seed)
    model = spec.build(mesh, model_cfg, train).to(dev)
    rec = Recorder(model)
    rows, resume = _start(model, rec, out, setup, test, train_cfg.eval_batch_size)
    core.write_csv(out, rows)
    core.record_session(out, max(r["epoch"] for r in rows if r["code"] == "ours"), dev)

    def on_epoch_end(epoch: int, fit_row: dict) -> None:
        wall, cpu = rec.clock.seconds()
        row = evaluate(model, test, test.pos, setup.case, epoch, train_cfg.eval_batch_size)
        row.update(train_loss=rec.train_loss(), val_rmse_m=fit_row["val_rmse"], lr=fit_row["lr"],
                   wall_s=wall, cpu_s=cpu)
        rows.append(row)
        core.write_csv(out, rows)
        print(core.progress_line(row, setup.epochs, mesh.n_nodes), flush=True)

    fit(model, train, val, train_cfg, out, resume=resume, progress=progress,
        on_epoch_end=on_epoch_end, extra_state=rec.extra)
    return rows


def _start(model, rec: Recorder, out: Path, setup: core.Setup, test, batch: int):
    """``(rows, resume)``: the rows so far (a fresh run: standing still and the untrained
    model) and whether ``fit`` continues ``last.pt``; the row of a finished epoch whose hook
    did not run is recomputed from ``last.pt``."""
    from meshodenet.training.train import CheckpointError, load_checkpoint

    rows = [r for r in core.read_csv(out) if r["code"] in ("ours", "standing_still")]
    done = max((r["epoch"] for r in rows if r["code"] == "ours"), default=None)
    last = out / "last.pt"
    if not last.exists():
        if done:
            raise core.ABError(f"{out / core.CSV_FILE} has epochs up to {done} but {last} is "
                               "missing; choose another --out")
        if done is None:
            rows = [core.standing_still_row(setup.case, test.pos),
                    evaluate(model, test, test.pos, setup.case, 0, batch)]
        return rows, False
    try:
        ck = load_checkpoint(last)
    except CheckpointError as e:
        raise core.ABError(f"{e}; choose another --out") from None
    if done is None or ck["epoch"] not in (done, done + 1):
        raise core.ABError(f"{last} is at epoch {ck['epoch']} but {out / core.CSV_FILE} at "
                           f"{done}; choose another --out")
    if ck["epoch"] == done + 1:
        model.load_state_dict(ck["model"])
        row = evaluate(model, test, test.pos, setup.case, ck["epoch"], batch)
        hist = ck["history"][-1]
        row.update(train_loss=rec.train_loss(ck.get("extra") or {}), val_rmse_m=hist["val_rmse"],
                   lr=hist["lr"], wall_s=hist["epoch_time_s"])
        rows.append(row)
    return rows, True

