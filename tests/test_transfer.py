"""Learned models on meshes they were not trained on (``TrajectoryModel.on_mesh``): every learner
rolls out on a finer mesh of its kind, the training mesh's rollouts do not change, the learned
energy is a density, and what a model cannot represent is refused in one line (exit 2)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from meshodenet.energy.core import static_features
from meshodenet.energy.dissipation import node_features
from meshodenet.energy.model import ImplicitEnergy
from meshodenet.mesh.data import DataError, Mesh, Trajectories
from meshodenet.registry import MODELS
from tests.conftest import rod_arrays, strip_arrays

torch.set_num_threads(1)

OLD_MESSAGE = "use a run trained on this case"
#: a coarse mesh and one twice as fine, of each kind (the strip: similar triangles)
MESHES = {"line": (lambda: rod_arrays(n_nodes=5), lambda: rod_arrays(n_nodes=9, B=2)),
          "triangle": (lambda: strip_arrays(nx=5, ny=2), lambda: strip_arrays(nx=9, ny=3))}
LEARNERS = sorted(MODELS)


def build(name: str, arrays: dict, prior: str = "uniform", seed: int = 0):
    """``name``'s smoke model on ``arrays``, statistics from its trajectories (float64)."""
    spec = MODELS[name]
    mesh = Mesh.from_arrays(arrays)
    _, cfg = spec.presets("smoke", mesh.kind)
    if hasattr(cfg, "stiffness_prior"):
        cfg = dataclasses.replace(cfg, stiffness_prior=prior)
    torch.manual_seed(seed)
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    model = spec.build(mesh, cfg, data).double()
    for p in model.parameters():  # away from the zero-output start: every weight matters
        p.data.add_(0.05 * torch.randn_like(p))
    return model, data


def roll(model, data):
    with torch.no_grad():
        return model.rollout_all(data)


def variants():
    for name in LEARNERS:
        for kind in MESHES:
            yield name, kind, "uniform"
            if "energy" in name:
                yield name, kind, "features"


@pytest.mark.parametrize("name,kind,prior", list(variants()))
def test_every_learner_rolls_out_on_a_finer_mesh(name, kind, prior):
    coarse, fine = (f() for f in MESHES[kind])
    model, data = build(name, coarse, prior)
    before = roll(model, data)
    fine_mesh = Mesh.from_arrays(fine)
    moved = model.on_mesh(fine_mesh, "fine")
    assert moved is not model and moved.mesh is fine_mesh
    fine_data = Trajectories.from_arrays(fine, dtype=torch.float64)
    pos, vel = roll(moved, fine_data)
    assert pos.shape == vel.shape == fine_data.pos.shape
    assert torch.isfinite(pos).all() and torch.isfinite(vel).all()
    clamped = torch.as_tensor(fine_mesh.node_type == 1)
    assert torch.equal(pos[:, :, clamped], fine_data.pos[:, :1, clamped].expand_as(
        pos[:, :, clamped]))
    after = roll(model, data)  # the trained model is untouched by its copy
    assert all(torch.equal(a, b) for a, b in zip(before, after))


@pytest.mark.parametrize("name", LEARNERS)
@pytest.mark.parametrize("kind", sorted(MESHES))
def test_on_the_training_mesh_the_model_is_itself(name, kind):
    """The rollout path on the training mesh is the one before transfers existed: ``on_mesh``
    hands back the model itself, also for the mesh as a checkpoint stores it."""
    arrays = MESHES[kind][0]()
    model, data = build(name, arrays)
    assert model.on_mesh(Mesh.from_arrays(arrays)) is model
    assert model.on_mesh(Mesh.from_dict(model.mesh.to_dict())) is model
    renamed = Mesh.from_arrays(dict(arrays, case=np.array("another_name")))
    assert model.on_mesh(renamed) is model


@pytest.mark.parametrize("name,kind,prior", list(variants()))
def test_a_transfer_to_the_training_mesh_changes_nothing(name, kind, prior):
    """Forced through the transfer (rebuild, shared weights, rescaling by rho = 1), the
    training mesh's rollouts are the model's own: exactly, but for the least-squares fit of a
    ``features`` stiffness factor (round-off, within Newton's tolerance)."""
    arrays = MESHES[kind][0]()
    model, data = build(name, arrays, prior)
    copy = model.transfer(Mesh.from_arrays(arrays))
    assert copy is not model
    want, got = roll(model, data), roll(copy, data)
    for a, b in zip(want, got):
        if prior == "features":
            torch.testing.assert_close(b, a, rtol=1e-6, atol=1e-9)
        else:
            assert torch.equal(a, b)


def _old_standardised(f):
    """The column standardisation as it was written before ``reference`` existed."""
    sd = f.std(0)
    return np.where(sd > 1e-12, (f - f.mean(0)) / np.where(sd > 0, sd, 1), 0.0)


@pytest.mark.parametrize("kind", sorted(MESHES))
def test_static_features_on_the_training_mesh_are_bit_identical(kind):
    """The refactored feature code (raw features, then ``standardised``) gives the training
    mesh's features bit for bit as before, with or without itself as ``reference``."""
    from meshodenet.energy.core import _raw_static_features
    from meshodenet.energy.dissipation import _raw_node_features

    mesh = Mesh.from_arrays(MESHES[kind][0]())
    for ref in (None, mesh):
        feats = static_features(mesh, reference=ref)
        for k, raw in _raw_static_features(mesh)[0].items():
            assert np.array_equal(feats[k][1], _old_standardised(raw[1]))
        assert np.array_equal(node_features(mesh, reference=ref),
                              _old_standardised(_raw_node_features(mesh)[0]))


def _arc(n_nodes: int, length: float, curvature: float) -> np.ndarray:
    """``n_nodes`` on a circular arc of ``curvature`` in the x-y plane, chords ``length /
    (n_nodes - 1)``: no stretch, only bending."""
    chord = length / (n_nodes - 1)
    R = 1 / curvature
    a = 2 * math.asin(chord / (2 * R))
    th = a * np.arange(n_nodes)
    return np.stack([R * np.sin(th), R * (1 - np.cos(th)), 0 * th], 1)


def test_the_learned_energy_is_a_density():
    """A rod energy learned on 5 nodes, moved to 9 (rho = 1/2): a uniform stretch stores the
    same energy (edges: a density per length), a uniform bend the same energy per hinge length
    (hinges: their squared angle goes as rho^2), so the energy of a deformation does not
    depend on the mesh that resolves it."""
    model, _ = build("implicit_energy", rod_arrays(n_nodes=5))
    fine_arrays = rod_arrays(n_nodes=9)
    fine = model.on_mesh(Mesh.from_arrays(fine_arrays))
    y = torch.tensor([7e8], dtype=torch.float64)
    energies = {}
    for m, arr in ((model, rod_arrays(n_nodes=5)), (fine, fine_arrays)):
        rest = torch.as_tensor(arr["rest_pos"])[None]
        n = rest.shape[1]
        stretched = rest * torch.tensor([1.003, 1.0, 1.0], dtype=torch.float64)
        bent = torch.as_tensor(_arc(n, 0.1, 3.0))[None]
        with torch.no_grad():
            sys = m.system(y)
            energies[n] = (float(sys.energy(stretched)),
                           float(sys.energy(bent)) / (n - 2) * (n - 1))
    (s5, b5), (s9, b9) = energies[5], energies[9]
    assert s5 > 0 and b5 > 0
    assert s9 == pytest.approx(s5, rel=1e-12)
    # to second order in the turning angle per hinge (0.075 rad coarse): |kappa_b| = 2 tan(a/2)
    assert b9 == pytest.approx(b5, rel=3e-3)


def test_a_rod_model_on_a_plate_and_back_is_refused():
    for a, b in ((rod_arrays(), strip_arrays()), (strip_arrays(), rod_arrays())):
        for name in LEARNERS:
            model, _ = build(name, a)
            other = Mesh.from_arrays(b)
            with pytest.raises(DataError) as e:
                model.on_mesh(other, "the data")
            msg = str(e.value)
            assert "line mesh" in msg and "triangle mesh" in msg and "\n" not in msg
            assert OLD_MESSAGE not in msg


def test_a_planar_model_is_refused_motion_out_of_its_plane():
    planar = strip_arrays()
    for k in ("pos", "vel"):
        planar[k] = planar[k].copy()
        planar[k][..., 2] = 0.0
    planar["force"] = np.roll(planar["force"], -1, axis=1)  # gravity along y, in the plane
    for name in ("implicit_energy", "meshodenet"):
        model, _ = build(name, planar)
        with pytest.raises(DataError, match="moves in 3-D.*stays in its plane"):
            model.on_mesh(Mesh.from_arrays(strip_arrays()), "the data")


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # a mesh without dihedral hinges
def test_an_energy_is_refused_elements_it_never_learned():
    """A sheet of two triangles out of its plane has one dihedral hinge; one triangle none: a
    model trained on one triangle has no bending energy for a sheet that needs one."""
    two = strip_arrays(nx=2, ny=2)
    keep = two["cells"][0]  # the first triangle's nodes, renamed 0, 1, 2
    one = dict(two, cells=np.array([[0, 1, 2]]), edges=np.array([[0, 1], [1, 2], [0, 2]]))
    for k in ("node_type", "rest_pos", "mass", "force", "damping"):
        one[k] = two[k][keep]
    for k in ("pos", "vel"):
        one[k] = two[k][:, :, keep]
    model, _ = build("implicit_energy", one)
    assert model.kinds == ["edge"]
    with pytest.raises(DataError, match="dihedral elements.*learned energies of edge"):
        model.on_mesh(Mesh.from_arrays(strip_arrays()), "the data")


def test_the_old_refusal_message_is_gone():
    root = Path(__file__).resolve().parents[1]
    for path in list((root / "meshodenet").rglob("*.py")) + list((root / "benchmarks").rglob(
            "*.py")):
        assert OLD_MESSAGE not in path.read_text(), path


# --- the CLI: meshbench rollout --run R --file F ------------------------------------------------
@pytest.fixture(scope="module")
def runs(tiny_case, tiny_plate, tmp_path_factory):
    """A rod and a plate MeshGraphNet (1 smoke epoch) and the data of the rod twice as fine."""
    from benchmarks.suite.generate import generate
    from benchmarks.suite.registry import get_case
    from benchmarks.suite.runs import train_run

    out = tmp_path_factory.mktemp("runs")
    files = {}
    for (case, root), kind in ((tiny_case, "rod"), (tiny_plate, "plate")):
        train_run(case.id, "mgn", "smoke", out / kind, data_dir=root, epochs=1, progress=False,
                  evaluate=False, device="cpu")
        files[kind] = root / case.id / "test.npz"
    fine = get_case(f"{tiny_case[0].id}@r2")
    generate(fine, tiny_case[1], workers=1, progress=False)
    files["rod@r2"] = tiny_case[1] / fine.id / "test.npz"
    return out, files


def _rollout(run, file, out, capsys):
    from benchmarks.cli import main

    rc = main(["rollout", "--run", str(run), "--file", str(file), "--out", str(out),
               "--device", "cpu"])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_cli_rolls_a_rod_model_out_on_a_finer_rod(runs, tmp_path, capsys):
    out, files = runs
    rc, stdout, err = _rollout(out / "rod", files["rod@r2"], tmp_path / "p.npz", capsys)
    assert rc == 0, err
    assert "transfer" in stdout and "@r2" in stdout
    with np.load(tmp_path / "p.npz", allow_pickle=False) as z, \
            np.load(files["rod@r2"], allow_pickle=False) as truth:
        assert z["pos"].shape == truth["pos"].shape and z["pos"].shape[2] == 41
        assert np.isfinite(z["pos"]).all()


@pytest.mark.parametrize("run,file", [("rod", "plate"), ("plate", "rod")])
def test_cli_refuses_a_model_on_the_other_kind_of_mesh(runs, run, file, tmp_path, capsys):
    out, files = runs
    rc, _, err = _rollout(out / run, files[file], tmp_path / "p.npz", capsys)
    assert rc == 2
    assert "line mesh" in err and "triangle mesh" in err and "Traceback" not in err
    assert OLD_MESSAGE not in err
    assert not (tmp_path / "p.npz").exists()


def test_cli_refuses_mgn_another_time_step(runs, tmp_path, capsys):
    from groundtruth import store

    out, files = runs
    arrays = store.load_npz(files["rod@r2"])
    store.save_npz(tmp_path / "slow.npz", dict(arrays, t=arrays["t"] * 2))
    rc, _, err = _rollout(out / "rod", tmp_path / "slow.npz", tmp_path / "p.npz", capsys)
    assert rc == 2 and "trained to step" in err and "Traceback" not in err


def test_the_training_mesh_rollout_is_the_loaded_models(runs, tmp_path):
    """Through ``rollout_arrays`` on the run's own test split: no transfer, and the very
    rollout of the checkpoint's model (the code path before transfers existed)."""
    from benchmarks.suite.runs import _load_run, rollout_arrays
    from groundtruth import store

    out, files = runs
    pred, metrics = rollout_arrays(out / "rod", data_file=files["rod"], device="cpu")
    assert "transfer" not in metrics
    _, model, _ = _load_run(out / "rod", "best", "cpu")
    data = Trajectories.from_arrays(store.load_npz(files["rod"]))
    pos, _ = roll(model, data)
    assert np.array_equal(pred["pos"], pos.double().numpy())


def test_checkpoints_load_as_before(runs):
    """A transferred model is built from the checkpoint as it is (weights_only, no new
    entries): its state is the checkpoint's but for the mesh's own quantities."""
    from benchmarks.suite.runs import _load_run

    out, files = runs
    _, model, ck = _load_run(out / "rod", "best", "cpu")
    assert set(model.state_dict()) == set(ck["model"])
    assert isinstance(model, MODELS["mgn"].model_cls)


def test_implicit_energy_keeps_its_rollout_settings():
    model, _ = build("implicit_energy", rod_arrays(n_nodes=5))
    model.solver, model.on_newton_failure = "reference", "nan"
    fine = model.on_mesh(Mesh.from_arrays(rod_arrays(n_nodes=9)))
    assert isinstance(fine, ImplicitEnergy)
    assert (fine.solver, fine.on_newton_failure) == ("reference", "nan")
