"""MeshGraphNet trained through its own short rollouts (``mgn_unrolled``): its config, presets
and model.

The network, features, normalisers, step and rollout are MeshGraphNet's
(``meshodenet.gnn.mgn``); only the training loss differs. MeshGraphNet learns one step from
two true frames and, rolled out, drifts on its own errors; MeshODENet is trained on rollouts of
many intervals and drifts less but is worse one step ahead (docs/TRAINING.md). Here a sample is
a window of ``unroll`` steps: from the true frames ``k - 1, k`` (with MeshGraphNet's training
noise on frame ``k``) the model steps ``unroll`` times on its own predictions, and the loss,
backpropagated through the whole window, is the mean over its steps ``j = 1 .. unroll`` of

.. math::
    \\frac{1}{|F|} \\sum_{i \\in F} \\Big| \\frac{\\hat x_{k+j,i} - x_{k+j,i}}
        {\\sigma_a \\, \\Delta t^2 \\, j (j + 1) / 2} \\Big|^2 ,

``F`` the free nodes, ``sigma_a`` the acceleration normaliser (per component, 1 where the data
does not move, those components left out). A constant error ``delta`` of the normalised
acceleration displaces frame ``k + j`` by ``sigma_a delta dt^2 j (j + 1) / 2``, so every step
of the window weighs the same for it, and with ``unroll = 1`` the loss is MeshGraphNet's
exactly. Step ``j = 1`` targets frame ``k + 1`` moved by the noise as MeshGraphNet does; the
later steps target the true frames.

One training sample is (trajectory, start ``k``), ``k = 0 .. T - 1 - unroll``. A batch of
``n`` samples trains on its first ``ceil(n / unroll)`` windows, so that an optimizer step
costs about what a one-step batch of ``n`` costs (the trainer's ``batch_size`` and
``max_batches`` mean the same budget as MeshGraphNet's). ``one_step_epochs``: the first so
many epochs train MeshGraphNet's one-step loss on whole batches (a curriculum: one-step
pretraining, then windows).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from meshodenet.gnn import network
from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig, mgn_presets
from meshodenet.mesh.data import Trajectories
from meshodenet.training.presets import check_int, check_preset


@dataclass(frozen=True)
class UnrolledMGNConfig(MeshGraphNetConfig):
    """``MeshGraphNetConfig`` plus ``unroll``: steps per training window (1: MeshGraphNet's
    one-step loss), and ``one_step_epochs``: epochs of one-step training before the windows."""

    unroll: int = 8
    one_step_epochs: int = 0

    def __post_init__(self):
        super().__post_init__()
        for name, lo in (("unroll", 1), ("one_step_epochs", 0)):
            check_int(self, name, lo)


class UnrolledMGN(MeshGraphNet):
    """MeshGraphNet with the unrolled training loss of the module doc; shapes and buffers as
    ``MeshGraphNet``."""

    name = "mgn_unrolled"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.epoch = 0

    def start_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    @property
    def window(self) -> int:
        """Steps per training window in the current epoch (1 during ``one_step_epochs``)."""
        return 1 if self.epoch < self.config.one_step_epochs else self.config.unroll

    def n_training_samples(self, data: Trajectories) -> int:
        return len(data) * max(data.n_frames - self.window, 0)

    def training_loss(self, data, samples, generator=None):
        """The module doc's loss; in one-step epochs (``window == 1``) MeshGraphNet's own.
        The window is stepped in displacements from the true start frame ``x_k``, so that
        the small second differences are not rounded at the positions' scale."""
        K = self.window
        if K == 1:
            return super().training_loss(data, samples, generator)
        self._check_dt(data.t, "training data t")
        if data.n_frames <= K:
            raise ValueError(f"UnrolledMGNConfig.unroll = {K} needs trajectories of more than "
                             f"{K} frames; these have {data.n_frames}")
        samples = samples.to(data.pos.device)[:-(-len(samples) // K)]
        traj, k = samples // (data.n_frames - K), samples % (data.n_frames - K)
        _, x_prev, x0, _ = self._frames(data, traj * (data.n_frames - 1) + k)
        ctx = self.context(data.youngs[traj], x0.dtype)
        free = ctx.batch.free.reshape(len(traj), -1, 1)
        active = self.active.to(x0.dtype)
        u, shift = self._add_noise(torch.zeros_like(x0), torch.zeros_like(x0), free * active,
                                   generator)
        ahead = data.pos[traj[:, None], k[:, None] + torch.arange(1, K + 1, device=k.device)]
        targets = ahead - x0[:, None]  # (S, K, N, 3) displacements from x_k
        targets[:, 0] += shift  # step 1 corrects the noise as MeshGraphNet's target does
        targets = targets.transpose(0, 1).reshape(K, -1, 3)
        x0, u, u_prev = x0.reshape(-1, 3), u.reshape(-1, 3), (x_prev - x0).reshape(-1, 3)
        std = torch.where(active > 0, ctx.acc_std, torch.ones_like(ctx.acc_std))
        gnn = None if self.engine == "reference" else network.FastGNN(self.gnn, ctx, self.config.activation)
        moving = ctx.batch.free.bool()
        n_free = ctx.batch.free.sum().clamp_min(1)
        total = x0.new_zeros(())
        for j in range(1, K + 1):
            a = self(x0 + u, x0 + u_prev, ctx, gnn) * ctx.acc_std + ctx.acc_mean
            u, u_prev = torch.where(moving, 2 * u - u_prev + a * ctx.dt ** 2, u), u
            e = (u - targets[j - 1]) / (std * ctx.dt ** 2 * (j * (j + 1) / 2))
            total = total + ((e ** 2 * active).sum(-1, keepdim=True) * ctx.batch.free).sum()
        return total / (K * n_free)


def unrolled_mgn_presets(preset: str, kind: str) -> tuple:
    """``(TrainConfig, UnrolledMGNConfig)`` of ``preset``: MeshGraphNet's (``mgn_presets``)
    with windows of ``unroll = 8`` steps; ``quick`` trains one-step until MeshGraphNet's
    learning-rate milestone and on windows after it (docs/MGN.md, "MeshGraphNet through its
    own rollouts"), ``paper`` on windows throughout; ``smoke`` unrolls 3 steps after one one-step epoch."""
    check_preset(preset)
    train, cfg = mgn_presets(preset, kind)
    extra = {}
    if preset == "quick":
        extra = dict(one_step_epochs=train.lr_milestones[0])
    elif preset == "smoke":
        extra = dict(unroll=3, one_step_epochs=1)
    return train, UnrolledMGNConfig(**{**dataclasses.asdict(cfg), **extra})


__all__ = ["UnrolledMGN", "UnrolledMGNConfig", "unrolled_mgn_presets"]
