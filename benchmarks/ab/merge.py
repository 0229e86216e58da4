"""``python -m benchmarks.ab merge``: the two runs' ``ab.csv`` and the authors' published
training log in one table, ``RESULTS/NAME_ab.csv`` (``core.COLUMNS``, plain CSV: bare
``pandas.read_csv`` loads it), and a figure, ``RESULTS/figures/NAME_ab.png``.

The published log is the authors' plate training on their own data (about 155 nodes, their
ground truth; one GPU): code ``authors_published``, its epoch e written as e + 1 (epochs
finished), ``wall_s`` their seconds per epoch. Without a checkout it is the excerpt in
``docs/reference/authors_plate_log.csv`` (test loss at the epochs docs/SOURCES.md lists, "The
authors' data layout and training log"); with ``--authors-repo`` the whole
``logs/*_history.csv`` of their checkout (read as a CSV, no code is run). Its losses are in
the same units but not on the same data: compare shapes, not values.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from benchmarks.ab import core

REFERENCE_LOG = Path(__file__).resolve().parents[2] / "docs" / "reference" / "authors_plate_log.csv"
#: The published log belongs to this case only (their repository has no rod log).
PUBLISHED_CASE = "plate_cantilever"
#: Output names: ``plate_ab.csv``, ``rod_ab.csv`` (other cases: their id).
NAMES = {"plate_cantilever": "plate", "rod_falling": "rod"}
#: The ``code`` of a ``--code ours`` run with the case's ``paper`` preset as it is now.
PAPER_PRESET = "ours (paper preset)"
#: The settings in which the authors' code differs from our model (docs/AB.md, "What
#: differs"): their name in a label and whether a model's settings take the authors' one.
CONVENTIONS = {"output scale": lambda m: m["acc_scale"] == "velocity",
               "loss": lambda m: m["loss"] == "rms",
               "node features": lambda m: m["layout"] in ("authors", "authors_nodes"),
               "edge features": lambda m: m["layout"] in ("authors", "authors_edges"),
               "normaliser": lambda m: m["normalizer"] == "authors"}
CONVENTION_FIELDS = ("acc_scale", "loss", "layout", "normalizer")
#: Legend, colour and line style of the figure's curves (others: their code, further colours).
CURVES = {"authors": ("their code, our data", "C3", "-"),
          "ours, our conventions and normaliser": (None, "C0", "-"),
          "ours, our normaliser": (None, "C2", "-"),
          PAPER_PRESET: (None, "C9", "-"),
          "authors_published": ("their code, their data (published log)", "C7", "--")}


def read_run(out: Path, code: str, case: str, allow_smoke: bool) -> tuple[list, dict]:
    """The rows of run directory ``out`` (its ``ab.csv``) and its ``ab_config.json``;
    ``ABError`` unless it is a run of ``code`` on ``case`` (and, without ``allow_smoke``, on
    whole splits)."""
    out = Path(out)
    cfg_path = out / core.CONFIG_FILE
    if not cfg_path.exists():
        raise core.ABError(f"--{code} {out}: not an A/B run directory (no {core.CONFIG_FILE})")
    cfg = json.loads(cfg_path.read_text())
    if cfg.get("code") != code or cfg.get("case") != case:
        raise core.ABError(f"--{code} {out}: a run of code {cfg.get('code')!r} on "
                           f"{cfg.get('case')!r}, not {code!r} on {case!r}")
    if not allow_smoke and (cfg.get("max_train") or cfg.get("max_test")):
        raise core.ABError(f"--{code} {out}: a smoke run on part of the data (--max-train "
                           f"{cfg.get('max_train')}, --max-test {cfg.get('max_test')}); pass "
                           "--allow-smoke to merge it anyway")
    rows = core.read_csv(out)
    if not rows:
        raise core.ABError(f"--{code} {out}: no {core.CSV_FILE} yet")
    return rows, cfg


def published_rows(case: str, repo=None) -> list:
    """The authors' published log as rows (none for a case other than the plate)."""
    import pandas as pd

    if case != PUBLISHED_CASE:
        return []
    if repo is None:
        df = pd.read_csv(REFERENCE_LOG, comment="#")
    else:
        logs = sorted((Path(repo) / "logs").glob("*_history.csv"))
        if len(logs) != 1:
            raise core.ABError(f"--authors-repo {repo}: expected one logs/*_history.csv, found "
                               f"{[p.name for p in logs]}")
        df = pd.read_csv(logs[0])
    rows = []
    for r in df.to_dict("records"):
        row = core.empty_row(case, "authors_published", int(r["epoch"]) + 1)
        for src, dst in (("train_loss", "train_loss"), ("test_loss", "test_loss"),
                         ("learning_rate", "lr"), ("time_per_epoch", "wall_s")):
            if src in r:
                row[dst] = float(r[src])
        rows.append(row)
    return rows


def variant_code(cfg: dict, kind: str) -> str:
    """The ``code`` of a ``--code ours`` run in the merged table, named by how it differs from
    the case's ``paper`` preset as it is now (``kind``: the mesh kind, ``line`` or
    ``triangle``): ``ours (paper preset)`` without a difference; else ``ours, `` and what
    differs: each of the authors' conventions the run takes where the preset does not, or
    leaves where the preset takes it (``their normaliser`` / ``our normaliser``; ``our
    conventions`` for all four of output scale, loss, node and edge features), other model
    settings and the ``--set train.`` settings as ``F=V``; and ``seed S`` for a seed other than
    the authors' 42. From the resolved settings the run stored, so that a run keeps its code
    whatever ``--set`` list gave them."""
    from benchmarks.suite.runs import get_model_spec

    extra = cfg.get("extra") or {}
    model = extra.get("model") or {}
    config = get_model_spec("meshodenet").presets("paper", kind)[1]
    preset = core.jsonable(config)
    # a field the run predates resolves to its default, with which it was trained
    have = {**core.jsonable(type(config)()), **{k: v for k, v in model.items() if k in preset}}
    words = {"our": [], "their": []}
    for name, takes_theirs in CONVENTIONS.items():
        if takes_theirs(have) != takes_theirs(preset):
            words["their" if takes_theirs(have) else "our"].append(name)
    parts = []
    for whose, names in words.items():
        if set(names) >= {"output scale", "loss", "node features", "edge features"}:
            names = ["conventions"] + [n for n in names if n == "normaliser"]
        elif {"node features", "edge features"} <= set(names):
            names = [n for n in names if n != "edge features"]
            names[names.index("node features")] = "features"
        if names:
            parts.append(f"{whose} " + (names[0] if len(names) == 1 else
                                        ", ".join(names[:-1]) + " and " + names[-1]))
    parts += [f"{k}={have[k]}" for k in preset
              if k not in CONVENTION_FIELDS and have[k] != preset[k]]
    parts += [o.split(".", 1)[-1] for o in extra.get("overrides") or [] if o.startswith("train.")]
    seed = [f"seed {cfg['seed']}"] if cfg.get("seed", core.AUTHORS_SEED) != core.AUTHORS_SEED else []
    return ", ".join([PAPER_PRESET if not parts else "ours", *parts, *seed])


def mesh_kind(case: str) -> str:
    """Rods are line meshes, every other case a triangle mesh (as ``train``'s epochs)."""
    from benchmarks.suite.registry import get_case

    return "line" if get_case(case).kind == "rod" else "triangle"


def merge(case: str, authors_dir, ours_dir, results="results/paper", repo=None,
          allow_smoke: bool = False, name: str | None = None, variants=()) -> Path:
    """Write ``RESULTS/NAME_ab.csv`` and ``RESULTS/figures/NAME_ab.png``; returns the CSV.
    ``variants``: more ``--code ours`` run directories (their ``code``: ``variant_code``)."""
    from meshodenet.training.train import write_rows

    a_rows, a_cfg = read_run(authors_dir, "authors", case, allow_smoke)
    runs = [(ours_dir, *read_run(ours_dir, "ours", case, allow_smoke))]
    runs += [(d, *read_run(d, "ours", case, allow_smoke)) for d in variants]
    rows, codes, kind = [r for r in a_rows if r["code"] == "authors"], {}, mesh_kind(case)
    still = [r for r in a_rows if r["code"] == "standing_still"]
    for d, o_rows, o_cfg in runs:
        if a_cfg.get("data") != o_cfg.get("data"):
            raise core.ABError(f"the runs were fed different data: {a_cfg.get('data')} "
                               f"({authors_dir}) and {o_cfg.get('data')} ({d})")
        code = variant_code(o_cfg, kind)
        if code in codes:
            raise core.ABError(f"{d} and {codes[code]} are both {code!r}: merge one of them")
        codes[code] = d
        rows += [{**r, "code": code} for r in o_rows if r["code"] == "ours"]
        still += [r for r in o_rows if r["code"] == "standing_still"]
    if still and any(not math.isclose(r["test_loss"], still[0]["test_loss"], rel_tol=1e-5)
                     for r in still):
        raise core.ABError("the runs' standing-still test losses differ: not the same test split")
    rows += still[:1] + published_rows(case, repo)
    rows.sort(key=lambda r: (r["code"], r["epoch"]))
    results = Path(results)
    name = name or NAMES.get(case, case)
    csv_path = results / f"{name}_ab.csv"
    write_rows(csv_path, rows, core.COLUMNS)
    figure(rows, results / "figures" / f"{name}_ab.png", case, a_cfg["data"])
    return csv_path


def figure(rows: list, path: Path, case: str, data: dict) -> None:
    """Test loss (authors' units, log scale) and test RMSE (mm) against epochs finished."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_l, ax_r) = plt.subplots(1, 2, figsize=(11, 6.2))
    curves = dict(CURVES)
    more = sorted({r["code"] for r in rows} - set(CURVES) - {"standing_still"})
    free = [c for c in (f"C{i}" for i in range(10)) if c not in ("C0", "C2", "C3", "C7", "C9")]
    for i, code in enumerate(more):  # bisection runs: ours with --set settings
        curves[code] = (None, free[i % len(free)], "-")
    for code, (label, color, style) in curves.items():
        label = label or code
        sel = sorted((r for r in rows if r["code"] == code), key=lambda r: r["epoch"])
        if not sel:
            continue
        ep = [r["epoch"] for r in sel]
        marker = "." if code != "authors_published" or len(sel) < 50 else None
        ax_l.plot(ep, [r["test_loss"] for r in sel], style, color=color, marker=marker, label=label)
        if code != "authors_published":
            ax_r.plot(ep, [1e3 * r["test_rmse_m"] for r in sel], style, color=color, marker=".",
                      label=label)
    for r in rows:
        if r["code"] == "standing_still":
            ax_l.axhline(r["test_loss"], color="k", ls=":", lw=1, label="standing still")
            ax_r.axhline(1e3 * r["test_rmse_m"], color="k", ls=":", lw=1, label="standing still")
    ax_l.set(yscale="log", xlabel="epochs finished (0: untrained)",
             ylabel="test loss (authors' units), m",
             title=f"{case}: test loss")
    last = max((r["epoch"] for r in rows if r["code"] not in ("authors_published",
                                                                "standing_still")), default=0)
    if last:  # the published log runs 600 epochs: show the A/B's range
        ax_l.set_xlim(-0.5, last + 0.5)
    ax_r.set(yscale="log", xlabel="epochs finished (0: untrained)",
             ylabel="test RMSE, mm (Euclidean; frames k ≥ 1, all nodes)",
             title=f"{data['n_train']} train / {data['n_test']} test trajectories, "
                   f"{data['frames']} frames, {data['nodes']} nodes")
    for ax in (ax_l, ax_r):
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = ax_l.get_legend_handles_labels()  # one legend below both panels
    seen = dict(zip(labels, handles))
    fig.legend(seen.values(), seen.keys(), loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.05 + 0.032 * ((len(seen) + 1) // 2), 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
