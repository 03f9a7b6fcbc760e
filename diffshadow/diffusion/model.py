"""The weight-space transformer (paper §3.3, HyperDiffusion / G.pt): a GPT without the causal mask.

One token per SIREN parameter tensor (each weight matrix, each bias) — or, for a tensor with more values than
the model width, one per chunk of it (G.pt) — each with its own linear map into the model width and back
out; a timestep token and a light token appended in context; a learned positional embedding; pre-LayerNorm
blocks. It predicts the clean (standardised) weights x0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from diffshadow.siren import WeightLayout


@dataclass(frozen=True)
class TransformerConfig:
    n_layer: int = 4
    n_embd: int = 128
    n_head: int = 4
    light_freqs: int = 6  # NeRF positional encoding of the direction: sin/cos(2^k π w), k < light_freqs
    dropout: float = 0.0
    tensor_tokens: int = 1  # tokens (near-equal chunks) per tensor with more values than n_embd; 1: the paper


def token_sizes(sizes: list[int], tensor_tokens: int, width: int) -> list[int]:
    """The values per token: each tensor of `sizes` with more than `width` values split into `tensor_tokens`
    near-equal chunks (at most one value per chunk); the others whole."""
    out = []
    for size in sizes:
        n = min(tensor_tokens, size) if size > width else 1
        out += [size // n + (i < size % n) for i in range(n)]
    return out


PRESETS = {
    "paper": TransformerConfig(n_layer=12, n_embd=720, n_head=16),  # paper §3.4
    # SIRENs wider than 32 want a wider model, not a deeper one (tooth, width-64 SIRENs, geometry stage:
    # small 35.78 / 22.53 dB seen / unseen, 8 x 192 35.61 / 22.68, 4 x 384 36.84 / 23.78; a84b9d4)
    "medium": TransformerConfig(n_layer=4, n_embd=384, n_head=6),
    "small": TransformerConfig(n_layer=4, n_embd=192, n_head=4),  # CPU default for the tiny scene
    "tiny": TransformerConfig(n_layer=2, n_embd=64, n_head=2),  # tests
}


# ---------------------------------------------------------------- embedding layers


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal frequency embedding of integer timesteps (DDPM / DiT). (B,) → (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    return torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1) if dim % 2 else emb


def light_encoding(w: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """NeRF positional encoding of unit directions: (B, 3) → (B, 3 + 6·n_freqs)."""
    scales = (2.0 ** torch.arange(n_freqs, device=w.device, dtype=w.dtype)) * math.pi
    x = w[:, :, None] * scales  # (B, 3, F)
    return torch.cat([w, torch.sin(x).flatten(1), torch.cos(x).flatten(1)], dim=-1)


# ---------------------------------------------------------------- core model


class SelfAttention(nn.Module):
    """Multi-head self-attention over all tokens (no causal mask: weights attend across layers)."""

    def __init__(self, cfg: TransformerConfig):
        super().__init__()
        assert cfg.n_embd % cfg.n_head == 0, "n_embd must be a multiple of n_head"
        self.n_head = cfg.n_head
        self.qkv = nn.Linear(cfg.n_embd, 3 * cfg.n_embd)
        self.proj = nn.Linear(cfg.n_embd, cfg.n_embd)
        self.dropout = cfg.dropout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t, c = x.shape
        q, k, v = self.qkv(x).split(c, dim=2)
        q, k, v = (z.view(b, t, self.n_head, c // self.n_head).transpose(1, 2) for z in (q, k, v))  # (B, H, T, D)
        dropout = self.dropout if self.training else 0.0
        if q.dtype == torch.bfloat16 and q.device.type == "cpu":
            # PyTorch's CPU attention backward in bfloat16 took 5x its float32 time (6.2 against 1.2 ms a call at the
            # README's sizes): the bfloat16 step took 0.89x float32's with it, 0.78x with the attention in float32.
            # Back in bfloat16 after it, for a bfloat16 copy of the model (half-precision sampling)
            with torch.autocast("cpu", enabled=False):
                y = nn.functional.scaled_dot_product_attention(q.float(), k.float(), v.float(),
                                                               dropout_p=dropout).to(q.dtype)
        else:
            y = nn.functional.scaled_dot_product_attention(q, k, v, dropout_p=dropout)
        return self.proj(y.transpose(1, 2).reshape(b, t, c))


class MLP(nn.Module):
    def __init__(self, cfg: TransformerConfig):
        super().__init__()
        self.fc = nn.Linear(cfg.n_embd, 4 * cfg.n_embd)
        self.proj = nn.Linear(4 * cfg.n_embd, cfg.n_embd)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(nn.functional.gelu(self.fc(x)))


class LayerNorm(nn.LayerNorm):
    """nn.LayerNorm whose scale and shift are applied after the normalisation on a CPU, outside PyTorch's fused
    kernel, whose CPU backward adds their gradients in per-thread parts: the same parameters, and a training's
    bytes that do not depend on its thread count (train_diffusion at 1.03x the time; docs/numerics.md). CUDA keeps
    the fused kernel, one launch, the same on every run."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.device.type != "cpu":
            return super().forward(x)
        return torch.addcmul(self.bias, nn.functional.layer_norm(x, self.normalized_shape, eps=self.eps), self.weight)


class Block(nn.Module):
    """Pre-LayerNorm transformer block (GPT-2)."""

    def __init__(self, cfg: TransformerConfig):
        super().__init__()
        self.ln_1 = LayerNorm(cfg.n_embd)
        self.attn = SelfAttention(cfg)
        self.ln_2 = LayerNorm(cfg.n_embd)
        self.mlp = MLP(cfg)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.ln_1(x))
        return x + self.mlp(self.ln_2(x))


class WeightTransformer(nn.Module):
    """Noisy standardised SIREN weights (B, n_params), timestep (B,), light (B, 3) → predicted x0 (B, n_params)."""

    def __init__(self, layout: WeightLayout, cfg: TransformerConfig):
        super().__init__()
        self.layout = layout
        self.cfg = cfg
        d = cfg.n_embd
        self.sizes = token_sizes(layout.sizes, cfg.tensor_tokens, d)
        self.token_in = nn.ModuleList(nn.Linear(size, d) for size in self.sizes)
        self.token_out = nn.ModuleList(nn.Linear(d, size) for size in self.sizes)
        self.time_mlp = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        self.light_in = nn.Linear(3 + 6 * cfg.light_freqs, d)
        self.pos = nn.Parameter(torch.zeros(1, len(self.sizes) + 2, d))
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layer))
        self.ln_f = LayerNorm(d)
        self.initialize()
        self._group_tokens()

    def _group_tokens(self) -> None:
        """Tokens of one size share a batched product (`_tokens_in`, `_tokens_out`): the 24 tokens of a width-32
        SIREN have 4 sizes. The per-token maps stay the parameters (checkpoints and gradient clipping unchanged);
        the buffers below reorder weights and tokens between the layout's order and the groups'."""
        groups: dict[int, list[int]] = {}
        for i, size in enumerate(self.sizes):
            groups.setdefault(size, []).append(i)
        self.groups = list(groups.items())  # (size, token indices), in order of first appearance
        order = torch.tensor([i for _, tokens in self.groups for i in tokens])  # token indices in group order
        columns = torch.arange(sum(self.sizes)).split(self.sizes)  # each token's weight columns
        cols = torch.cat([columns[i] for i in order.tolist()])  # weight columns in group order
        # non-persistent: derived from the layout, so they follow .to(device) and stay out of the state dict
        for name, index in (("_cols", cols), ("_cols_back", torch.argsort(cols)), ("_tokens", order),
                            ("_tokens_back", torch.argsort(order))):
            self.register_buffer(name, index, persistent=False)

    @staticmethod
    def _stacked(maps: nn.ModuleList, tokens: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        if len(tokens) == 1:
            return maps[tokens[0]].weight[None], maps[tokens[0]].bias[None]
        return torch.stack([maps[i].weight for i in tokens]), torch.stack([maps[i].bias for i in tokens])

    def _tokens_in(self, x: torch.Tensor) -> torch.Tensor:
        """(B, n_params) → (B, T, d): each token's own linear map, one batched product per token size."""
        b, grouped, start, out = x.shape[0], x.index_select(1, self._cols), 0, []
        for size, tokens in self.groups:
            n = len(tokens)
            part = grouped[:, start:start + n * size].view(b, n, size).transpose(0, 1)  # (n, B, size)
            start += n * size
            w, bias = self._stacked(self.token_in, tokens)  # (n, d, size), (n, d)
            out.append(torch.baddbmm(bias[:, :, None], w, part.transpose(1, 2)))  # (n, d, B)
        return torch.cat(out).index_select(0, self._tokens_back).permute(2, 0, 1)

    def _tokens_out(self, h: torch.Tensor) -> torch.Tensor:
        """(B, T + 2, d) → (B, n_params): the weight tokens' maps back out, one batched product per size."""
        b, grouped, start, out = h.shape[0], h.index_select(1, self._tokens).transpose(0, 1), 0, []
        for size, tokens in self.groups:
            n = len(tokens)
            w, bias = self._stacked(self.token_out, tokens)  # (n, size, d), (n, size)
            y = torch.baddbmm(bias[:, :, None], w, grouped[start:start + n].transpose(1, 2))  # (n, size, B)
            start += n
            out.append(y.permute(2, 0, 1).reshape(b, n * size))
        return torch.cat(out, dim=1).index_select(1, self._cols_back)

    def initialize(self) -> None:
        """GPT-2 style: normal(0, 0.02) linears, zero biases; the output maps start at zero so the first
        prediction is the mean (standardised 0) rather than noise."""
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.pos, std=0.02)
        for m in self.token_out:
            nn.init.zeros_(m.weight)

    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def forward(self, x: torch.Tensor, t: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        # the encodings are computed in float32 (sin of 2^k π w), then cast to the network's dtype
        context = torch.stack([self.time_mlp(timestep_embedding(t, self.cfg.n_embd).to(x.dtype)),
                               self.light_in(light_encoding(light.float(), self.cfg.light_freqs).to(x.dtype))], dim=1)
        h = torch.cat([self._tokens_in(x), context], dim=1) + self.pos  # (B, T + 2, d)
        for block in self.blocks:
            h = block(h)
        return self._tokens_out(self.ln_f(h))  # (B, n_params)
