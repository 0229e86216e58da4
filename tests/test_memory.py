"""Training memory (docs/SCALE.md, "Memory"): what grew with the mesh or the data set and need
not. Implicit-Energy's least-squares start takes the frames through its element MLPs in chunks,
its statistics one trajectory at a time and its training frames are converted after indexing;
MeshGraphNet's blocks keep no edge messages alive for the backward pass of their sum; a
training run keeps one float32 copy of its trajectories. Each change gives the same bits as
the code before it, written out here; the memory is pinned by the largest tensor storage the
code creates (``Largest``), not by timing or RSS."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from meshodenet.energy import start as energy_start
from meshodenet.energy.core import measure
from meshodenet.energy.model import EnergyConfig, ImplicitEnergy
from meshodenet.gnn import network
from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig
from meshodenet.mesh.data import Mesh, Trajectories
from tests.conftest import rod_arrays, strip_arrays


class Largest(TorchDispatchMode):
    """The largest storage (bytes) of any tensor an op creates while active (views allocate
    nothing and are left out)."""

    def __init__(self):
        super().__init__()
        self.nbytes = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if func.is_view:
            return out
        for t in tree_leaves(out):
            if isinstance(t, torch.Tensor):
                self.nbytes = max(self.nbytes, t.untyped_storage().nbytes())
        return out


def _energy(make, **cfg):
    arrays = make(B=8, T=201)
    data = Trajectories.from_arrays(arrays)
    return ImplicitEnergy(Mesh.from_arrays(arrays), EnergyConfig(**cfg), None), data


# --- Implicit-Energy ---------------------------------------------------------------------------
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_least_squares_columns_in_chunks_are_the_same_bits(make, monkeypatch):
    """The fit's columns in chunks of 64 frames equal those of one pass over every frame (320),
    bit for bit, and the pass in chunks never creates the ``(frames, elements, hidden)``
    activations of all frames at once."""
    model, data = _energy(make, hidden=64, stiffness_prior="features")
    model._statistics(data)
    samples = torch.arange(0, len(data) * (data.n_frames - 1), 5)
    traj, _, _, x1, _ = model._frames(data, samples)
    youngs = data.youngs[traj]
    out = {}
    for name, chunk_bytes in (("one pass", 2**50), ("chunks", 1)):  # 1: 64 frames a chunk
        monkeypatch.setattr(energy_start, "FIT_CHUNK_BYTES", chunk_bytes)
        with Largest() as mode:
            out[name] = (model._balance_columns(youngs, x1), mode.nbytes)
    (cols, owner), one_pass = out["one pass"]
    (chunked, owner2), in_chunks = out["chunks"]
    assert [k for k, _ in owner] == [k for k, _ in owner2] and len(cols) == len(chunked) > 1
    assert all(torch.equal(a, b) for a, b in zip(cols, chunked))
    n = max(len(getattr(model, f"{k}_nodes")) for k in model.kinds)
    assert one_pass >= len(x1) * n * 64 * 8  # an activation of every frame
    assert len(x1) == 320 and in_chunks * 4 < one_pass
    monkeypatch.setattr(energy_start, "FIT_CHUNK_BYTES", 2**20 * n * 64 * 8 + 100)
    assert model.fit_chunk() == 2**20


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_statistics_one_trajectory_at_a_time_are_the_same_bits(make):
    """``ystats``, ``sigma`` and ``qrange`` equal the whole-split formulas they replaced, bit
    for bit, without the float64 positions of every frame gathered onto the elements."""
    model, data = _energy(make, clamp_q=True)
    with Largest() as mode:
        model._statistics(data)
    pos = data.pos.to(torch.float64)
    step = (pos[:, 1:] - pos[:, :-1])[:, :, model.free]
    # (ystats is filled from a default-dtype tensor: float32-rounded, as before)
    assert float(model.ystats[3]) == float(torch.tensor(float((step**2).sum(-1).mean())))
    gathered = 0
    for k, (nodes, _, rest, l0) in model._elems().items():
        xe = pos[:, :, nodes]
        gathered = max(gathered, xe.untyped_storage().nbytes())
        q = measure(k, xe, rest, l0)
        sigma = float(torch.sqrt((q**2).mean()))
        assert float(getattr(model, f"{k}_sigma")) == sigma
        qh = q / getattr(model, f"{k}_sigma")
        assert torch.equal(getattr(model, f"{k}_qrange"), torch.stack([qh.min(), qh.max()]))
    assert mode.nbytes < gathered


@pytest.mark.parametrize("make, prior", [(rod_arrays, "uniform"), (rod_arrays, "features"),
                                         (strip_arrays, "uniform")])
def test_reduced_start_is_the_whole_one_in_chunks(make, prior, monkeypatch):
    """Above ``START_WHOLE_BYTES`` (set to 0 here) the statistics are summed over chunks of
    frames and the least-squares system is reduced chunk by chunk (QR): the same buffers to
    round-off (the memory it saves is measured at r = 8, docs/SUBDOMAIN.md). Not the synthetic
    strip's ``features`` columns: they are dependent (condition 2e16), and where a direction
    is dropped is decided by round-off in either fit; the real plate's (condition 2.5e4)
    agree to 3e-14 (measured on plate_cantilever's data, docs/SUBDOMAIN.md)."""
    out, calls = {}, []
    reduced = energy_start.LeastSquaresStart._reduced_lstsq
    monkeypatch.setattr(energy_start.LeastSquaresStart, "_reduced_lstsq",
                        lambda self, *a: calls.append(a[-1]) or reduced(self, *a))
    for name, whole in (("whole", 2**50), ("reduced", 0)):
        monkeypatch.setattr(energy_start, "START_WHOLE_BYTES", whole)
        monkeypatch.setattr(energy_start, "START_CHUNK_BYTES", 2**12)  # several chunks
        torch.manual_seed(0)
        model, data = _energy(make, stiffness_prior=prior, clamp_q=True)
        model._statistics(data)
        model._fit_log_stiffness(data)
        out[name] = (model, {k: v.clone() for k, v in model.state_dict().items()})
    (_, a), (model, b) = out["whole"], out["reduced"]
    assert a.keys() == b.keys() and len(calls) == 1 and calls[0] < 320 // 4  # several chunks
    for k in a:
        if not a[k].is_floating_point():
            assert torch.equal(a[k], b[k]), k
        else:
            torch.testing.assert_close(b[k], a[k], rtol=1e-12, atol=0, msg=k)
    samples = torch.arange(0, len(data) * (data.n_frames - 1), 5)
    G, rhs, _, _ = model._balance_system(data, samples)
    b = rhs.reshape(-1, 1)
    s_whole = torch.linalg.lstsq(G, b).solution[:, 0]
    s_reduced, _ = model._reduced_lstsq(data, samples, 7)
    torch.testing.assert_close(s_reduced, s_whole, rtol=1e-12, atol=0)


def test_training_frames_are_converted_after_indexing():
    """``_frames`` of a few samples equals the old conversion of the whole split, bit for bit,
    and creates nothing of the split's size."""
    model, data = _energy(strip_arrays)
    samples = torch.tensor([0, 7, 201, 1599])
    with Largest() as mode:
        traj, xk, vk, x1, h = model._frames(data, samples)
    T = data.n_frames
    tr, k = samples // (T - 1), samples % (T - 1)
    pos = data.pos.to(torch.float64)
    hk = (data.t.double()[k] - data.t.double()[(k - 1).clamp(min=0)]).clamp_min(1e-300)
    v = torch.where((k == 0)[:, None, None], data.vel[tr, 0].double(),
                    (pos[tr, k] - pos[tr, (k - 1).clamp(min=0)]) / hk[:, None, None])
    assert torch.equal(xk, pos[tr, k]) and torch.equal(x1, pos[tr, k + 1])
    assert torch.equal(vk, v * model.free[:, None])
    assert mode.nbytes < pos.untyped_storage().nbytes() / 4


def _dense_training_loss(model, data, samples):
    """The one-step training loss as it was before the band solve: the Newton matrix of the
    active coordinates as a dense ``(B, n, n)`` tensor and torch's dense factorisation."""
    traj, xk, vk, x1, h = model._frames(data, samples)
    sys = model.system(data.youngs[traj])
    act = model._active(xk, vk)
    vk, h = model._implicit_form(vk, model._start(sys, xk, vk), h)
    geo = sys.geometry(x1)
    A = model._matrix(sys, x1, h, act, geo, xk, create_graph=model.config.exact_loss_gradient)
    r = model._residual(sys, x1, xk, vk, h, create_graph=True, geo=geo)[:, act]
    d = model._solve(A, r)
    n = len(model.free.nonzero())
    return (d**2).sum() / (len(traj) * n * float(model.ystats[3])), len(traj), len(act)


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("learner", ["energy", "dissipation"])
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_training_loss_in_band_storage_is_the_dense_one(make, learner, exact):
    """The one-step loss and its parameter gradients through the band solve (``BandSolve``)
    equal those through the dense Newton matrix to round-off, with and without the matrix's
    own dependence on the parameters (``exact_loss_gradient``), for the energy alone and
    with the learned dissipation."""
    from tests.test_energy_dissipation import _model

    arrays = make(B=8, T=201)
    data = Trajectories.from_arrays(arrays)
    if learner == "energy":
        model, _ = _energy(make, hidden=16, exact_loss_gradient=exact)
        model._statistics(data)
        torch.manual_seed(1)
        with torch.no_grad():  # an energy whose MLP is not flat, so its Hessian matters
            for p in model.parameters():
                p.add_(0.1 * torch.randn_like(p))
    else:
        model, _ = _model(arrays, exact_loss_gradient=exact)
    samples = torch.arange(0, len(data) * (data.n_frames - 1), 53)
    params = [p for p in model.parameters() if p.requires_grad]
    dense, B, n = _dense_training_loss(model, data, samples)
    g_dense = torch.autograd.grad(dense, params, allow_unused=True)
    band = model.training_loss(data, samples)
    g_band = torch.autograd.grad(band, params, allow_unused=True)
    assert torch.isfinite(band.detach()) and float(band.detach()) > 0
    torch.testing.assert_close(band, dense, rtol=1e-10, atol=0)
    some = 0
    for a, b in zip(g_band, g_dense):
        assert (a is None) == (b is None)
        if a is not None:
            scale = float(b.abs().max())
            some += scale > 0
            torch.testing.assert_close(a, b, rtol=0, atol=1e-9 * max(scale, 1e-300))
    assert some >= 2


@pytest.mark.parametrize("make", [lambda **k: rod_arrays(n_nodes=200, **k),
                                  lambda **k: strip_arrays(nx=60, ny=4, **k)],
                         ids=["rod", "strip"])
def test_training_loss_never_forms_the_dense_newton_matrix(make):
    """The one-step loss and its backward pass create no tensor of a quarter of the dense
    Newton matrices' ``(B, n, n)`` size: what they hold grows with the mesh, not its
    square."""
    model, data = _energy(make, hidden=16, exact_loss_gradient=True)
    model._statistics(data)
    samples = torch.arange(0, len(data) * (data.n_frames - 1), 97)
    with Largest() as mode:
        loss = model.training_loss(data, samples)
        loss.backward()
    n = len(model._active(data.pos[:1, 0].double(), data.vel[:1, 0].double()))
    assert n >= 390 and mode.nbytes < len(samples) * n * n * 8 / 4


def _banded(n: int, w: int, definite: bool, seed: int = 0) -> tuple:
    """A random symmetric matrix of bandwidth ``w``: ``(dense (n, n), lower band (w + 1,
    n))``, positive definite or indefinite."""
    g = np.random.default_rng(seed)
    A = np.zeros((n, n))
    for k in range(1, w + 1):
        v = g.standard_normal(n - k)
        A[np.arange(k, n), np.arange(n - k)] = A[np.arange(n - k), np.arange(k, n)] = v
    A += np.diag(2.5 * w + g.random(n)) if definite else np.diag(g.standard_normal(n))
    ab = np.zeros((w + 1, n))
    for k in range(w + 1):
        ab[k, :n - k] = np.diagonal(A, -k)
    return A, ab


@pytest.mark.parametrize("definite", [True, False])
def test_band_solve_and_its_gradients(definite):
    """``BandSolve`` solves its matrix (Cholesky, or LU where it is indefinite) as the dense
    solve does, and its gradients in the right-hand side and in every stored entry pass
    ``gradcheck`` (the padding entries outside the matrix get none)."""
    from meshodenet.energy import linalg as la

    A, ab = _banded(12, 3, definite)
    assert (la.band_factor(ab)[0] == "band") == definite
    b = np.random.default_rng(5).standard_normal((2, 12))
    x = la.BandSolve.apply(torch.as_tensor(np.stack([ab, ab])), torch.as_tensor(b))
    np.testing.assert_allclose(x.numpy(), np.linalg.solve(A, b.T).T, rtol=1e-12, atol=1e-12)
    abt = torch.as_tensor(ab)[None].requires_grad_(True)
    bt = torch.as_tensor(b[:1]).requires_grad_(True)
    assert torch.autograd.gradcheck(la.BandSolve.apply, (abt, bt))
    (la.BandSolve.apply(abt, bt) ** 2).sum().backward()
    for k in range(1, 4):
        assert not abt.grad[0, k, 12 - k:].any()


def test_band_newton_step_of_an_indefinite_matrix_is_the_dense_one():
    """The batched solver's step on an indefinite matrix: the LU step where it descends,
    else the convexified Cholesky's, as ``factor`` and ``substitute`` give them densely."""
    from meshodenet.energy import linalg as la

    A, ab = _banded(30, 4, definite=False, seed=2)
    dense = torch.as_tensor(A)[None]
    for seed in range(6):
        r = np.random.default_rng(seed).standard_normal((1, 30))
        b = -torch.as_tensor(r)
        fac = la.factor(dense)
        ref = la.substitute(fac, b)
        if float((b * ref).sum()) <= 0:
            ref = la.substitute(la.factor(dense, convexify=True), b)
        facs = [la.band_factor(ab)]
        assert facs[0][0] == "lu"
        np.testing.assert_allclose(la.band_solve(facs, r), ref.numpy(), rtol=1e-10,
                                   atol=1e-12)


# --- MeshGraphNet ------------------------------------------------------------------------------
def _mgn_step(layers: int = 3):
    arrays = strip_arrays(B=3, T=6)
    data = Trajectories.from_arrays(arrays)
    torch.manual_seed(0)
    model = MeshGraphNet(Mesh.from_arrays(arrays), MeshGraphNetConfig(
        hidden=8, layers=layers, mlp_hidden_layers=1, noise=0.1), data)
    loss = model.training_loss(data, torch.arange(12), torch.Generator().manual_seed(0))
    return model, loss


def _nodes(loss):
    seen, stack = [], [loss.grad_fn]
    while stack:
        fn = stack.pop()
        if fn is None or any(fn is s for s in seen):
            continue
        seen.append(fn)
        stack += [f for f, _ in fn.next_functions]
    return seen


def test_mgn_step_keeps_no_edge_messages_for_their_sum():
    """Each block's sum at the receivers keeps only the receivers (``SumAtReceivers``), not
    the messages autograd's ``index_add`` kept for their shape; the gradients are those of
    ``index_add``, bit for bit."""
    model, loss = _mgn_step()
    nodes = _nodes(loss)
    assert not [f for f in nodes if f.name().startswith("IndexAddBackward")]
    sums = [f for f in nodes if "SumAtReceivers" in f.name()]
    assert len(sums) == 3 and all(len(f.saved_tensors) == 1 and f.saved_tensors[0].dtype
                                  == torch.long for f in sums)
    loss.backward()
    grads = [p.grad.clone() for p in model.parameters()]

    class Plain:  # the code before: autograd's index_add
        @staticmethod
        def apply(m, receivers, n):
            return m.new_zeros(n, m.shape[1]).index_add_(0, receivers, m)

    orig = network.SumAtReceivers
    network.SumAtReceivers = Plain
    try:
        model, loss = _mgn_step()
        assert [f for f in _nodes(loss) if f.name().startswith("IndexAddBackward")]
        loss.backward()
    finally:
        network.SumAtReceivers = orig
    assert all(torch.equal(a, p.grad) for a, p in zip(grads, model.parameters()))


def test_mgn_step_statistics_are_the_same_bits():
    """``step_rms`` one trajectory at a time equals the whole-split formula."""
    model, _ = _mgn_step(layers=1)
    data = Trajectories.from_arrays(strip_arrays(B=3, T=6))
    free = torch.as_tensor(model.mesh.node_type == 0)
    step = (data.pos[:, 1:] - data.pos[:, :-1])[:, :, free].double()
    sq = step.pow(2).reshape(-1, 3).mean(0)[model.active > 0]
    assert float(model.step_rms) == float(sq.mean().sqrt()) > 0


# --- the training run --------------------------------------------------------------------------
def test_a_training_run_keeps_one_copy_of_its_trajectories(tmp_path, monkeypatch):
    """While ``fit`` runs, the resolved run no longer holds the training file's float64 arrays
    and no tensors of the whole file are alive: only the training and validation subsets."""
    import dataclasses

    from benchmarks.suite import registry
    from benchmarks.suite.generate import generate
    from benchmarks.suite.runs import resolve_run, train_resolved
    from meshodenet.training import train as training

    case = registry.CASES["rod_cantilever"]
    small = dataclasses.replace(case, n_train=7, n_test=1, t_end=4 * case.save_dt)
    monkeypatch.setattr(registry, "CASES", {**registry.CASES, case.id: small})
    generate(small, tmp_path, workers=1, progress=False)
    r = resolve_run(case.id, "mgn", "smoke", data_dir=tmp_path)
    shape = r["arrays"]["pos"].shape
    seen = {}

    class Stop(Exception):
        pass

    def fit(model, train, val, *a, **k):
        gc.collect()
        seen["whole"] = [o for o in gc.get_objects()
                         if type(o) is Trajectories and tuple(o.pos.shape) == shape]
        seen["train"], seen["val"] = len(train), len(val)
        raise Stop

    monkeypatch.setattr(training, "fit", fit)
    with pytest.raises(Stop):
        train_resolved(r, tmp_path / "run", data_dir=tmp_path, device="cpu", progress=False)
    assert "arrays" not in r
    assert seen["train"] + seen["val"] == shape[0] and seen["val"] >= 1
    assert seen["whole"] == []
