"""QueST skill prior: an autoregressive GPT over FSQ tokens, conditioned on context tokens, with a KV cache."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from lerobot_cso.policy.skill_autoencoder import sinusoidal_positions
from lerobot_cso.sampling import FULL, Sampling

KVCache = list[tuple[Tensor, Tensor]]


def filtered_log_probs(logits: Tensor, temperature: float = 1.0, top_k: int | None = None) -> Tensor:
    """Log-probabilities of the distribution actually sampled from: logits / T, restricted to the top k."""
    logits = logits / temperature
    if top_k is not None and top_k < logits.shape[-1]:
        kth = logits.topk(top_k, dim=-1).values[..., -1:]
        logits = logits.masked_fill(logits < kth, float("-inf"))
    return logits.log_softmax(dim=-1)


def entropy(log_probs: Tensor) -> Tensor:
    """Entropy (nats) of each distribution ``log_probs`` (..., V) over its last axis; a token outside the top k
    (log-prob -inf) adds 0."""
    return torch.special.entr(log_probs.exp()).sum(dim=-1)


def token_logprob(log_probs: Tensor, tokens: Tensor) -> Tensor:
    """The log-prob (...) of each token id ``tokens`` (...) under its distribution ``log_probs`` (..., V)."""
    return log_probs.gather(-1, tokens.unsqueeze(-1)).squeeze(-1)


def draw_tokens(log_probs: Tensor, greedy: bool = False, generator: torch.Generator | None = None) -> Tensor:
    """One token id per row (B, 1) from log-probs (B, V): the argmax, or a draw by inverse CDF.

    One uniform number per row against the cumulative probabilities: the same distribution as
    ``torch.multinomial``, which draws an exponential for every one of the V entries (profiled at batch 48,
    V = 1 000: ≈ 1.1 ms per token step against ≈ 0.2 ms here); a token of probability 0 (outside the top k) is
    never drawn.
    """
    if greedy:
        return log_probs.argmax(dim=-1, keepdim=True)
    cdf = log_probs.exp().cumsum(dim=-1)
    u = torch.rand(cdf.shape[0], 1, generator=generator, dtype=cdf.dtype, device=cdf.device) * cdf[:, -1:]
    return torch.searchsorted(cdf, u, right=True).clamp_(max=cdf.shape[-1] - 1)


def skill_log_prob(token_log_probs: Tensor) -> Tensor:
    """Eq. 7: log π(Z_t | s_t) = Σ_j log π(z_t^j | s_t, z_t^{<j}); sums the last (token) dimension."""
    return token_log_probs.sum(dim=-1)


class CausalSelfAttention(nn.Module):
    """Multi-head causal self-attention that can append to and return a key/value cache."""

    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.dropout = dropout

    def forward(self, x: Tensor, past: tuple[Tensor, Tensor] | None) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        b, length, dim = x.shape
        q, k, v = (t.view(b, length, self.heads, dim // self.heads).transpose(1, 2) for t in self.qkv(x).split(dim, -1))
        if past is not None:
            k, v = torch.cat([past[0], k], dim=2), torch.cat([past[1], v], dim=2)
        offset = k.shape[2] - length
        # Query i (absolute position offset + i) may attend to keys 0 … offset + i.
        mask = torch.ones(length, k.shape[2], dtype=torch.bool, device=x.device).tril(offset)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=self.dropout if self.training else 0.0)
        return self.proj(y.transpose(1, 2).reshape(b, length, dim)), (k, v)


class Block(nn.Module):
    """Pre-norm transformer block (GELU MLP of width 4·dim)."""

    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.ln1 = nn.LayerNorm(dim)
        self.attn = CausalSelfAttention(dim, heads, dropout)
        self.ln2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim), nn.Dropout(dropout))

    def forward(self, x: Tensor, past: tuple[Tensor, Tensor] | None) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        attn, present = self.attn(self.ln1(x), past)
        x = x + attn
        return x + self.mlp(self.ln2(x)), present


class SkillPrior(nn.Module):
    """GPT over [context…, <start>, z1 … z_{n-1}] predicting z1 … z_n (token id ``vocab_size`` is <start>)."""

    def __init__(self, vocab_size: int, n_tokens: int, dim: int, layers: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.vocab_size = vocab_size
        self.n_tokens = n_tokens
        self.token_embedding = nn.Embedding(vocab_size + 1, dim)
        self.register_buffer("positions", sinusoidal_positions(n_tokens, dim), persistent=False)
        self.drop = nn.Dropout(dropout)
        self.blocks = nn.ModuleList([Block(dim, heads, dropout) for _ in range(layers)])
        self.ln_f = nn.LayerNorm(dim)
        self.head = nn.Linear(dim, vocab_size)

    def _embed(self, tokens: Tensor, start: int) -> Tensor:
        return self.token_embedding(tokens) + self.positions[start : start + tokens.shape[1]]

    def _run(self, x: Tensor, cache: KVCache | None) -> tuple[Tensor, KVCache]:
        present = []
        for i, block in enumerate(self.blocks):
            x, kv = block(x, None if cache is None else cache[i])
            present.append(kv)
        return self.head(self.ln_f(x)), present

    def _start(self, context: Tensor) -> Tensor:
        return torch.full((context.shape[0], 1), self.vocab_size, dtype=torch.long, device=context.device)

    def logits(self, context: Tensor, tokens: Tensor) -> Tensor:
        """Teacher-forced logits (B, n, V) for the tokens (B, n) given context (B, P, dim)."""
        inputs = torch.cat([self._start(context), tokens[:, :-1]], dim=1)
        x = self.drop(torch.cat([context, self._embed(inputs, 0)], dim=1))
        logits, _ = self._run(x, None)
        return logits[:, context.shape[1] :]

    @torch.no_grad()
    def sample(
        self,
        context: Tensor,
        sampling: Sampling = FULL,
        generator: torch.Generator | None = None,
        use_cache: bool = True,
    ) -> tuple[Tensor, Tensor]:
        """Sample n tokens; returns ids (B, n) and their log-probs under the filtered distribution (B, n)."""
        sequence = torch.cat([context, self._embed(self._start(context), 0)], dim=1)
        x, cache = self.drop(sequence), None
        tokens, log_probs = [], []
        for j in range(self.n_tokens):
            logits, present = self._run(x, cache)
            logp = filtered_log_probs(logits[:, -1], sampling.temperature, sampling.top_k)
            token = draw_tokens(logp, sampling.greedy, generator)
            tokens.append(token)
            log_probs.append(logp.gather(-1, token))
            if j + 1 == self.n_tokens:
                break
            step = self.drop(self._embed(token, j + 1))
            if use_cache:
                x, cache = step, present
            else:
                sequence = torch.cat([sequence, self._embed(token, j + 1)], dim=1)
                x = self.drop(sequence)
        return torch.cat(tokens, dim=1), torch.cat(log_probs, dim=1)
