"""Reading a ``meshbench bench engine`` result: its table (``report``) and its ratios to a
baseline measured earlier (``compare``); both work on the dict ``run_bench`` returns and on the
JSON ``--json`` wrote."""

from __future__ import annotations

import json

from benchmarks.cost.enginebench import GRAPHS, REGIMES, gpu_peak


def compare(new: dict, base: dict, base_impl: str | None = None) -> list[str]:
    """Lines of ratios ``new / base`` (higher is better for rates, lower for times)."""
    lines = []
    devices = [r.get("device", {}).get("device", "cpu") for r in (new, base)]
    if devices[0] != devices[1]:
        lines.append(f"devices differ: this run on {devices[0]}, the baseline on {devices[1]}")
    changed = set()  # cases whose mesh differs from the baseline's: nothing of theirs compared

    def pick(d, prefer):
        if prefer and prefer in d:
            return d[prefer]
        return next(iter(d.values()))

    for g, e in new.get("graphs", {}).items():
        b = base.get("graphs", {}).get(g)
        if not b:
            continue
        if (b.get("nodes"), b.get("directed_edges")) != (e.get("nodes"), e.get("directed_edges")):
            lines.append(f"{g:6s} not compared: the baseline's graph has {b.get('nodes')} nodes, "
                         f"{b.get('directed_edges')} directed edges, this run's {e.get('nodes')}, "
                         f"{e.get('directed_edges')} (the case changed)")
            continue
        for reg, res in e["regimes"].items():
            br = b["regimes"].get(reg)
            if not br:
                continue
            bv = _rate(pick(br, base_impl))
            for i, r in res.items():
                lines.append(f"{g:6s} {reg:7s} {i:9s} evals/s {_rate(r):10.0f} vs "
                             f"{bv:10.0f}: x{_rate(r) / bv:.2f}")
    for c, e in new.get("epochs", {}).items():
        b = base.get("epochs", {}).get(c)
        if not b:
            continue
        bn, nn = pick(b, base_impl).get("nodes"), next(iter(e.values())).get("nodes")
        if bn != nn:
            changed.add(c)
            lines.append(f"{c}: not compared (paper epoch, surrogate, MGN): the baseline's "
                         f"mesh has {bn} nodes, this run's {nn} (the case changed)")
            continue
        bv = pick(b, base_impl)["epoch_s"]
        for i, r in e.items():
            lines.append(f"paper epoch {c} {i}: {r['epoch_s']:.1f} s vs {bv:.1f} s: "
                         f"x{bv / r['epoch_s']:.2f} faster")
    for c, e in new.get("surrogate", {}).items():
        b = base.get("surrogate", {}).get(c)
        if not b or c in changed:
            continue
        bi = {k: v for k, v in b.items() if k != "solver"}
        bv = pick(bi, base_impl)
        for i, r in e.items():
            if i == "solver":
                continue
            lines.append(f"surrogate {c} {i}: single {r['single_s']:.3f} s vs "
                         f"{bv['single_s']:.3f} s (x{bv['single_s'] / r['single_s']:.2f}), "
                         f"batched {r['batched_per_trajectory_s']:.4f} vs "
                         f"{bv['batched_per_trajectory_s']:.4f} s/trajectory "
                         f"(x{bv['batched_per_trajectory_s'] / r['batched_per_trajectory_s']:.2f})")
    for c, e in new.get("mgn", {}).items():
        b = base.get("mgn", {}).get(c)
        if not b or c in changed:
            continue
        bv = pick({k: v for k, v in b.items() if isinstance(v, dict)}, base_impl)
        for i, r in e.items():
            if isinstance(r, dict):
                lines.append(f"mgn {c} {i}: step x{bv['step_s'] / r['step_s']:.2f} faster, "
                             f"rollout x{bv['rollout_s'] / r['rollout_s']:.2f} faster")
    return lines


def _rate(r: dict) -> float:
    """Evaluations per second of the best of the interleaved rounds."""
    return r.get("evals_per_s_best", r["evals_per_s"])


def report(res: dict) -> list[str]:
    """The table of a ``run_bench`` result (also of a saved JSON), rates of the best round, and
    the ratio of every implementation to the first one listed."""
    lines = [device_line(res)] if "device" in res else []
    impls = res["settings"]["impls"]
    for g in sorted(res["graphs"], key=lambda k: list(GRAPHS).index(k) if k in GRAPHS else 99):
        e = res["graphs"][g]
        lines.append(f"{g}: {e['nodes']} nodes, {e['directed_edges']} directed edges, "
                     f"{e['forward_mflop_per_eval']:.2f} MFLOP per forward evaluation; matmul "
                     f"peak on these shapes {e['matmul_peak_gflops']:.1f} GFLOP/s")
        for reg in sorted(e["regimes"], key=lambda k: REGIMES.index(k) if k in REGIMES else 9):
            rr = e["regimes"][reg]
            mult = 1 if reg == "nograd" else 3
            base = _rate(rr[impls[0]])
            for i, r in rr.items():
                gf = _rate(r) * e["forward_mflop_per_eval"] * mult / 1e3
                mem = f", peak +{r['peak_above_setup_gb'] * 1024:.0f} MB" \
                    if "peak_above_setup_gb" in r else ""
                mem += gpu_peak(r)
                ratio = f"  x{_rate(r) / base:.2f}" if i != impls[0] else ""
                lines.append(f"  {reg:7s} {i:9s} {_rate(r):8.0f} evals/s {gf:6.2f} GFLOP/s "
                             f"({100 * gf / e['matmul_peak_gflops']:.1f}% of peak){mem}{ratio}")
    for c, e in res.get("epochs", {}).items():
        for i, r in e.items():
            lines.append(f"paper epoch {c} [{i}]: {r['epoch_s']:.1f} s ({r['step_s']:.2f} s per "
                         f"step x {r['steps_per_epoch']} steps, from {r['steps_timed']} timed, "
                         f"validation excluded); peak RSS {r['peak_rss_gb']:.2f} GB"
                         + gpu_peak(r))
    for c, e in res.get("surrogate", {}).items():
        s = e["solver"]
        for i, r in e.items():
            if i != "solver":
                lines.append(f"surrogate {c} [{i}]: solver {s['per_trajectory_s']:.2f} s per "
                             f"trajectory; rollout alone {r['single_s']:.3f} s "
                             f"(x{r['speedup_single']:.1f}), batched by {r['batch']} "
                             f"{r['batched_per_trajectory_s']:.4f} s per trajectory "
                             f"(x{r['speedup_batched']:.1f})")
    if res.get("energy"):
        from benchmarks.cost.energybench import energy_line

        lines += [energy_line(c, r) for c, r in res["energy"].items()]
    for c, e in res.get("mgn", {}).items():
        for i in impls:
            if i in e:
                lines.append(f"mgn {c} [{i}]: step {e[i]['step_s'] * 1e3:.0f} ms "
                             f"({e['batch_frames']} frames), rollout {e[i]['rollout_s']:.2f} s "
                             f"({e['rollout_frames']} frames)")
    return lines


def load_json(path) -> dict:
    with open(path) as f:
        return json.load(f)


def device_line(res: dict) -> str:
    """Where a result was measured: the device and, on a GPU, its name and memory."""
    d = res["device"]
    if d.get("type") != "cuda":
        return f"device: {d['device']} ({d.get('name', '?')})"
    return (f"device: {d['device']} ({d['name']}, {d['total_memory_gb']:.0f} GB, CUDA "
            f"{d.get('cuda')}, torch {d.get('torch')})")

