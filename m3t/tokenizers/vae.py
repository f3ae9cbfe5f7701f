"""Conv1d residual VAE tokenizer of one modality (M3T Sec. 3.2, App. 0.D.1; MotionGPT's motion VAE).

Encoder: Conv1d(D -> W, k3) + ReLU, then ``down_stages`` x [Conv1d(W -> W, k4, stride 2), ResNet1D of
``depth`` dilated residual blocks (dilation growth ``dilation_growth``)], then Conv1d(W -> d, k3).
Decoder mirrors it: Conv1d(d -> W, k3) + ReLU, ``down_stages`` x [ResNet1D with reversed dilation,
nearest-neighbour upsample x2, Conv1d(W -> W, k3)], Conv1d(W -> W, k3) + ReLU, Conv1d(W -> D, k3).
Residual block: ``x + Conv1d_k1(ReLU(Conv1d_k3,dilated(ReLU(x))))``.

Inputs are standardised with per-dimension statistics of the training data (stored as buffers, so a
checkpoint is self-contained) and outputs mapped back; the loss of Eq. 6 is taken on the parameters.

Axis legend: B batch, T frames (a multiple of ``downsample``), D input dim, W width, d latent dim,
N = T / downsample tokens.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from m3t.tokenizers.config import QUANTIZERS, VAEConfig
from m3t.tokenizers.fsq import FSQ
from m3t.tokenizers.vq import EMAVQ, PlainVQ


@dataclass(frozen=True)
class TokenizerOutput:
    """recon: (B, T, D); indices: (B, N) int64; latents: (B, N, d) before quantisation; quant_loss: scalar
    (VQ commitment, 0 for FSQ); perplexity: scalar, of the batch's codes."""

    recon: torch.Tensor
    indices: torch.Tensor
    latents: torch.Tensor
    quant_loss: torch.Tensor
    perplexity: torch.Tensor


class ResBlock(nn.Module):
    def __init__(self, width: int, dilation: int):
        super().__init__()
        self.conv1 = nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation)
        self.conv2 = nn.Conv1d(width, width, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, W, T)
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


def resnet1d(width: int, depth: int, growth: int, reverse: bool) -> nn.Sequential:
    dilations = [growth**i for i in range(depth)]
    return nn.Sequential(*(ResBlock(width, d) for d in (dilations[::-1] if reverse else dilations)))


def encoder_layers(cfg: VAEConfig) -> nn.Sequential:
    w = cfg.width
    layers: list[nn.Module] = [nn.Conv1d(cfg.input_dim, w, 3, padding=1), nn.ReLU()]
    for _ in range(cfg.down_stages):
        layers += [nn.Conv1d(w, w, 4, stride=2, padding=1), resnet1d(w, cfg.depth, cfg.dilation_growth, False)]
    return nn.Sequential(*layers)


def decoder_layers(cfg: VAEConfig) -> nn.Sequential:
    w = cfg.width
    layers: list[nn.Module] = [nn.Conv1d(cfg.latent_dim, w, 3, padding=1), nn.ReLU()]
    for _ in range(cfg.down_stages):
        layers += [resnet1d(w, cfg.depth, cfg.dilation_growth, True), nn.Upsample(scale_factor=2, mode="nearest"),
                   nn.Conv1d(w, w, 3, padding=1)]
    layers += [nn.Conv1d(w, w, 3, padding=1), nn.ReLU(), nn.Conv1d(w, cfg.input_dim, 3, padding=1)]
    return nn.Sequential(*layers)


def make_quantizer(cfg: VAEConfig) -> FSQ | EMAVQ | PlainVQ:
    """The quantiser ``cfg.quantizer`` names (``tokenizer.quantizer``: one of :data:`QUANTIZERS`)."""
    if cfg.quantizer == "fsq":
        return FSQ(cfg.levels)
    if cfg.quantizer in ("vq", "vq_ema"):
        return EMAVQ(cfg.codebook_size, cfg.vq_code_dim, cfg.vq_decay, cfg.vq_beta, reset=cfg.quantizer == "vq")
    if cfg.quantizer == "vq_plain":
        return PlainVQ(cfg.codebook_size, cfg.vq_code_dim, cfg.vq_beta)
    raise ValueError(f"tokenizer.quantizer {cfg.quantizer!r} unknown; allowed: {', '.join(QUANTIZERS)}")


class MotionTokenizer(nn.Module):
    """One modality's VAE + quantiser: ``(B, T, D)`` parameters <-> ``(B, T / 4)`` token indices."""

    def __init__(self, cfg: VAEConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = encoder_layers(cfg)
        self.to_latent = nn.Conv1d(cfg.width, cfg.latent_dim, 3, padding=1)
        self.decoder = decoder_layers(cfg)
        self.quantizer = make_quantizer(cfg)
        self.register_buffer("mean", torch.zeros(cfg.input_dim))
        self.register_buffer("std", torch.ones(cfg.input_dim))

    @property
    def codebook_size(self) -> int:
        return self.cfg.codebook_size

    def set_normalisation(self, mean: torch.Tensor, std: torch.Tensor, floor: float = 1e-2) -> None:
        """Per-dimension statistics of the training data; ``floor`` keeps near-constant dims from exploding."""
        self.mean.copy_(mean)
        self.std.copy_(std.clamp_min(floor))

    def _check(self, x: torch.Tensor) -> None:
        if x.ndim != 3 or x.shape[-1] != self.cfg.input_dim:
            raise ValueError(f"tokenizer expects (B, T, {self.cfg.input_dim}) parameters, got {tuple(x.shape)}")
        if x.shape[1] % self.cfg.downsample:
            raise ValueError(f"sequence length {x.shape[1]} is not a multiple of {self.cfg.downsample}; "
                             "pad it with m3t.tokenizers.data.pad_to_multiple first")

    def hidden(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, D) -> (B, N, W) encoder features just before the latent projection (the SLR probe's input)."""
        self._check(x)
        h = self.encoder(((x - self.mean) / self.std).transpose(1, 2))  # (B, W, N)
        return h.transpose(1, 2)

    def encode_latents(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, D) -> (B, N, d) continuous latents."""
        h = self.hidden(x).transpose(1, 2)  # (B, W, N)
        return self.to_latent(h).transpose(1, 2)

    def decode_codes(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, N, d) quantised codes -> (B, N * downsample, D) parameters."""
        out = self.decoder(codes.transpose(1, 2)).transpose(1, 2)  # (B, T, D)
        return out.float() * self.std + self.mean

    def forward(self, x: torch.Tensor) -> TokenizerOutput:
        latents = self.encode_latents(x)
        q = self.quantizer(latents)
        recon = self.decode_codes(q.codes.to(latents.dtype))
        return TokenizerOutput(recon, q.indices, latents, q.loss, q.perplexity)

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, D) parameters -> (B, N) int64 token indices."""
        return self.quantizer(self.encode_latents(x)).indices

    @torch.no_grad()
    def decode(self, indices: torch.Tensor) -> torch.Tensor:
        """(B, N) int64 token indices -> (B, N * downsample, D) parameters."""
        return self.decode_codes(self.quantizer.indices_to_codes(indices))


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
