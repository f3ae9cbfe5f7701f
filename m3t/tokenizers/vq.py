"""Vector quantisers: the VQ baselines that M3T compares FSQ against (Tab. 3), from strongest to plainest.

All three assign each latent to its nearest code (squared Euclidean distance), pass the gradient straight
through, put a commitment loss ``beta * ||z - sg(q)||^2`` on the encoder and initialise the codebook from the
first training batch, so that they differ in the codebook's update rule alone:

- ``vq`` (:class:`EMAVQ`, ``reset=True``), "strong VQ": the quantiser of T2M-GPT / SOKE. Codes are exponential
  moving averages of the latents assigned to them (no codebook gradient), and every code whose EMA usage
  count drops below ``reset_threshold`` is re-initialised to a randomly chosen latent of the current batch
  (its EMA statistics restart there). A reset code sits on the data by construction, so utilisation stays
  near 100 %.
- ``vq_ema`` (:class:`EMAVQ`, ``reset=False``): the same EMA updates, no reset. A code that stops being chosen
  keeps its place (its sum and count decay together) and stays dead.
- ``vq_plain`` (:class:`PlainVQ`): the VQ-VAE of van den Oord et al. (2017): the codebook is a parameter
  learned by the optimiser through the codebook loss ``||sg(z) - q||^2`` (weight 1); no EMA, no reset.

Under DDP the EMA sums and counts are all-reduced (the plain codebook's gradient is averaged by DDP like any
other), and the initial / reset candidates are broadcast from rank 0, so every rank keeps the same codebook.

Axis legend: ``...`` leading axes (batch, time), d code dim, K codebook size, N flattened latents.
"""
from __future__ import annotations

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn

from m3t.tokenizers.fsq import QuantizerOutput, batch_perplexity


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


class _NearestCodeVQ(nn.Module):
    """What the three share: the codebook's first-batch initialisation, nearest-code assignment, the forward
    pass. Subclasses hold ``codebook`` (K, d) and define :meth:`_update` and :meth:`_codebook_loss`."""

    codebook: torch.Tensor

    def __init__(self, codebook_size: int, dim: int, beta: float):
        super().__init__()
        self.codebook_size, self.dim, self.beta = int(codebook_size), int(dim), float(beta)
        self.register_buffer("initialised", torch.zeros((), dtype=torch.bool))
        self.last_resets = 0  # number of codes reset by the latest update (for logging and tests)

    def _candidates(self, flat: torch.Tensor) -> torch.Tensor:
        """K latents drawn from the batch (repeated when the batch is smaller than K), same on every rank."""
        repeats = -(-self.codebook_size // flat.shape[0])
        pool = flat.repeat(repeats, 1) if repeats > 1 else flat
        pool = pool + (0.01 / max(self.dim, 1) ** 0.5) * torch.randn_like(pool) * (repeats > 1)
        picked = pool[torch.randperm(pool.shape[0], device=flat.device)[: self.codebook_size]].contiguous()
        if _distributed():
            dist.broadcast(picked, src=0)
        return picked

    def nearest(self, flat: torch.Tensor) -> torch.Tensor:
        """(N, d) -> (N,) index of the nearest code (squared Euclidean distance)."""
        codebook = self.codebook.detach()
        distance = (flat.pow(2).sum(-1, keepdim=True) - 2 * flat @ codebook.T
                    + codebook.pow(2).sum(-1)[None])  # (N, K)
        return distance.argmin(dim=-1)

    @torch.no_grad()
    def _initialise(self, flat: torch.Tensor) -> None:
        self.codebook.copy_(self._candidates(flat))
        self.initialised.fill_(True)

    def _update(self, flat: torch.Tensor, indices: torch.Tensor) -> None:
        """Move the codebook after a training batch (EMA); nothing for a learned codebook."""

    def _codebook_loss(self, flat: torch.Tensor, quantised: torch.Tensor) -> torch.Tensor:
        """The loss that moves a learned codebook; 0 for EMA codebooks."""
        return flat.new_zeros(())

    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        if z.shape[-1] != self.dim:
            raise ValueError(f"VQ with code dim {self.dim} got latents with {z.shape[-1]} channels")
        flat = z.float().reshape(-1, self.dim)  # (N, d)
        if self.training and not bool(self.initialised):
            self._initialise(flat.detach())
        indices = self.nearest(flat.detach())
        quantised = self.codebook[indices]  # (N, d), taken before this batch's EMA update
        if self.training:
            quantised = quantised.clone()  # the EMA update below writes the codebook in place
            self._update(flat.detach(), indices)
        loss = self.beta * F.mse_loss(flat, quantised.detach()) + self._codebook_loss(flat, quantised)
        codes = (flat + (quantised - flat).detach()).reshape(z.shape)
        indices = indices.reshape(z.shape[:-1])
        return QuantizerOutput(codes, indices, loss, batch_perplexity(indices, self.codebook_size))

    def indices_to_codes(self, indices: torch.Tensor) -> torch.Tensor:
        """(...,) int64 -> (..., d) codebook vectors."""
        return self.codebook[indices.long()].detach()


class EMAVQ(_NearestCodeVQ):
    """EMA vector quantiser with ``codebook_size`` codes of dimension ``dim``; ``reset`` re-initialises dead
    codes (``vq``), without it they stay where they died (``vq_ema``)."""

    def __init__(self, codebook_size: int, dim: int, decay: float = 0.99, beta: float = 0.02,
                 reset_threshold: float = 1.0, reset: bool = True):
        super().__init__(codebook_size, dim, beta)
        self.decay, self.reset_threshold, self.reset = float(decay), float(reset_threshold), bool(reset)
        self.register_buffer("codebook", torch.zeros(self.codebook_size, self.dim))
        self.register_buffer("ema_sum", torch.zeros(self.codebook_size, self.dim))
        self.register_buffer("ema_count", torch.zeros(self.codebook_size))

    @torch.no_grad()
    def _update(self, flat: torch.Tensor, indices: torch.Tensor) -> None:
        onehot = F.one_hot(indices, self.codebook_size).type(flat.dtype)  # (N, K)
        code_sum, code_count = onehot.T @ flat, onehot.sum(0)  # (K, d), (K,)
        if _distributed():
            dist.all_reduce(code_sum)
            dist.all_reduce(code_count)
        self.ema_sum.mul_(self.decay).add_(code_sum, alpha=1 - self.decay)
        self.ema_count.mul_(self.decay).add_(code_count, alpha=1 - self.decay)
        if not self.reset:
            # an unused code's sum and count decay by the same factor: it stays put, until the count underflows
            # the division (after ~1,400 steps at decay 0.99), from where it is simply kept
            alive = (self.ema_count > 1e-6).unsqueeze(-1)
            self.codebook.copy_(torch.where(alive, self.ema_sum / self.ema_count.clamp_min(1e-6).unsqueeze(-1),
                                            self.codebook))
            return
        used = (self.ema_count >= self.reset_threshold).unsqueeze(-1)  # (K, 1)
        updated = self.ema_sum / self.ema_count.clamp_min(1e-6).unsqueeze(-1)
        self.codebook.copy_(torch.where(used, updated, self._candidates(flat)))
        # A reset code restarts its statistics at the threshold (otherwise its stale EMA sum would drag it
        # back towards where it died the next time it is chosen).
        self.ema_count.copy_(torch.where(used[:, 0], self.ema_count, self.reset_threshold))
        self.ema_sum.copy_(torch.where(used, self.ema_sum, self.codebook * self.reset_threshold))
        self.last_resets = int((~used).sum())

    @torch.no_grad()
    def _initialise(self, flat: torch.Tensor) -> None:
        super()._initialise(flat)
        self.ema_sum.copy_(self.codebook)
        self.ema_count.fill_(1.0)


class PlainVQ(_NearestCodeVQ):
    """VQ-VAE quantiser (``vq_plain``): a learned codebook moved only by the codebook loss ``||sg(z) - q||^2``."""

    def __init__(self, codebook_size: int, dim: int, beta: float = 0.02):
        super().__init__(codebook_size, dim, beta)
        self.codebook = nn.Parameter(torch.zeros(self.codebook_size, self.dim))

    def _codebook_loss(self, flat: torch.Tensor, quantised: torch.Tensor) -> torch.Tensor:
        return F.mse_loss(quantised, flat.detach())
