"""Device handling without a GPU: ``--device`` parsing and errors, the kernel pins per device,
and every model trained and rolled out on a CUDA device emulated on the CPU
(``tests/fakecuda.py``), which fails where a real GPU would refuse to mix devices. The real
GPU checks are in ``tests/test_gpu.py`` (marker ``gpu``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.conftest import rod_arrays, strip_arrays
from tests.fakecuda import DeviceMismatch, FakeCuda, label, label_cpu

MODELS = ("meshodenet", "mgn", "meshodenet_imex", "mgn_unrolled", "implicit_energy",
          "implicit_energy_dissipation")


# --- the emulation itself -------------------------------------------------------------------
def test_fake_cuda_refuses_what_cuda_refuses():
    """The emulation raises where CUDA does, and lets through what CUDA allows."""
    with FakeCuda():
        a, b = torch.ones(3, device="cuda"), torch.ones(3)
        assert a.device.type == "cuda" and b.device.type == "cpu"
        for bad in (lambda: a + b, lambda: a.index_select(0, torch.tensor([0])),
                    lambda: torch.randn(3, generator=torch.Generator(), device="cuda"),
                    lambda: a.numpy(), lambda: label_cpu(torch.nn.Linear(3, 2))(a[None])):
            with pytest.raises(DeviceMismatch):
                bad()
        assert label(a + torch.tensor(2.0)) == "cuda"  # a CPU scalar beside CUDA tensors
        assert label(a[torch.tensor([0, 2])]) == "cuda"  # CPU indices into a CUDA tensor
        moved = b.to(a.device)
        assert label(moved) == "cuda" and label(b) == "cpu"
        lin = label_cpu(torch.nn.Linear(3, 2)).to("cuda")
        lin(a[None]).sum().backward()
        assert label(lin.weight) == label(lin.weight.grad) == "cuda"


# --- every model on the emulated GPU --------------------------------------------------------
def _train_and_roll_out(model_id, arrays, tmp_path, **model_changes):
    """``train_resolved``'s order on the emulated device: data there, the model built from it
    and moved there, one epoch of ``fit`` (training, validation, checkpoints), a rollout."""
    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.registry import get_model_spec
    from meshodenet.training.train import fit

    spec = get_model_spec(model_id)
    mesh = Mesh.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    tc = dataclasses.replace(tc, epochs=1, max_batches=2)
    mc = dataclasses.replace(mc, **model_changes)
    with FakeCuda() as mode:
        data = Trajectories.from_arrays(arrays, device="cuda")
        train, val = data.subset(torch.arange(len(data) - 1)), data.subset(torch.tensor([-1]))
        torch.manual_seed(0)
        model = label_cpu(spec.build(mesh, mc, train)).to("cuda")
        assert all(label(p) == "cuda" for p in model.parameters())
        result = fit(model, train, val, tc, tmp_path, progress=False)
        pos, vel = model.rollout_all(val)
    assert label(pos) == label(vel) == "cuda" and mode.ops > 100
    assert result.epochs_run == 1 and (tmp_path / "last.pt").exists()
    return pos


@pytest.mark.parametrize("kind", ["rod", "strip"])
@pytest.mark.parametrize("model_id", MODELS)
def test_every_model_trains_and_rolls_out_on_an_emulated_gpu(model_id, kind, tmp_path):
    arrays = rod_arrays(B=3, T=7) if kind == "rod" else strip_arrays(B=3, T=7)
    pos = _train_and_roll_out(model_id, arrays, tmp_path)
    assert pos.shape == (1, 7, arrays["pos"].shape[2], 3)


@pytest.mark.parametrize("model_id", ["meshodenet", "meshodenet_imex"])
def test_weighted_losses_and_release_on_an_emulated_gpu(model_id, tmp_path):
    """The options of the ``quick`` presets off in ``smoke``: frames weighted by their
    no-motion loss (its weights were once left on the CPU), the release step's loss, windows
    started at the release, the logarithmic modulus and the rest coordinates."""
    _train_and_roll_out(model_id, rod_arrays(B=3, T=7), tmp_path, frame_weight=0.5,
                        release_weight=0.05, release_fraction=0.5, youngs_feature="log",
                        rest_position=True)


@pytest.mark.parametrize("grad_mode", ["direct", "adjoint"])
def test_meshodenet_gradient_modes_on_an_emulated_gpu(grad_mode, tmp_path):
    """The reference solvers (direct backpropagation through torch ops, torchdiffeq's
    adjoint) besides the fast engine's ``checkpoint``."""
    _train_and_roll_out("meshodenet", rod_arrays(B=3, T=7), tmp_path, grad_mode=grad_mode)


def test_mgn_noise_and_reference_engine_on_an_emulated_gpu(tmp_path):
    """MeshGraphNet's training noise (drawn from the trainer's CPU generator, then moved) and
    the module-by-module engine with PyG's scatter."""
    _train_and_roll_out("mgn", rod_arrays(B=3, T=7), tmp_path, noise=0.03, engine="reference")


# --- --device ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["gpu", "cuda:x", "cpu:0", "CUDA", ""])
def test_a_bad_device_name_is_one_line(name):
    from benchmarks.suite.runs import pick_device

    with pytest.raises(ValueError, match="is not a device; valid: auto, cpu, cuda, cuda:K"):
        pick_device(name)


def test_auto_picks_cuda_when_torch_sees_it(monkeypatch):
    from benchmarks.suite.runs import pick_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert pick_device("auto") == torch.device("cuda")
    assert pick_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(ValueError, match="sees 2 CUDA device"):
        pick_device("cuda:2")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert pick_device("auto") == torch.device("cpu")


@pytest.mark.parametrize("argv", [["train", "--case", "rod_falling", "--out", "{tmp}/r"],
                                  ["rollout", "--run", "{tmp}/r", "--out", "{tmp}/p.npz"],
                                  ["run", "--suite", "smoke", "--results", "{tmp}/res"],
                                  ["bench", "--no-memory"], ["bench", "train"]])
def test_cuda_without_a_gpu_is_a_one_line_error(argv, tmp_path, capsys, monkeypatch):
    """``--device cuda`` where torch sees no GPU: exit 2, one line naming the flag, before any
    work (no run directory, no data generated)."""
    from benchmarks.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    if argv[0] == "rollout":  # a run directory for the rollout to find
        (tmp_path / "r").mkdir()
        (tmp_path / "r" / "config.json").write_text("{}")
    assert main(argv + ["--device", "cuda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device 'cuda' but torch sees no CUDA device" in err[0]
    assert not (tmp_path / "r").exists() or argv[0] == "rollout"
    assert not (tmp_path / "res").exists()


def test_torch_kernel_pins_are_skipped_for_cuda_only(monkeypatch):
    """CPU runs pin torch's kernels (results reproducible across x86-64 machines); a run on
    CUDA keeps only OpenBLAS's pin (the ground truth's solvers run on the CPU); ``auto``
    pins (it is decided after torch loads)."""
    import platform

    from benchmarks.suite import procs

    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    monkeypatch.delenv("MESHBENCH_NO_PIN", raising=False)
    for k in procs.REPRO_ENV:
        monkeypatch.delenv(k, raising=False)
    assert set(procs.repro_env("cpu")) == set(procs.repro_env("auto")) == set(procs.REPRO_ENV)
    assert set(procs.repro_env()) == set(procs.REPRO_ENV)
    assert set(procs.repro_env("cuda:1")) == {"OPENBLAS_CORETYPE"}
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx512")  # the user's own setting stays
    assert procs.repro_env("cpu")["ATEN_CPU_CAPABILITY"] == "avx512"


def test_fast_engine_tape_budget_per_device(monkeypatch):
    """The CPU keeps ``TAPE_BUDGET_BYTES`` of activations; a GPU a share of its free memory
    (never less than the CPU's)."""
    from meshodenet.gnn import fast

    assert fast.tape_budget(torch.device("cpu")) == fast.TAPE_BUDGET_BYTES
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda d=None: (40 * 2**30, 80 * 2**30))
    assert fast.tape_budget(torch.device("cuda")) == int(fast.TAPE_GPU_FRACTION * 40 * 2**30)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda d=None: (2**20, 80 * 2**30))
    assert fast.tape_budget(torch.device("cuda")) == fast.TAPE_BUDGET_BYTES


def test_train_on_cuda_records_the_device(tiny_case, tmp_path, monkeypatch):
    """``meshbench train --device cuda`` (emulated): the run trains there and its session,
    whence ``runs.csv``'s ``device`` column, says ``cuda``."""
    import json

    from benchmarks.suite.runs import train_run

    case, root = tiny_case
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with FakeCuda():
        train_run(case.id, "meshodenet", "smoke", tmp_path / "r", data_dir=root, epochs=1,
                  device="cuda", progress=False, evaluate=False)
    sessions = json.loads((tmp_path / "r" / "sessions.json").read_text())
    assert [s["device"] for s in sessions] == ["cuda"]


def test_bench_sections_run_on_an_emulated_gpu():
    """``meshbench bench --device cuda``'s work in this process: every regime, the surrogate's
    rollouts and MeshGraphNet's step and rollout, with the model and data on the device."""
    from benchmarks.cost import enginebench as eb

    with FakeCuda():
        for regime in eb.REGIMES:
            r = eb.Regime("rod1", regime, "current", 2, "cuda")
            assert label(next(r.model.parameters())) == "cuda" and r.run(1) >= 1
        surrogate = eb._surrogate("rod_falling", "current", 2, 1, "cuda")
        mgn = eb.mgn_bench("rod_falling", ["current"], rounds=1, log=lambda m: None,
                           device="cuda")
    assert surrogate["batch"] == 2 and mgn["current"]["step_s"] > 0
