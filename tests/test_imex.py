"""MeshODENet-IMEX (``meshodenet.gnn.imex``) and the ``youngs_feature`` option."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from meshodenet.gnn import reference
from meshodenet.gnn.features import FeatureStats
from meshodenet.gnn.imex import ImexConfig, MeshODENetIMEX
from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.registry import get_model_spec, load_model
from tests.conftest import rod_arrays, strip_arrays


def _build(arrays, dtype=torch.float64, **cfg):
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, dtype=dtype)
    torch.manual_seed(0)
    model = MeshODENetIMEX(mesh, ImexConfig(hidden=8, mlp_hidden_layers=1, **cfg), tr)
    return model.to(dtype), tr


def _manual_rollout(model, tr, idx, T):
    """The scheme written out with the reference field, one step at a time."""
    ctx = model.field_context(tr.youngs[idx])
    x, v = tr.pos[idx, 0].reshape(-1, 3), tr.vel[idx, 0].reshape(-1, 3) * ctx.batch.free
    g = model.gamma.repeat(len(idx))[:, None]
    xs = [x]
    for k in range(T - 1):
        h = tr.t[k + 1] - tr.t[k]
        w = reference.vector_field(model, torch.stack([x, v]), ctx)[1]
        v = (v + h * g * w) / (1 + h * g)
        x = x + h * v
        xs.append(x)
    return torch.stack(xs).reshape(T, len(idx), -1, 3).transpose(0, 1)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_rollout_is_the_semi_implicit_scheme_with_equal_gradients(make):
    arrays = make()
    arrays["damping"] = arrays["mass"] * np.linspace(0.5, 5e4, len(arrays["mass"]))
    model, tr = _build(arrays)
    idx = torch.tensor([0, 1])
    T = tr.n_frames
    want = _manual_rollout(model, tr, idx, T)
    got, vel = model.rollout(tr.pos[idx, 0], tr.vel[idx, 0], tr.youngs[idx], tr.t)
    assert torch.allclose(got, want, rtol=1e-12, atol=1e-15)
    assert (got[:, :, arrays["node_type"] == 1] == tr.pos[idx, :1][:, :, arrays["node_type"] == 1]
            ).all()
    # gradients: the fast field under autograd, with and without segment checkpoints,
    # against the reference field
    grads = []
    for engine, seg in (("reference", 0), ("fast", 0), ("fast", 2)):
        model.config = replace(model.config, engine=engine)
        object.__setattr__(model.config, "checkpoint_every", seg)
        model.zero_grad()
        p, _ = model.rollout(tr.pos[idx, 0], tr.vel[idx, 0], tr.youngs[idx], tr.t)
        ((p - tr.pos[idx]) ** 2).sum().backward()
        grads.append(torch.cat([q.grad.reshape(-1) for q in model.parameters()]))
    for g in grads[1:]:
        assert torch.allclose(g, grads[0], rtol=1e-10, atol=1e-10 * float(grads[0].abs().max()))


def test_stiff_drag_makes_the_step_first_order():
    """gamma h >> 1: the new velocity is the learned one, whatever the old velocity."""
    arrays = rod_arrays()
    arrays["damping"] = arrays["mass"] * 1e12
    model, tr = _build(arrays)
    ctx = model.field_context(tr.youngs[:1])
    x0, v0 = tr.pos[0, 0], tr.vel[0, 3]
    w = reference.vector_field(model, torch.stack([x0, v0]), ctx)[1]
    _, vel = model.rollout(x0[None], v0[None], tr.youngs[:1], tr.t[:2])
    assert torch.allclose(vel[0, 1], w, rtol=1e-9, atol=0)


def test_output_normaliser_is_fitted_to_the_learned_velocity_target():
    arrays = rod_arrays(B=4, T=7)
    model, tr = _build(arrays)
    g = arrays["damping"] / arrays["mass"]
    h = np.diff(arrays["t"])[None, :, None, None]
    v = arrays["vel"]
    w = v[:, 1:] + (v[:, 1:] - v[:, :-1]) / (h * g[None, None, :, None])
    w = w.reshape(-1, 3)
    np.testing.assert_allclose(model.stats.acc.mean.numpy(), w.mean(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(model.stats.acc.std.numpy()[1], w.std(0)[1], rtol=1e-9)


def test_bad_drag_and_config_are_refused():
    arrays = rod_arrays()
    arrays["damping"] = arrays["damping"].copy()
    arrays["damping"][2] = 0.0
    with pytest.raises(ValueError, match="node 2"):
        _build(arrays)
    with pytest.raises(ValueError, match="checkpoint_every"):
        ImexConfig(checkpoint_every=-1)
    with pytest.raises(ValueError, match="hidden"):
        ImexConfig(hidden=0)
    for cls in (ImexConfig, MeshODENetConfig):
        with pytest.raises(ValueError, match="youngs_feature.*'sqrt'"):
            cls(youngs_feature="sqrt")


def test_log_youngs_feature_is_the_normalised_logarithm():
    arrays = rod_arrays(B=4)
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, dtype=torch.float64)
    from meshodenet.mesh.graph import GraphTopology

    stats = FeatureStats("line", "log").compute(GraphTopology(mesh), tr)
    y = np.log(arrays["youngs"])
    assert stats.node.mean[0].item() == pytest.approx(y.mean(), rel=1e-12)
    assert stats.node.std[0].item() == pytest.approx(y.std(), rel=1e-9)


def test_registered_trains_resumes_and_reloads(tmp_path):
    from meshodenet.training.train import fit

    arrays = rod_arrays(B=4)
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays)
    spec = get_model_spec("meshodenet_imex")
    tcfg, mcfg = spec.presets("smoke", "line")
    model = spec.build(mesh, mcfg, tr)
    fit(model, tr.subset([0, 1, 2]), tr.subset([3]), tcfg, tmp_path, progress=False)
    fit(model, tr.subset([0, 1, 2]), tr.subset([3]), tcfg, tmp_path, progress=False,
        resume=True)
    again, _ = load_model(tmp_path / "best.pt")
    assert isinstance(again, MeshODENetIMEX)
    with torch.no_grad():
        a, _ = again.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)
    assert torch.isfinite(a).all()


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_rest_position_feature_fast_equals_reference(make):
    from meshodenet.gnn import fast
    from meshodenet.gnn.meshodenet import MeshODENet
    from meshodenet.gnn.network import FastField

    arrays = make()
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, dtype=torch.float64)
    torch.manual_seed(0)
    model = MeshODENet(mesh, MeshODENetConfig(hidden=8, rest_position=True,
                                              youngs_feature="log"), tr).double()
    ctx = model.field_context(tr.youngs[:2])
    assert ctx.node_static.shape[1] == (1 if mesh.kind == "line" else 3) + 3
    z = torch.stack([tr.pos[:2, 2].reshape(-1, 3), tr.vel[:2, 2].reshape(-1, 3)])
    want = reference.vector_field(model, z, ctx)
    got = fast.evaluate(FastField(model, ctx), z)
    assert torch.allclose(got, want, rtol=1e-10, atol=1e-12 * float(want.abs().max()))
    # the rest coordinates are what the static features hold (normalised)
    s = ctx.node_static[:, -3:] * model.stats.node.std[ctx.node_static.shape[1] - 3:
                                                      ctx.node_static.shape[1]]
    s = s + model.stats.node.mean[ctx.node_static.shape[1] - 3: ctx.node_static.shape[1]]
    moving = model.stats.node.std[ctx.node_static.shape[1] - 3: ctx.node_static.shape[1]] > 0
    rest = torch.as_tensor(arrays["rest_pos"]).repeat(2, 1)
    assert torch.allclose(s[:, moving], rest[:, moving], atol=1e-12)


def test_mgn_vector_acceleration_normaliser():
    from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig

    arrays = rod_arrays(B=3, T=8)
    arrays["pos"][..., 0] += 1e-4 * np.sin(np.arange(8))[None, :, None]  # some x motion
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, dtype=torch.float64)
    comp = MeshGraphNet(mesh, MeshGraphNetConfig(hidden=8, layers=1), tr)
    vec = MeshGraphNet(mesh, MeshGraphNetConfig(hidden=8, layers=1, acc_norm="vector"), tr)
    sc, sv = comp.stats.acc.std, vec.stats.acc.std
    assert sc[0] != sc[1] and sc[2] == 0
    assert sv[0] == sv[1] == pytest.approx(float(sc[:2].pow(2).mean().sqrt()), rel=1e-12)
    assert sv[2] == 0 and torch.equal(comp.active, vec.active)
    with pytest.raises(ValueError, match="acc_norm"):
        MeshGraphNetConfig(acc_norm="per_node")


def _window_starts(model, tr, samples, gen):
    """``(trajectory, start frame)`` of each window ``training_loss`` rolls out."""
    seen = []

    def spy(x0, v0, youngs, t):
        seen.append(x0.clone())
        n = len(x0)
        return x0[:, None].expand(n, len(t), *x0.shape[1:]), None

    model.rollout = spy
    model.training_loss(tr, samples, gen)
    del model.rollout
    x0 = seen[0]  # (n, N, 3): match each against every frame of every trajectory
    d = ((tr.pos[None] - x0[:, None, None]) ** 2).sum((-1, -2))  # (n, B, T)
    flat = d.reshape(len(x0), -1).argmin(1)
    return flat // tr.n_frames, flat % tr.n_frames


def test_release_fraction_default_draws_nothing_and_option_starts_windows_at_frame_0():
    from meshodenet.gnn.meshodenet import release_count

    arrays = rod_arrays(B=4, T=8)  # 7 intervals: windows of 2, 3 per trajectory, offset 0-1
    model, tr = _build(arrays, shooting=2)
    tr.pos[..., 0] += torch.arange(tr.n_frames, dtype=tr.pos.dtype)[None, :, None]  # unique
    tr.pos[..., 1] += 100 * torch.arange(len(tr), dtype=tr.pos.dtype)[:, None, None]  # frames
    n_w = 3
    samples = torch.tensor([1, 5, 7, 10, 11, 4])
    for frac, n0 in ((0.0, 0), (0.5, 3), (1.0, 6)):  # integer counts: no extra draw
        model.config = ImexConfig(hidden=8, mlp_hidden_layers=1, shooting=2,
                                  release_fraction=frac)
        gen = torch.Generator().manual_seed(3)
        ref = torch.Generator().manual_seed(3)
        offset = torch.randint(0, 2, (len(samples),), generator=ref)  # today's only draw
        traj, start = _window_starts(model, tr, samples, gen)
        want = (samples % n_w) * 2 + offset
        want[:n0] = 0
        assert traj.tolist() == (samples // n_w).tolist()
        assert start.tolist() == want.tolist()
        assert torch.equal(gen.get_state(), ref.get_state())
    # a fractional count is rounded up with probability its fractional part, from the generator
    gen = torch.Generator().manual_seed(0)
    counts = [release_count(0.3, 4, gen) for _ in range(4000)]
    assert set(counts) == {1, 2}
    assert np.mean(counts) == pytest.approx(1.2, abs=0.03)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    assert [release_count(0.3, 4, g1) for _ in range(50)] == \
        [release_count(0.3, 4, g2) for _ in range(50)]
    assert release_count(0.0, 4, None) == 0 and release_count(0.25, 8, None) == 2


def test_release_fraction_is_checked_and_old_runs_read_as_the_default():
    from benchmarks.suite.runs import apply_overrides, with_defaults
    from meshodenet.gnn.imex import imex_presets

    for cls in (ImexConfig, MeshODENetConfig):
        for name in ("release_fraction", "frame_weight"):
            for bad in (1.5, -0.1, float("nan"), True, "0.5"):
                with pytest.raises(ValueError, match=rf"{cls.__name__}\.{name} .*{bad!r}"):
                    cls(**{name: bad})
    tc, mc = imex_presets("quick", "triangle")
    with pytest.raises(ValueError, match=r"release_fraction .*2\.0"):
        apply_overrides(tc, mc, ["model.release_fraction=2"])
    # the plate's quick preset oversamples the release, the rod's and MeshODENet's do not
    assert mc.release_fraction == 0.05 and imex_presets("quick", "line")[1].release_fraction == 0
    assert get_model_spec("meshodenet").presets("quick", "triangle")[1].release_fraction == 0
    # only the rod's IMEX quick preset weighs frames (docs/TRAINING.md); the paper's loss: none
    assert imex_presets("quick", "line")[1].frame_weight == 0.5
    assert [imex_presets(p, k)[1].frame_weight for p in ("paper", "smoke")
            for k in ("line", "triangle")] + [mc.frame_weight] == [0.0] * 5
    assert all(get_model_spec("meshodenet").presets(p, k)[1].frame_weight == 0
               for p in ("paper", "quick", "smoke") for k in ("line", "triangle"))
    stored = {"model": "meshodenet_imex", "model_config": {"hidden": 32}, "train": {}}
    assert with_defaults(stored)["model_config"]["release_fraction"] == 0.0
    assert with_defaults(stored)["model_config"]["frame_weight"] == 0.0
    stored["model"] = "meshodenet"
    assert with_defaults(stored)["model_config"]["release_fraction"] == 0.0
    assert with_defaults(stored)["model_config"]["frame_weight"] == 0.0


@pytest.mark.parametrize("lam", [0.0, 0.1, 2.0])
def test_release_weight_adds_the_first_step_relative_to_standing_still(lam):
    """Whole rollouts of every trajectory: standing still scores ``1 + lambda``. Windows: the
    release step starts from frame 0 of each sample's trajectory whatever the window, and adds
    ``lambda`` times its mean square error over ``s_rel`` to the trajectory loss."""
    for cls, cfg in ((MeshODENetIMEX, ImexConfig), (MeshODENet, MeshODENetConfig)):
        arrays = rod_arrays(B=3, T=6)
        mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
        model = cls(mesh, cfg(hidden=8, mlp_hidden_layers=1, release_weight=lam), tr).double()
        calls = []

        def still(x0, v0, youngs, t, calls=calls):
            calls.append((x0.clone(), len(t)))
            return x0[:, None].expand(-1, len(t), -1, -1), None

        model.rollout = still
        assert float(model.training_loss(tr, torch.arange(3))) == \
            pytest.approx(1.0 + lam, rel=1e-12)
        assert len(calls) == 1 + bool(lam)
        # windows of 2 intervals (2 per trajectory): samples 0-3 are trajectories 0, 0, 1, 1
        model.config = replace(model.config, shooting=2)
        idx, frame0 = torch.arange(4), tr.pos[torch.tensor([0, 0, 1, 1]), 0]
        e = torch.tensor([3e-3, -4e-3, 0.0], dtype=torch.float64)  # |e|^2 = 2.5e-5

        def wrong_release(x0, v0, youngs, t, calls=calls, e=e):
            calls.append((x0.clone(), len(t)))
            out = x0[:, None].expand(-1, len(t), -1, -1).clone()
            if len(t) == 2:  # the release step (windows here have 3 frames)
                out[0, 1, 2] += e
            return out, None

        model.rollout = wrong_release
        got = float(model.training_loss(tr, idx, torch.Generator().manual_seed(0)))
        if lam:
            x0, n_t = calls[-1]
            assert n_t == 2 and torch.equal(x0, frame0)
        model.config = replace(model.config, release_weight=0.0)
        base = float(model.training_loss(tr, idx, torch.Generator().manual_seed(0)))
        s_rel = float(((tr.pos[:, 1] - tr.pos[:, 0]) ** 2).sum(-1).mean())
        sq = ((tr.pos[torch.tensor([0, 0, 1, 1]), 1] - frame0) ** 2).sum(-1)
        sq[0, 2] = ((tr.pos[0, 1, 2] - tr.pos[0, 0, 2] - e) ** 2).sum()
        assert got - base == pytest.approx(lam * float(sq.mean()) / s_rel, rel=1e-9, abs=1e-15)


def test_release_weight_is_checked_and_old_runs_read_as_the_default():
    from benchmarks.suite.runs import apply_overrides, with_defaults
    from meshodenet.gnn.imex import imex_presets

    for cls in (ImexConfig, MeshODENetConfig):
        for bad in (-0.1, float("nan"), float("inf"), True, "0.5"):
            with pytest.raises(ValueError, match=rf"{cls.__name__}\.release_weight .*{bad!r}"):
                cls(release_weight=bad)
        assert cls(release_weight=3).release_weight == 3
    tc, mc = imex_presets("quick", "line")
    with pytest.raises(ValueError, match=r"release_weight .*-1\.0"):
        apply_overrides(tc, mc, ["model.release_weight=-1"])
    # of IMEX's presets only the rod's quick one weighs the release (docs/TRAINING.md)
    assert mc.release_weight == 0.05 and mc.rest_position
    assert imex_presets("quick", "triangle")[1].rest_position
    # plates: every model's quick preset has the rest coordinates (docs/TRAINING.md); rods:
    # IMEX's and MGN's
    for m in ("meshodenet", "mgn", "mgn_unrolled", "meshodenet_imex"):
        spec = get_model_spec(m)
        assert spec.presets("quick", "triangle")[1].rest_position
        assert spec.presets("quick", "line")[1].rest_position == (m != "meshodenet")
    assert not any(imex_presets(p, k)[1].rest_position
                   for p in ("paper", "smoke") for k in ("line", "triangle"))
    assert imex_presets("quick", "triangle")[1].release_weight == 0
    assert all(imex_presets(p, k)[1].release_weight == 0
               for p in ("paper", "smoke") for k in ("line", "triangle"))
    # MeshODENet: only the plate's quick preset (docs/HISTORY.md, "MeshODENet's plate from whole rollouts")
    assert [get_model_spec("meshodenet").presets(p, k)[1].release_weight
            for p in ("paper", "quick", "smoke") for k in ("line", "triangle")] \
        == [0, 0, 0, 0.05, 0, 0]
    for model in ("meshodenet_imex", "meshodenet"):
        stored = {"model": model, "model_config": {"hidden": 32}, "train": {}}
        assert with_defaults(stored)["model_config"]["release_weight"] == 0.0


@pytest.mark.parametrize("p", [0.0, 0.5, 1.0])
def test_frame_weight_loss_is_relative_to_standing_still(p):
    """Whole rollouts of every trajectory: standing still scores 1 for every exponent, and an
    error ``e`` at frame 1 alone costs ``|e|^2 s_1^-p / (S mean_d s_d^(1-p))``."""
    for cls, cfg in ((MeshODENetIMEX, ImexConfig), (MeshODENet, MeshODENetConfig)):
        arrays = rod_arrays(B=3, T=6)
        mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
        model = cls(mesh, cfg(hidden=8, mlp_hidden_layers=1, frame_weight=p), tr).double()
        S, idx = tr.n_frames - 1, torch.arange(len(tr))
        model.rollout = lambda x0, v0, youngs, t: (x0[:, None].expand(-1, len(t), -1, -1), None)
        assert float(model.training_loss(tr, idx)) == pytest.approx(1.0, rel=1e-12)
        s_d = ((tr.pos[:, 1:] - tr.pos[:, :1]) ** 2).sum(-1).mean(dim=(0, 2))
        e = torch.zeros_like(tr.pos)
        e[0, 1, 2] = torch.tensor([3e-3, -4e-3, 0.0], dtype=torch.float64)  # |e|^2 = 2.5e-5
        model.rollout = lambda x0, v0, youngs, t, pred=tr.pos + e: (pred, None)
        want = 2.5e-5 / (len(tr) * mesh.n_nodes) * s_d[0] ** -p / (S * (s_d ** (1 - p)).mean())
        assert float(model.training_loss(tr, idx)) == pytest.approx(float(want), rel=1e-12)
