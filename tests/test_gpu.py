"""The CUDA path on a real GPU (marker ``gpu``; ``pytest -m gpu``, ``tox -e gpu``): a training
step and a rollout of every model agree between the CPU and CUDA in float64 to round-off, a
short training on CUDA lowers its loss, and ``meshbench train`` / ``bench`` run with
``--device cuda``. Skipped, with the reason, where torch sees no CUDA device (CI). The same
checks run CPU against CPU without the marker, so that the comparison itself is tested
everywhere; device bugs are also looked for without a GPU in ``tests/test_device.py``."""

from __future__ import annotations

import copy
import dataclasses
import json

import pytest
import torch

from tests.conftest import rod_arrays, strip_arrays

MODELS = ("meshodenet", "mgn", "meshodenet_imex", "mgn_unrolled", "implicit_energy",
          "implicit_energy_dissipation")
MESHES = {"rod": lambda: rod_arrays(B=4, T=9), "strip": lambda: strip_arrays(B=4, T=9)}
CUDA = torch.cuda.is_available()
needs_gpu = pytest.mark.skipif(
    not CUDA, reason=f"torch {torch.__version__} sees no CUDA device (CUDA build: "
    f"{torch.version.cuda or 'none'}); run on a GPU machine with `tox -e gpu`")
#: float64 on two devices: the same operations, summed in other orders (CUDA's index_add_ and
#: reductions), so equal to round-off amplified by a short rollout, far below float32's eps
RTOL, ATOL_REL = 1e-9, 1e-12


def _setup(model_id: str, arrays: dict):
    """A float64 model of ``model_id`` (``smoke`` preset, seeded) and its training data, on the
    CPU."""
    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.registry import get_model_spec

    spec = get_model_spec(model_id)
    mesh = Mesh.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    torch.manual_seed(0)
    return spec.build(mesh, mc, data).double(), data, tc


def _step_and_rollout(model, data, batch: int) -> dict:
    """Loss, every parameter's gradient of one training step (samples and noise from a seeded
    CPU generator, as the trainer's), and the rollout of every trajectory, on the CPU."""
    gen = torch.Generator().manual_seed(1)
    model.train()
    samples = torch.randperm(model.n_training_samples(data), generator=gen)[:batch]
    model.zero_grad(set_to_none=True)
    loss = model.training_loss(data, samples, gen)
    loss.backward()
    out = {"loss": loss.detach()}
    out.update({f"grad {n}": p.grad for n, p in model.named_parameters() if p.grad is not None})
    model.eval()
    out["rollout pos"], out["rollout vel"] = model.rollout_all(data)
    return {k: v.detach().cpu() for k, v in out.items()}


def compare_devices(model_id: str, arrays: dict, device: str) -> dict:
    """The largest relative difference per quantity of ``_step_and_rollout`` between the CPU
    and ``device`` (the same weights copied there); asserts they agree to ``RTOL``."""
    model, data, tc = _setup(model_id, arrays)
    other = copy.deepcopy(model).to(device)
    ref = _step_and_rollout(model, data, tc.batch_size)
    got = _step_and_rollout(other, data.to(device), tc.batch_size)
    assert set(got) == set(ref) and len(ref) > 3
    diffs = {}
    for k, r in ref.items():
        scale = float(r.abs().max()) if r.numel() else 0.0
        diffs[k] = float((got[k] - r).abs().max()) / max(scale, 1e-300) if r.numel() else 0.0
        torch.testing.assert_close(got[k], r, rtol=RTOL, atol=ATOL_REL * scale,
                                   msg=lambda m, k=k: f"{model_id} {k} on {device}: {m}")
    return diffs


def short_training(device: str, tmp_path) -> list:
    """Training losses of 6 epochs of MeshODENet (``smoke`` model, whole 8-interval rollouts of
    4 rods, lr 3e-3) on ``device``."""
    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.registry import get_model_spec
    from meshodenet.training.train import fit

    arrays = rod_arrays(B=5, T=9)
    spec = get_model_spec("meshodenet")
    mesh = Mesh.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    tc = dataclasses.replace(tc, epochs=6, lr=3e-3, batch_size=2, max_batches=0)
    mc = dataclasses.replace(mc, shooting=0)
    data = Trajectories.from_arrays(arrays, device=device)
    train, val = data.subset(torch.arange(4)), data.subset(torch.tensor([4]))
    torch.manual_seed(0)
    model = spec.build(mesh, mc, train).to(device)
    result = fit(model, train, val, tc, tmp_path, progress=False)
    return [row["train_loss"] for row in result.history]


# --- the comparison itself, everywhere ------------------------------------------------------
def test_the_comparison_is_exact_cpu_against_cpu():
    """``compare_devices`` with the CPU on both sides: the same numbers bit for bit."""
    diffs = compare_devices("meshodenet", MESHES["rod"](), "cpu")
    assert set(diffs.values()) == {0.0}


# --- on a GPU -------------------------------------------------------------------------------
@pytest.mark.gpu
@needs_gpu
@pytest.mark.parametrize("mesh", sorted(MESHES))
@pytest.mark.parametrize("model_id", MODELS)
def test_cpu_and_cuda_agree_in_float64(model_id, mesh):
    diffs = compare_devices(model_id, MESHES[mesh](), "cuda")
    print(f"{model_id} {mesh}: largest relative CPU/CUDA difference {max(diffs.values()):.2e}")


@pytest.mark.gpu
@needs_gpu
def test_a_short_training_on_cuda_lowers_the_loss(tmp_path):
    losses = short_training("cuda", tmp_path)
    assert losses[-1] < 0.8 * losses[0], losses


@pytest.mark.gpu
@needs_gpu
def test_meshbench_train_and_rollout_on_cuda(tiny_case, tmp_path):
    """``meshbench train --device cuda`` end to end: trains, evaluates the best checkpoint
    (loaded onto the GPU), records the device; the rollout command runs there too."""
    from benchmarks.cli import main

    case, root = tiny_case
    out = tmp_path / "run"
    assert main(["train", "--case", case.id, "--model", "meshodenet", "--preset", "smoke",
                 "--out", str(out), "--data-dir", str(root), "--device", "cuda",
                 "--no-progress"]) == 0
    assert json.loads((out / "sessions.json").read_text())[-1]["device"] == "cuda"
    assert json.loads((out / "test_metrics.json").read_text())["rmse_m"] > 0
    assert main(["rollout", "--run", str(out), "--out", str(tmp_path / "p.npz"),
                 "--data-dir", str(root), "--device", "cuda"]) == 0


@pytest.mark.gpu
@needs_gpu
def test_bench_on_cuda_reports_the_gpu(tmp_path):
    """A tiny ``meshbench bench --device cuda``: rates, the paper-epoch estimate with its peak
    GPU memory, and the device's name in the JSON."""
    from benchmarks.cli import main

    out = tmp_path / "gpu.json"
    assert main(["bench", "--device", "cuda", "--graphs", "rod1", "--regimes", "nograd,train",
                 "--rounds", "1", "--budget", "0.05", "--train-intervals", "2",
                 "--epoch-steps", "1", "--epoch-cases", "rod_falling", "--no-solver",
                 "--no-mgn", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["device"]["type"] == "cuda" and res["device"]["name"]
    assert res["graphs"]["rod1"]["regimes"]["train"]["current"]["cuda_peak_gb"] > 0
    assert res["epochs"]["rod_falling"]["current"]["cuda_peak_gb"] > 0
