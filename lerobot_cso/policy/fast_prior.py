"""Inference-only skill sampling: the prior's decode loop with a preallocated KV cache and fewer ops per token.

``FastSkillSampler`` samples exactly what ``SkillPrior.sample`` samples (same tokens, same random stream, the
log-probs of the filtered distribution), but keeps keys and values in one static buffer, needs no attention mask
for single-token steps and skips the dropout calls. Its linear layers run on the prior's own fp32 weights
(``weights="float32"``, numerically equivalent) or on a per-output-channel int8 copy of them
(``weights="int8"``, bf16 activations through ``torch._weight_int8pack_mm``: a quarter of the bytes streamed per
token, not equivalent — measured in ``tests/test_decode_fast.py`` and ``benchmarks/decode_latency.py``).
It never computes gradients; training keeps using ``SkillPrior``.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from lerobot_cso.policy.skill_prior import SkillPrior, draw_tokens, filtered_log_probs
from lerobot_cso.sampling import FULL, Sampling

WeightFormat = Literal["float32", "int8"]
WEIGHT_FORMATS: tuple[str, ...] = ("float32", "int8")


class Int8Linear:
    """Weight-only int8 linear: symmetric per-output-channel scales, bf16 activations, fp32 bias and output."""

    def __init__(self, linear: nn.Linear) -> None:
        weight = linear.weight.detach().float()
        scale = weight.abs().amax(dim=1).clamp(min=1e-12) / 127
        self.weight = (weight / scale[:, None]).round().clamp(-127, 127).to(torch.int8).contiguous()
        self.scale = scale.to(torch.bfloat16)
        self.bias = linear.bias.detach().float().clone()

    def __call__(self, x: Tensor) -> Tensor:
        flat = x.reshape(-1, x.shape[-1]).to(torch.bfloat16)
        y = torch._weight_int8pack_mm(flat, self.weight, self.scale).float() + self.bias
        return y.view(*x.shape[:-1], -1)


def _linear(linear: nn.Linear, weights: WeightFormat) -> nn.Linear | Int8Linear:
    return Int8Linear(linear) if weights == "int8" else linear


class FastSkillSampler:
    """Decode-loop copy of a ``SkillPrior`` for inference (``weights``: 'float32' shares the prior's tensors)."""

    def __init__(self, prior: SkillPrior, weights: WeightFormat = "float32") -> None:
        if weights not in WEIGHT_FORMATS:
            raise ValueError(f"weights must be one of {WEIGHT_FORMATS}, got {weights!r}")
        self.prior = prior
        self.weights = weights
        self.layers = [
            (
                block.ln1,
                _linear(block.attn.qkv, weights),
                _linear(block.attn.proj, weights),
                block.ln2,
                _linear(block.mlp[0], weights),
                _linear(block.mlp[2], weights),
            )
            for block in prior.blocks
        ]
        self.head = _linear(prior.head, weights)
        self.heads = prior.blocks[0].attn.heads

    def _step(self, x: Tensor, keys: Tensor, values: Tensor, pos: int) -> Tensor:
        """Run x (B, T, dim) at positions pos … pos+T−1, writing the cache; logits (B, V) of the last one."""
        b, length, dim = x.shape
        end = pos + length
        for i, (ln1, qkv, proj, ln2, fc1, fc2) in enumerate(self.layers):
            q, k, v = qkv(ln1(x)).view(b, length, 3, self.heads, dim // self.heads).permute(2, 0, 3, 1, 4)
            keys[i, :, :, pos:end] = k
            values[i, :, :, pos:end] = v
            # The new queries see every cached key; among themselves they are causal (a 1-token step needs no
            # mask, the first step starts at position 0 so is_causal is exactly the prior's mask).
            y = F.scaled_dot_product_attention(q, keys[i, :, :, :end], values[i, :, :, :end], is_causal=length > 1)
            x = x + proj(y.transpose(1, 2).reshape(b, length, dim))
            x = x + fc2(F.gelu(fc1(ln2(x))))
        return self.head(self.prior.ln_f(x[:, -1]))

    @torch.no_grad()
    def sample(
        self, context: Tensor, sampling: Sampling = FULL, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """Same contract as ``SkillPrior.sample``: token ids (B, n) and their filtered log-probs (B, n)."""
        prior = self.prior
        b, prefix, dim = context.shape
        shape = (len(self.layers), b, self.heads, prefix + prior.n_tokens, dim // self.heads)
        keys = torch.empty(shape, dtype=context.dtype, device=context.device)
        values = torch.empty_like(keys)
        x = torch.cat([context, prior._embed(prior._start(context), 0)], dim=1)
        pos, tokens, log_probs = 0, [], []
        for j in range(prior.n_tokens):
            logp = filtered_log_probs(self._step(x, keys, values, pos), sampling.temperature, sampling.top_k)
            pos += x.shape[1]
            token = draw_tokens(logp, sampling.greedy, generator)
            tokens.append(token)
            log_probs.append(logp.gather(-1, token))
            if j + 1 < prior.n_tokens:
                x = prior._embed(token, j + 1)
        return torch.cat(tokens, dim=1), torch.cat(log_probs, dim=1)
