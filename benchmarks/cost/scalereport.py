"""The outputs of ``meshbench bench scale`` (``benchmarks.cost.scalebench``): the tidy CSV,
the fitted exponents and crossovers (``fits.csv``), the figure and the printed tables."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from benchmarks.cost.scalecore import (
    CASES,
    COLUMNS,
    CROSSOVER_RATIO,
    GRAD_MODES,
    LEARNERS,
    METHODS,
    PROVENANCE,
    fit_power,
)


# --- outputs ---------------------------------------------------------------------------------
def write_csv(path: Path, rows: list) -> None:
    import pandas as pd

    from groundtruth import store

    recs = []
    for x in rows:
        rec = {k: x[k] for k in COLUMNS}
        rec.update({k: x.get("_prov", {}).get(k, "") for k in PROVENANCE})
        recs.append(rec)
    df = pd.DataFrame(recs, columns=COLUMNS + PROVENANCE)
    text = df.to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")


def write_table(path: Path, recs: list) -> None:
    import pandas as pd

    from groundtruth import store

    text = pd.DataFrame(recs).to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")


def _series(rows, case, method, variant, quantity):
    pts = sorted((x["nodes"], x["value"]) for x in rows
                 if x["case"] == case and x["method"] == method and
                 (variant is None or x["variant"] == variant) and x["quantity"] == quantity
                 and np.isfinite(x["value"]) and x["value"] > 0)
    return [p[0] for p in pts], [p[1] for p in pts]


def fit_table(rows) -> list:
    """Exponents (all sizes, and sizes >= 1000 nodes) of every cost and memory series, and per
    learner the crossover with the ground truth (``CROSSOVER_RATIO`` times cheaper per
    simulated second)."""
    out = []
    keys = sorted({(x["case"], x["method"], x["variant"], x["quantity"]) for x in rows
                   if x["quantity"] in ("step_cpu_s", "rollout_interval_s", "train_step_s",
                                        "peak_rss_gb", "first_solve_cpu_s",
                                        "newton_iterations_per_step", "system_build_cpu_s")})
    for case, method, variant, quantity in keys:
        n, v = _series(rows, case, method, variant, quantity)
        for label, lo in (("all", 0), (">=1e3 nodes", 1000)):
            sel = [(a, b) for a, b in zip(n, v) if a >= lo]
            if len(sel) < 2:
                continue
            p, c = fit_power(*zip(*sel))
            out.append({"case": case, "kind": "exponent", "method": method, "variant": variant,
                        "quantity": quantity, "range": label, "points": len(sel),
                        "nodes_min": sel[0][0], "nodes_max": sel[-1][0], "value": p,
                        "prefactor": c, "note": ""})
    for case in sorted({x["case"] for x in rows}):
        gn, gv = _series(rows, case, "groundtruth", "auto", "cost_per_sim_s")
        for m in LEARNERS:
            ln, lv = _series(rows, case, m, None, "cost_per_sim_s")
            if not gn or not ln:
                continue
            out.append(crossover(case, m, dict(zip(gn, gv)), dict(zip(ln, lv))))
    return out


def crossover(case, method, gt: dict, learner: dict) -> dict:
    """Nodes at which ``learner`` (CPU s per simulated second by nodes) is ``CROSSOVER_RATIO``
    times cheaper than the ground truth ``gt``: measured (log-log interpolation between the
    two sizes around it), else predicted from the exponents fitted over the largest three
    common sizes."""
    common = sorted(set(gt) & set(learner))
    rec = {"case": case, "kind": "crossover_10x", "method": method, "variant": "",
           "quantity": "nodes", "range": "", "points": len(common),
           "nodes_min": common[0] if common else np.nan,
           "nodes_max": common[-1] if common else np.nan, "value": np.nan, "prefactor": np.nan}
    if not common:
        return dict(rec, note="no common sizes")
    ratio = {n: gt[n] / learner[n] for n in common}
    ratios = "; ".join(f"{n}: {ratio[n]:.3g}" for n in common)
    if ratio[common[0]] >= CROSSOVER_RATIO:
        return dict(rec, value=common[0], range="measured",
                    note=f"already >= {CROSSOVER_RATIO:g}x at the smallest size; ratio gt/learner "
                    f"by nodes {ratios}")
    for a, b in zip(common[:-1], common[1:]):
        if ratio[a] < CROSSOVER_RATIO <= ratio[b]:
            x = math.log(a) + (math.log(CROSSOVER_RATIO) - math.log(ratio[a])) * \
                (math.log(b) - math.log(a)) / (math.log(ratio[b]) - math.log(ratio[a]))
            return dict(rec, value=math.exp(x), range="measured",
                        note=f"between {a} and {b} nodes (log-log interpolated); ratio "
                        f"gt/learner by nodes {ratios}")
    last = common[-3:]
    if len(last) < 2:
        return dict(rec, range="not reached", note=f"one size only; ratio {ratios}")
    pg, cg = fit_power(last, [gt[n] for n in last])
    pl, cl = fit_power(last, [learner[n] for n in last])
    note = (f"not reached up to {common[-1]} nodes (ratio there {ratio[common[-1]]:.3g}); "
            f"exponents over {last[0]}-{last[-1]} nodes: ground truth {pg:.2f}, learner "
            f"{pl:.2f}")
    if pg <= pl:
        return dict(rec, range="not reached", note=note + "; the learner grows as fast or "
                    "faster: never, by these exponents")
    n_star = (CROSSOVER_RATIO * cl / cg) ** (1.0 / (pg - pl))
    return dict(rec, value=n_star, range="predicted", note=note + f"; predicted at "
                f"{n_star:.3g} nodes")


LABELS = {"groundtruth": "ground truth", "solver_h": "solver at h", "meshodenet": "MeshODENet",
          "mgn": "MGN", "meshodenet_imex": "MeshODENet-IMEX", "implicit_energy": "Implicit-Energy",
          "implicit_energy_dissipation": "Implicit-Energy, learned dissipation"}


def plot(path: Path, rows, cap_gb: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from groundtruth import store

    cases = [c for c in CASES if any(x["case"] == c for x in rows)]
    fig, axes = plt.subplots(len(cases), 2, figsize=(13, 4.6 * len(cases)), squeeze=False)
    colors = dict(zip(METHODS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    styles = {"auto": "-", "banded": ":", "direct": "-", "adjoint": "--", "checkpoint": ":"}
    for ax, case in zip(axes, cases):
        for method in METHODS:
            variants = sorted({x["variant"] for x in rows if x["case"] == case and
                               x["method"] == method and x["quantity"] == "cost_per_sim_s"})
            for v in variants:
                n, val = _series(rows, case, method, v, "cost_per_sim_s")
                if n:
                    lab = LABELS[method] + (f" ({v})" if method == "groundtruth" else "")
                    ax[0].loglog(n, val, styles.get(v, "-"), marker="o" if method in (
                        "groundtruth", "solver_h") else "s", color=colors[method], label=lab)
            for v in (GRAD_MODES if method == "meshodenet" else ("default",)):
                n, val = _series(rows, case, method, v, "peak_rss_gb")
                if n:
                    ax[1].loglog(n, val, styles.get(v, "-"), marker="s", color=colors[method],
                                 label=LABELS[method] + (f" ({v})" if method == "meshodenet"
                                                         else ""))
        ax[0].set(xlabel="nodes", ylabel="CPU s per simulated second",
                  title=f"{case}: cost per simulated second")
        ax[1].axhline(cap_gb, color="k", ls=":", label=f"{cap_gb:g} GB cap")
        ax[1].set(xlabel="nodes", ylabel="peak resident memory of one training step, GB",
                  title=f"{case}: training memory")
        for a in ax:
            a.grid(True, which="both", alpha=0.3)
            a.legend(fontsize=7)
    fig.tight_layout()

    def write(f):
        fig.savefig(f, format="png", dpi=110)
    store.atomic_write(Path(path), write)
    plt.close(fig)


# --- printed tables --------------------------------------------------------------------------
def tables(rows, fits) -> list[str]:
    lines = []
    for case in sorted({x["case"] for x in rows}):
        lines.append(f"== {case}")
        rs = sorted({x["r"] for x in rows if x["case"] == case})

        def val(r, method, variant, q, case=case):
            for x in rows:
                if (x["case"], x["r"], x["method"], x["quantity"]) == (case, r, method, q) and \
                        (variant is None or x["variant"] == variant):
                    return x["value"]
            return float("nan")
        lines.append(f"{'r':>4} {'nodes':>7} {'gt auto s/step':>14} {'banded s/step':>13} "
                     f"{'ratio':>6} {'Newton/step':>11} {'band LU solve':>13} "
                     f"{'auto/LU solve':>13}")
        for r in rs:
            n = next(x["nodes"] for x in rows if x["case"] == case and x["r"] == r)
            a, b = val(r, "groundtruth", "auto", "step_cpu_s"), \
                val(r, "groundtruth", "banded", "step_cpu_s")
            lu = val(r, "groundtruth", "banded", "first_solve_cpu_s")
            lines.append(f"{r:>4} {n:>7} {a:>14.4g} {b:>13.4g} {b / a:>6.2f} "
                         f"{val(r, 'groundtruth', 'auto', 'newton_iterations_per_step'):>11.2f} "
                         f"{lu:>13.4g} {a / lu:>13.3g}")
        lines.append("CPU s per simulated second (rollout per interval / save_dt; ground truth "
                     "per step / dt):")
        head = ["groundtruth", "solver_h"] + list(LEARNERS)
        lines.append(f"{'r':>4} {'nodes':>7} " + " ".join(f"{LABELS[m][:14]:>14}" for m in head))
        for r in rs:
            n = next(x["nodes"] for x in rows if x["case"] == case and x["r"] == r)
            vals = [val(r, m, "auto" if m == "groundtruth" else None, "cost_per_sim_s")
                    for m in head]
            lines.append(f"{r:>4} {n:>7} " + " ".join(f"{v:>14.4g}" for v in vals))
        lines.append("one training step: s / peak RSS GB")
        cols = [(m, v) for m in LEARNERS for v in (GRAD_MODES if m == "meshodenet"
                                                  else ("default",))]
        lines.append(f"{'r':>4} {'nodes':>7} " + " ".join(
            f"{(m[:10] + ('/' + v[:4] if v != 'default' else '')):>16}" for m, v in cols))
        for r in rs:
            n = next(x["nodes"] for x in rows if x["case"] == case and x["r"] == r)
            cells = []
            for m, v in cols:
                s, g = val(r, m, v, "train_step_s"), val(r, m, v, "peak_rss_gb")
                cells.append(f"{s:>8.3g}/{g:<7.3g}" if np.isfinite(s) else f"{'-':>16}")
            lines.append(f"{r:>4} {n:>7} " + " ".join(cells))
    lines.append("== fitted exponents (>= 1e3 nodes) and crossovers")
    for f in fits:
        if f["kind"] == "exponent" and f["range"] == ">=1e3 nodes" and f["quantity"] in (
                "step_cpu_s", "rollout_interval_s", "train_step_s", "peak_rss_gb"):
            lines.append(f"  {f['case']} {f['method']} [{f['variant']}] {f['quantity']}: "
                         f"N^{f['value']:.2f} over {f['points']} sizes {f['nodes_min']}-"
                         f"{f['nodes_max']}")
        elif f["kind"] == "crossover_10x":
            lines.append(f"  {f['case']} {f['method']}: 10x cheaper than ground truth: "
                         f"{f['range']} {f['value']:.4g} nodes; {f['note']}")
    return lines
