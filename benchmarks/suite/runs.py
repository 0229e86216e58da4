"""Glue between the store and the torch side: training runs and rollouts of learned models.

A run directory holds ``config.json`` (the resolved configuration: case, model, preset,
training and model settings, seeds, the validation split), ``sessions.json`` (provenance of
every invocation: versions, git SHA, device, threads, wall time), ``last.pt``, ``best.pt``,
``history.csv`` and, once training ends, ``test_metrics.json``.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform
import time
import typing
from pathlib import Path

import numpy as np

from benchmarks.suite.registry import get_case
from groundtruth import store

CONFIG_FILE = "config.json"
#: a suite run's rollout of its best checkpoint on the test split (``store.save_npz`` arrays)
PRED_FILE = "test_rollout.npz"
#: a suite run's record (written last: the run is finished) and its tidy test metrics
RECORD_FILE = "record.json"
METRICS_FILE = "test_metrics.csv"


def suite_models() -> dict:
    """The torch side's ``MODELS`` with the suite's own models registered (``solver_h``,
    ``benchmarks.suite.solver_row``). The benchmarks side looks models up here
    (``get_model_spec``), so that every process has them, workers included, while this module
    loads without torch."""
    from benchmarks.suite import solver_row  # noqa: F401 - registers solver_h on import
    from meshodenet.registry import MODELS

    return MODELS


def get_model_spec(model_id: str):
    """``meshodenet.registry.get_model_spec`` of ``suite_models()``."""
    suite_models()
    from meshodenet.registry import get_model_spec as spec

    return spec(model_id)


def trainable(model_id: str) -> bool:
    """False for a registered model with nothing to learn (``trainable = False``: the solver
    row), which the runner records without training."""
    spec = suite_models().get(model_id)
    return spec is None or getattr(spec.model_cls, "trainable", True)


#: What ``--device`` accepts (``cuda:K`` names one GPU of several).
DEVICES = ("auto", "cpu", "cuda", "cuda:K")


def check_device_name(name: str) -> str:
    """``name`` if it is one of ``DEVICES`` (without importing torch), else a one-line
    ``ValueError``."""
    kind, sep, index = str(name).partition(":")
    ok = name == "auto" or (kind in ("cpu", "cuda") and not sep) or (kind == "cuda" and
                                                                     index.isdigit())
    if not ok:
        raise ValueError(f"--device {name!r} is not a device; valid: {', '.join(DEVICES)}")
    return name


def pick_device(name: str = "auto"):
    """The ``torch.device`` of ``--device name``: ``auto`` is the first CUDA device when torch
    sees one, else the CPU; ``cpu``; ``cuda`` or ``cuda:K``. ``ValueError`` (one line) for
    another name, or for CUDA where torch sees no such device."""
    import torch

    name = check_device_name(str(name))
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    kind, _, index = name.partition(":")
    if kind == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name!r} but torch sees no CUDA device (torch "
                         f"{torch.__version__}, CUDA build {torch.version.cuda or 'none'}); "
                         "use --device cpu, or install a CUDA build of torch (docs/GPU.md)")
    if index and int(index) >= torch.cuda.device_count():
        raise ValueError(f"--device {name!r} but torch sees {torch.cuda.device_count()} CUDA "
                         f"device(s) (cuda:0 to cuda:{torch.cuda.device_count() - 1})")
    return torch.device(name)


def _parse_value(text: str, current, annotation: str):
    if isinstance(current, bool) or annotation == "bool":
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"expected true/false, got {text!r}")
    if isinstance(current, tuple) or annotation.startswith("tuple"):
        return tuple(int(x) for x in text.split(",") if x.strip())
    if text.lower() == "none":
        return None
    if isinstance(current, int) or annotation == "int":
        return int(text)
    if isinstance(current, float) or "float" in annotation:
        return float(text)
    return text


def apply_overrides(train_cfg, model_cfg, overrides: typing.Sequence[str]):
    """Apply ``train.FIELD=VALUE`` / ``model.FIELD=VALUE`` strings with ``dataclasses.replace``."""
    changes = {"train": {}, "model": {}}
    targets = {"train": train_cfg, "model": model_cfg}
    for item in overrides:
        key, sep, text = item.partition("=")
        group, _, name = key.partition(".")
        if not sep or group not in targets or not name:
            raise ValueError(f"--set expects train.FIELD=VALUE or model.FIELD=VALUE, got {item!r}")
        flds = {f.name: f for f in dataclasses.fields(targets[group])}
        if name not in flds:
            raise ValueError(f"--set {item!r}: {type(targets[group]).__name__} has no field "
                             f"{name!r}; valid: {', '.join(sorted(flds))}")
        try:
            changes[group][name] = _parse_value(text, getattr(targets[group], name),
                                                str(flds[name].type))
        except ValueError as e:
            raise ValueError(f"--set {item!r}: {e}") from None
    return (dataclasses.replace(train_cfg, **changes["train"]),
            dataclasses.replace(model_cfg, **changes["model"]))


def session_info(device, started: float) -> dict:
    """A training session's provenance (``sessions.json``): when (``started``, a Unix time),
    library versions, git commit, device, threads and CPU count."""
    import torch

    return {"started": datetime.datetime.fromtimestamp(started, datetime.timezone.utc)
            .isoformat(timespec="seconds"), "versions": store.library_versions(),
            "git_sha": store.git_sha(), "device": str(device),
            "threads": torch.get_num_threads(), "cpu_count": os.cpu_count()}


def config_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    """``"key.path: old -> new"`` for every leaf where the nested dicts ``a`` and ``b`` differ,
    sorted."""
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_diff(va, vb, f"{prefix}{k}.")
        elif va != vb:
            out.append(f"{prefix}{k}: {va!r} -> {vb!r}")
    return out


#: What a run stored before a setting existed used, where that is not the setting's default:
#: the validation split was a seeded random draw until ``train.val_split`` (stratified by
#: modulus by default) was introduced.
LEGACY_DEFAULTS = {"train.val_split": "random"}


def with_defaults(config: dict) -> dict:
    """``config`` (a stored ``config.json``) with the training and model settings it lacks set
    to their defaults: a run stored before a setting existed ran with that setting's default,
    so it compares equal to today's configuration with the default (and differs from one that
    sets another value), except where ``LEGACY_DEFAULTS`` says what such a run used instead
    (a setting whose default changed when it was introduced). Unknown models and non-dict
    configs are returned as they are."""
    from meshodenet.training.train import TrainConfig

    models = suite_models()
    if not isinstance(config, dict) or config.get("model") not in models:
        return config
    out = dict(config)
    for key, cls in (("train", TrainConfig), ("model_config", models[config["model"]].config_cls)):
        if not isinstance(config.get(key), dict) or not dataclasses.is_dataclass(cls):
            continue
        filled = dict(config[key])
        for f in dataclasses.fields(cls):
            if f.name not in filled and f.default is not dataclasses.MISSING:
                filled[f.name] = json.loads(json.dumps(
                    LEGACY_DEFAULTS.get(f"{key}.{f.name}", f.default)))
        out[key] = filled
    return out


def resolve_run(case_id: str, model_id: str, preset: str, *, data_dir=None, overrides=(),
                epochs: int | None = None) -> dict:
    """Everything a training run is determined by, resolved without training: the case's
    training arrays, the model spec, the preset's configs after ``overrides``, the validation
    split, and ``config`` (the JSON-ready dict written to ``config.json``)."""
    from meshodenet.mesh.data import Mesh, validation_split

    case = get_case(case_id)
    spec = get_model_spec(model_id)
    arrays = store.load_split(case, "train", data_dir)
    mesh = Mesh.from_arrays(arrays, f"{case_id}/train.npz")
    train_cfg, model_cfg = spec.presets(preset, mesh.kind)
    train_cfg, model_cfg = apply_overrides(train_cfg, model_cfg, overrides)
    if epochs is not None:
        train_cfg = dataclasses.replace(train_cfg, epochs=epochs)
    n = arrays["pos"].shape[0]
    tr_idx, val_idx = validation_split(arrays["youngs"], train_cfg.val_fraction,
                                       train_cfg.val_split, train_cfg.split_seed)
    config = {
        "case": case_id, "case_hash": str(arrays["case_hash"]), "model": model_id,
        "preset": preset, "overrides": list(overrides),
        "train": dataclasses.asdict(train_cfg), "model_config": dataclasses.asdict(model_cfg),
        "seeds": {"seed": train_cfg.seed, "split_seed": train_cfg.split_seed},
        "split": {"n_file": n, "train_idx": tr_idx.tolist(), "val_idx": val_idx.tolist()},
    }
    config = json.loads(json.dumps(config))  # tuples -> lists, as read back from disk
    return {"case": case, "spec": spec, "arrays": arrays, "mesh": mesh, "train_cfg": train_cfg,
            "model_cfg": model_cfg, "tr_idx": tr_idx, "val_idx": val_idx, "config": config}


#: Differences from the stored configuration that ``meshbench train --resume`` continues
#: through: more epochs, another CPU budget or other budget checkpoints (they decide when
#: training stops and which best-so-far copies it keeps, not what it computes), and the
#: overrides that set them.
RESUME_IGNORES = ("train.epochs:", "train.max_cpu_s:", "train.budgets_s:", "overrides:")


@dataclasses.dataclass(frozen=True)
class RunDecision:
    """What to do with a run directory for a resolved configuration, decided once.

    ``action``: ``reuse`` (a finished run of this configuration: ``stored`` is its record),
    ``resume`` (a run of this configuration with a loadable ``last.pt``: ``stored`` is its
    configuration), ``retrain`` (a stored run that cannot continue: ``why``, ``problem``) or
    ``fresh`` (nothing stored). ``problem``: ``no_checkpoint``, ``bad_config``,
    ``config_changed`` (``changes`` lists them) or ``bad_checkpoint``."""

    action: str
    why: str = ""
    problem: str | None = None
    changes: tuple = ()
    stored: dict | None = None


def _changes(old: dict, new: dict, ignore: tuple) -> list[str]:
    """The differences of ``new`` from ``old`` not under the ``ignore`` prefixes."""
    if not ignore:
        return [] if old == new else (config_diff(old, new) or ["the configuration"])
    return [d for d in config_diff(old, new) if not d.startswith(ignore)]


def _finished_record(out: Path, config: dict, finished: tuple, ids: dict) -> dict | None:
    """The record (``finished[0]``, JSON with the run's ``config``) of a finished run of
    ``config`` whose outputs ``finished[1:]`` are all present and whose ``ids`` (run, case,
    model, ...) are the expected ones, else None."""
    rec_path = out / finished[0]
    if not rec_path.exists():
        return None
    rec = json.loads(rec_path.read_text())
    done = all((out / name).exists() for name in finished[1:])
    same_ids = all(rec.get(k) == v for k, v in ids.items())
    return rec if done and same_ids and with_defaults(rec.get("config")) == config else None


def decide_run(out, config: dict, *, finished: tuple = (), ids: dict | None = None,
               ignore: tuple = ()) -> RunDecision:
    """Decide what to do with run directory ``out`` for the resolved ``config``: reuse it
    when ``finished`` (a record file, then the outputs of a finished run) says it is done,
    resume it when its ``config.json`` matches (up to the ``ignore`` prefixes) and its
    ``last.pt`` loads, else retrain it (or start fresh when nothing is stored). A ``last.pt``
    in the old unsafe format raises ``UnsafeCheckpointError``: it is kept for the user to
    convert, never retrained over."""
    from meshodenet.training.train import CheckpointError, UnsafeCheckpointError, load_checkpoint

    out = Path(out)
    rec = _finished_record(out, config, finished, ids or {}) if finished else None
    if rec is not None:
        return RunDecision("reuse", stored=rec)
    cfg_path, last = out / CONFIG_FILE, out / "last.pt"
    if not cfg_path.exists() and not last.exists():
        return RunDecision("fresh", problem="no_checkpoint")
    try:
        old = with_defaults(json.loads(cfg_path.read_text()))
    except (OSError, json.JSONDecodeError) as e:
        return RunDecision("retrain", "config.json is unreadable", "bad_config", (str(e),))
    changes = tuple(_changes(old, config, ignore))
    if changes:
        return RunDecision("retrain", "configuration changed since the stored run",
                           "config_changed", changes, old)
    if not last.exists():
        return RunDecision("retrain", "no epoch had finished (no last.pt)", "no_checkpoint",
                           stored=old)
    try:
        load_checkpoint(last)
    except UnsafeCheckpointError:
        raise
    except CheckpointError as e:
        return RunDecision("retrain", str(e), "bad_checkpoint", stored=old)
    return RunDecision("resume", stored=old)


def _check_request(d: RunDecision, out: Path, resume: bool) -> None:
    """``meshbench train --resume``'s errors for a run that cannot continue."""
    again = f"start it again with `rm -r {out}` and the same command without --resume"
    if not resume:
        return
    if d.problem == "no_checkpoint":
        raise FileNotFoundError(f"--resume: {out / 'last.pt'} does not exist; run without "
                                "--resume to start this run")
    if d.problem == "bad_checkpoint":
        from meshodenet.training.train import CheckpointError

        raise CheckpointError(f"--resume: {d.why}; this run cannot continue: {again}")
    if d.problem == "bad_config":
        raise ValueError(f"--resume: {out / CONFIG_FILE} is unreadable ({d.changes[0]}); "
                         f"start the run again with `rm -r {out}` and the same command without "
                         "--resume")
    if d.problem == "config_changed":
        raise ValueError(f"--resume: the configuration differs from {out / CONFIG_FILE}: "
                         + "; ".join(d.changes) + ". Resume with the same settings or choose "
                         "another --out")


def train_run(case_id: str, model_id: str, preset: str, out, *, resume: bool = False,
              data_dir=None, overrides=(), epochs: int | None = None, device: str = "auto",
              progress: bool = True, on_epoch_end=None, evaluate: bool = True) -> dict:
    """``meshbench train``: train ``model_id`` on ``case_id`` into ``out`` (continue it with
    ``resume``); returns the summary it prints."""
    from meshodenet.training.train import UnsafeCheckpointError

    t_start = time.time()
    out = Path(out)
    r = resolve_run(case_id, model_id, preset, data_dir=data_dir, overrides=overrides,
                    epochs=epochs)
    if evaluate and (store.data_dir(data_dir) / r["case"].id / "test.npz").exists():
        store.load_split(r["case"], "test", data_dir)  # every input checked before epoch 1
    try:
        decision = decide_run(out, r["config"], ignore=RESUME_IGNORES) if resume else None
    except UnsafeCheckpointError as e:  # its message says how to convert a trusted one
        raise UnsafeCheckpointError(f"--resume: {e}") from None
    _check_request(decision, out, resume)
    return train_resolved(r, out, decision, data_dir=data_dir, device=device,
                          progress=progress, on_epoch_end=on_epoch_end, evaluate=evaluate,
                          t_start=t_start)


def train_resolved(r: dict, out, decision: RunDecision | None = None, *, data_dir=None,
                   device: str = "auto", progress: bool = True, on_epoch_end=None,
                   evaluate: bool = True, t_start: float | None = None) -> dict:
    """Train the resolved run ``r`` (``resolve_run``) into ``out``: continue it when
    ``decision`` (``decide_run``) is ``resume``, else start it; returns the summary.
    ``r["arrays"]`` (the training file's float64 arrays) is taken out of ``r``: training
    keeps only the float32 tensors of its training and validation trajectories."""
    import torch

    from meshodenet.mesh.data import Trajectories
    from meshodenet.training.train import fit

    t_start = time.time() if t_start is None else t_start
    out = Path(out)
    case, spec, mesh = r["case"], r["spec"], r["mesh"]
    config = dict(r["config"])
    train_cfg, model_cfg, tr_idx, val_idx = r["train_cfg"], r["model_cfg"], r["tr_idx"], r["val_idx"]
    cfg_path = out / CONFIG_FILE
    test_file = store.data_dir(data_dir) / case.id / "test.npz"
    resume = decision is not None and decision.action == "resume"
    if resume:
        config["overrides"] = decision.stored["overrides"]
    elif (out / "last.pt").exists():
        raise ValueError(f"{out} already holds a run; pass --resume to continue it or choose "
                         "another --out")
    from meshodenet.training.train import broadcast_parameters, distributed_rank

    lead = distributed_rank()[0] == 0  # torchrun: rank 0 writes, every rank trains
    dev = pick_device(device)
    if lead:
        store.save_json(cfg_path, config)

    full = Trajectories.from_arrays(r.pop("arrays"), device=dev)
    train, val = full.subset(torch.as_tensor(tr_idx)), full.subset(torch.as_tensor(val_idx))
    del full  # the subsets are copies: the whole file's tensors need not stay for training
    torch.manual_seed(train_cfg.seed)
    model = on_patches(spec.build(mesh, model_cfg, train).to(dev), train_cfg)
    broadcast_parameters(model)
    sessions_path = out / "sessions.json"
    sessions = json.loads(sessions_path.read_text()) if sessions_path.exists() else []
    session = session_info(dev, t_start)
    session["resumed"] = resume
    history = out / "history.csv"
    before = history.stat().st_mtime_ns if history.exists() else None
    try:
        if model.trainable:
            result = fit(model, train, val, train_cfg, out, resume=resume, progress=progress,
                         on_epoch_end=on_epoch_end)
        else:  # nothing to learn (the solver row): its checkpoints only
            from benchmarks.suite.solver_row import save_untrained

            result = save_untrained(model, out)
        session["epochs_run"] = result.epochs_run
        if not lead:
            return {"run": str(out), "rank": distributed_rank()[0]}
    except BaseException as e:
        if not lead:
            raise
        session["ended_by"] = type(e).__name__
        # a session is recorded only if it trained at least one epoch (history.csv moved):
        # a failure before the first epoch left nothing behind and is not a session
        if not (history.exists() and history.stat().st_mtime_ns != before):
            from meshodenet.training.train import CheckpointError

            if resume and isinstance(e, CheckpointError):
                raise CheckpointError(f"--resume: {e}; this run cannot continue: start it "
                                      f"again with `rm -r {out}` and the same command "
                                      "without --resume") from None
            raise
        session["wall_time_s"] = round(time.time() - t_start, 2)
        store.save_json(sessions_path, sessions + [session])
        raise
    session["wall_time_s"] = round(time.time() - t_start, 2)
    if distributed_rank()[1] > 1:
        session["world_size"] = distributed_rank()[1]
    store.save_json(sessions_path, sessions + [session])
    summary = {"run": str(out), "best_epoch": result.best_epoch,
               "best_val_rmse_m": result.best_val_rmse,
               "train_wall_time_s": round(result.wall_time_s, 2)}
    if evaluate and test_file.exists() and (out / "best.pt").exists():
        metrics = evaluate_run(out, "test", data_dir, device=device)
        summary.update(test_rmse_m=metrics["rmse_m"],
                       test_no_motion_rmse_m=metrics["no_motion_rmse_m"])
        store.save_json(out / "test_metrics.json", metrics)
    return summary


def on_patches(model, train_cfg):
    """``model`` trained on patches of ``train_cfg.patch_nodes`` nodes (counted as
    ``train_cfg.patch_budget`` says; ``meshodenet.subdomain.PatchTraining``: the model's own
    checkpoints), or ``model`` itself when it is 0."""
    if not train_cfg.patch_nodes:
        return model
    from meshodenet.subdomain import PatchTraining

    return PatchTraining(model, train_cfg.patch_nodes, budget=train_cfg.patch_budget)


def load_run_model(path: Path, device="cpu", fix: str = ""):
    """``meshodenet.registry.load_model(path)`` with one-line ``CheckpointError``s that name the
    file and end with ``fix`` (what to do); an ``UnsafeCheckpointError`` passes unchanged (its
    message says how to convert a trusted file)."""
    from meshodenet.registry import load_model
    from meshodenet.training.train import CheckpointError, UnsafeCheckpointError

    suite_models()  # the checkpoint may be of a model registered by the suite
    tail = f"; {fix}" if fix else ""
    try:
        return load_model(path, device)
    except UnsafeCheckpointError:
        raise
    except CheckpointError as e:
        raise CheckpointError(f"{e}{tail}") from None
    except (RuntimeError, KeyError, TypeError, ValueError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: not a checkpoint of a registered model "
                              f"({msg[:120]}){tail}") from None


def _load_run(run_dir: Path, checkpoint: str, device: str):
    run_dir = Path(run_dir)
    cfg_path = run_dir / CONFIG_FILE
    if not cfg_path.exists():
        raise FileNotFoundError(f"{cfg_path}: not a training run directory (meshbench train "
                                "--out DIR creates one)")
    if checkpoint not in ("best", "last"):
        raise ValueError(f"--checkpoint must be 'best' or 'last', got {checkpoint!r}")
    try:
        config = json.loads(cfg_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{cfg_path}: unreadable ({e}); retrain the run (meshbench train "
                         "--out DIR) or restore the file") from None
    model, ck = load_run_model(run_dir / f"{checkpoint}.pt", pick_device(device),
                               f"retrain the run (meshbench train --out {run_dir} ...) or "
                               "restore the file")
    if hasattr(model, "on_newton_failure"):  # evaluation: a failed implicit solve is a
        model.on_newton_failure = "nan"      # diverged rollout (NaN), not a crash
    return config, model, ck


def rollout_arrays(run_dir, split: str = "test", data_dir=None, checkpoint: str = "best",
                   device: str = "auto", data_file=None, arrays=None) -> tuple[dict, dict]:
    """Roll the run's model out over a split (or ``data_file``); returns the store-format
    arrays of the prediction and metrics (position RMSE and the no-motion baseline, m).
    ``arrays``: the split's arrays when the caller has already loaded them. Data on another
    mesh than the run's (``data_file`` of another case or resolution, e.g. ``CASE@r2``) are
    rolled out by the model on that mesh (``TrajectoryModel.on_mesh``: the same kind of mesh
    only; metrics then name both meshes under ``transfer``)."""
    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.metrics import no_motion, position_rmse, rmse_per_frame

    config, model, ck = _load_run(Path(run_dir), checkpoint, device)
    case = get_case(config["case"])
    if data_file is not None:  # ``arrays``: its arrays, when the caller has loaded them
        arrays = store.load_npz(Path(data_file)) if arrays is None else arrays
        name = str(data_file)
    else:
        name = f"{case.id}/{split}.npz"
        arrays = store.load_split(case, split, data_dir) if arrays is None else arrays
    trained = model
    model = model.on_mesh(Mesh.from_arrays(arrays, name), name)
    data = Trajectories.from_arrays(arrays, device=model.device, name=name)
    t0 = time.perf_counter()
    pos, vel = model.rollout_all(data, 16)
    wall = time.perf_counter() - t0
    true = data.pos
    per_frame = rmse_per_frame(pos, true)
    metrics = {"model": model.name, "case": case.id, "split": split if data_file is None
               else str(data_file), "checkpoint": checkpoint, "epoch": ck["epoch"],
               "rmse_definition": "sqrt(mean over trajectories, frames k>=1, nodes of "
                                  "|x_pred - x_true|^2), m",
               "rmse_m": position_rmse(pos, true),
               "no_motion_rmse_m": position_rmse(no_motion(true), true),
               "final_frame_rmse_m": float(per_frame[-1]), "rollout_wall_time_s": round(wall, 3),
               "n_trajectories": len(data)}
    if model is not trained:
        metrics["transfer"] = {"trained_on": trained.mesh.describe(),
                               "rolled_out_on": model.mesh.describe()}
    out = dict(arrays)
    out["pos"] = pos.detach().double().cpu().numpy()
    out["vel"] = vel.detach().double().cpu().numpy()
    out["model"] = np.array(model.name)
    return out, metrics


def evaluate_run(run_dir, split="test", data_dir=None, checkpoint="best", device="auto") -> dict:
    return rollout_arrays(run_dir, split, data_dir, checkpoint, device)[1]


def rollout_run(run_dir, out, split="test", data_dir=None, checkpoint="best",
                device="auto", data_file=None) -> dict:
    """Write the predicted trajectories of a split to ``out`` in the store's npz format."""
    out = Path(out)
    if out.suffix != ".npz":
        raise ValueError(f"--out must end in .npz, got {str(out)!r}")
    arrays, metrics = rollout_arrays(run_dir, split, data_dir, checkpoint, device, data_file)
    store.save_npz(out, arrays)
    return metrics


def load_test_rollout(run_dir) -> np.ndarray:
    """Predicted positions ``(B, T, N, 3)`` of a suite run's stored test rollout
    (``PRED_FILE``), loaded without unpickling."""
    with np.load(Path(run_dir) / PRED_FILE, allow_pickle=False) as z:
        return z["pos"]


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else the platform's processor."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
