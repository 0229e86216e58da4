"""Animated rollouts: a model's predicted trajectory drawn over the ground truth, frame by frame,
written as a GIF with matplotlib (Agg) and Pillow (no system encoder).

Each frame shows the mesh edges (the plate's triangle edges, the rod's polyline) of both
trajectories projected on the ground truth's plane of motion (``figures._plane``), with the
time (s), the trajectory's Young's modulus (Pa) and the position RMSE at that frame (m,
``benchmarks.suite.metrics.rmse_per_step``). The axes keep one window for the whole trajectory."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from benchmarks.suite import figures as F
from benchmarks.suite import metrics as M
from benchmarks.suite.runs import load_test_rollout
from groundtruth import store

MAX_FRAMES = 60  # GIF frames; longer trajectories are subsampled evenly
FRAME_MS = 100  # display time of one GIF frame
WIDTH = 4.8  # inches, at DPI: a GIF 432 pixels wide
DPI = 90
GT_COLOR = "0.15"
COLORS = 24  # size of the palette shared by all frames


def frame_steps(n_frames: int, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """At most ``max_frames`` saved frames out of ``n_frames``, evenly spaced, first and last
    included."""
    if max_frames < 2:
        raise ValueError(f"max_frames must be >= 2, got {max_frames!r}")
    k = min(n_frames, max_frames)
    return np.unique(np.round(np.linspace(0, n_frames - 1, k)).astype(int))


def si(value: float, unit: str, prefixes: dict) -> str:
    """``value`` with the largest of ``prefixes`` (name: factor) it reaches a tenth of, 3
    significant digits: ``si(5.3e8, "Pa", {"G": 1e9, "M": 1e6})`` -> ``"0.53 GPa"``."""
    for name, factor in sorted(prefixes.items(), key=lambda kv: -kv[1]):
        if abs(value) >= 0.1 * factor:
            return f"{value / factor:.3g} {name}{unit}"
    name, factor = min(prefixes.items(), key=lambda kv: kv[1])
    return f"{value / factor:.3g} {name}{unit}"


PA_PREFIXES = {"G": 1e9, "M": 1e6, "k": 1e3, "": 1.0}
M_PREFIXES = {"": 1.0, "m": 1e-3, "µ": 1e-6}


def _window(true: np.ndarray, pred: np.ndarray, axes: tuple) -> tuple:
    """Fixed ``(xlim, ylim)`` over the whole trajectory: the ground truth's extent widened to
    take in the prediction, but by at most half the ground truth's size on each side (a
    diverged rollout leaves the window instead of shrinking the ground truth to a dot)."""
    gt, pr = true[..., list(axes)].reshape(-1, 2), pred[..., list(axes)].reshape(-1, 2)
    lo, hi = gt.min(0), gt.max(0)
    size = max((hi - lo).max(), 1e-9)
    finite = pr[np.isfinite(pr).all(1)]
    if len(finite):
        lo = np.minimum(lo, np.maximum(finite.min(0), lo - 0.5 * size))
        hi = np.maximum(hi, np.minimum(finite.max(0), hi + 0.5 * size))
    pad = 0.06 * max((hi - lo).max(), 1e-9)
    return (lo[0] - pad, hi[0] + pad), (lo[1] - pad, hi[1] + pad)


def _segments(pos: np.ndarray, edges: np.ndarray, axes: tuple) -> np.ndarray:
    """``(E, 2, 2)`` end points of every edge in the plane ``axes``."""
    return pos[:, list(axes)][edges]


def _figure(xlim: tuple, ylim: tuple, axes: tuple):
    """A figure ``WIDTH`` inches wide whose height follows the window's aspect ratio (little
    empty space around a long plate), and its axes: equal aspect, fixed limits, units."""
    plt = F._plt()
    aspect = float(np.clip((ylim[1] - ylim[0]) / (xlim[1] - xlim[0]), 0.3, 1.0))
    fig, ax = plt.subplots(figsize=(WIDTH, 0.8 * WIDTH * aspect + 1.3), dpi=DPI)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal", adjustable="box")
    names = "xyz"
    ax.set_xlabel(f"{names[axes[0]]} (m)", fontsize=8)
    ax.set_ylabel(f"{names[axes[1]]} (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(True, alpha=0.25)
    return fig, ax


class _Scene:
    """One figure whose artists are updated in place for every frame."""

    def __init__(self, true, pred, arrays, index: int, label: str, color: str, title: str):
        from matplotlib.collections import LineCollection

        self.true, self.pred, self.edges = true, pred, np.asarray(arrays["edges"])
        self.t = np.asarray(arrays["t"], float)
        self.rmse = M.rmse_per_step(pred[None], true[None])[0]
        self.axes = F._plane(true)
        self.youngs = float(np.asarray(arrays["youngs"]).ravel()[index])
        self.fig, ax = _figure(*_window(true, pred, self.axes), self.axes)
        lw = 0.6 if len(np.asarray(arrays["cells"])) else 1.6  # plate edges thinner than a rod
        self.lines = []
        for pos, c, lbl in ((true, GT_COLOR, "ground truth"), (pred, color, label)):
            lc = LineCollection(_segments(pos[0], self.edges, self.axes), colors=c,
                                linewidths=lw, label=lbl)
            ax.add_collection(lc)
            self.lines.append(lc)
        # title, readout and legend outside the axes: they never hide the meshes
        self.fig.suptitle(title, fontsize=9)
        self.text = ax.set_title(" ", fontsize=8, family="monospace")
        self.fig.legend(loc="lower center", ncol=2, fontsize=7, frameon=False)
        self.fig.tight_layout(rect=(0, 0.3 / self.fig.get_figheight(), 1, 1))  # legend row
        self.palette = None

    def draw(self, k: int):
        """The Pillow image of saved frame ``k``."""
        from PIL import Image

        for lc, pos in zip(self.lines, (self.true, self.pred)):
            lc.set_segments(_segments(pos[k], self.edges, self.axes))
        # fixed widths: the centred readout does not jitter from frame to frame
        self.text.set_text(f"t = {self.t[k]:6.3f} s   Y = {si(self.youngs, 'Pa', PA_PREFIXES)}"
                           f"   RMSE = {si(self.rmse[k], 'm', M_PREFIXES):<9}")
        canvas = self.fig.canvas
        canvas.draw()
        rgb = Image.frombuffer("RGBA", canvas.get_width_height(), canvas.buffer_rgba())
        rgb = rgb.convert("RGB")
        # the first frame's palette for every frame: unchanged pixels keep their index, so
        # the GIF stores only the changed rectangle of each frame; no dithering (same bytes)
        if self.palette is None:
            self.palette = rgb.quantize(colors=COLORS, dither=Image.Dither.NONE)
        return rgb.quantize(palette=self.palette, dither=Image.Dither.NONE)


def animate(arrays: dict, pred_pos: np.ndarray, index: int, path: Path, *, label: str,
            title: str, color: str = "tab:blue", max_frames: int = MAX_FRAMES) -> Path:
    """Write the GIF of trajectory ``index``: ``arrays`` is the ground truth's split (store
    format, ``pos`` of shape (B, T, N, 3), m), ``pred_pos`` the model's positions of the same
    split (B, T, N, 3) or of this trajectory (T, N, 3). Returns ``path``."""
    true = np.asarray(arrays["pos"], float)[index]
    pred = np.asarray(pred_pos, float)
    pred = pred[index] if pred.ndim == 4 else pred
    if pred.shape != true.shape:
        raise ValueError(f"the prediction has shape {pred.shape}, the ground truth of "
                         f"trajectory {index} {true.shape}")
    scene = _Scene(true, pred, arrays, index, label, color, title)
    try:
        frames = [scene.draw(int(k)) for k in frame_steps(len(true), max_frames)]
    finally:
        F._plt().close(scene.fig)
    buf = io.BytesIO()
    frames[0].save(buf, format="GIF", save_all=True, append_images=frames[1:],
                   duration=FRAME_MS, loop=0, optimize=True)
    store.atomic_write(Path(path), lambda f: f.write(buf.getvalue()))
    return Path(path)


def suite_animations(out: Path, records: list, runs_dir: Path, tests: dict,
                     index: int = 0) -> list:
    """``out/rollout_CASE_MODEL.gif`` for every run of the lowest seed of each case, from its
    stored test rollout (``runs.PRED_FILE``) and test trajectory ``index`` of ``tests[case]``;
    a model with several variants (integrator, gradient mode) gets them in the name."""
    paths = []
    for case in sorted({r["case"] for r in records}):
        seed0 = F.first_seed([r for r in records if r["case"] == case])
        models = [r["model"] for r in seed0]
        for i, r in enumerate(seed0):
            name = r["model"] if models.count(r["model"]) == 1 else \
                f"{r['model']}_{r['integrator']}_{r['grad_mode']}"
            pred = load_test_rollout(Path(runs_dir) / r["run"])
            paths.append(animate(tests[case], pred, index, Path(out) / f"rollout_{case}_{name}.gif",
                                 label=F._label(r), color=F._color(r["model"], i),
                                 title=f"{case}: test trajectory {index}"))
    return paths
