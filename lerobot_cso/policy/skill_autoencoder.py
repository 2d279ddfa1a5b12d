"""QueST skill autoencoder: a chunk of actions ⇄ a short sequence of FSQ tokens."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from vector_quantize_pytorch import FSQ


def sinusoidal_positions(length: int, dim: int) -> Tensor:
    """Fixed sinusoidal position encodings, shape (length, dim)."""
    position = torch.arange(length, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    table = torch.zeros(length, dim)
    table[:, 0::2] = torch.sin(position * freq)
    table[:, 1::2] = torch.cos(position * freq[: dim // 2])
    return table


def causal_mask(length: int, device: torch.device | None = None) -> Tensor:
    """Boolean attention mask, True where attention is forbidden (future positions)."""
    return torch.ones(length, length, dtype=torch.bool, device=device).triu(1)


class CausalConvBlock(nn.Module):
    """Conv1d that only sees the past (left padding), then GroupNorm and Mish."""

    def __init__(self, dim: int, kernel: int, stride: int, groups: int = 8) -> None:
        super().__init__()
        self.pad = kernel - 1
        self.conv = nn.Conv1d(dim, dim, kernel, stride=stride)
        self.norm = nn.GroupNorm(groups, dim)
        self.act = nn.Mish()

    def forward(self, x: Tensor) -> Tensor:
        x = nn.functional.pad(x, (self.pad, 0))
        return self.act(self.norm(self.conv(x)))


def _transformer_layer(cls: type, dim: int, heads: int, dropout: float) -> nn.Module:
    return cls(dim, heads, 4 * dim, dropout, activation="gelu", batch_first=True, norm_first=True)


class SkillAutoencoder(nn.Module):
    """Action chunk (B, T, A) → FSQ tokens (B, T/F) → reconstructed chunk (B, T, A).

    Encoder: Linear → causal conv stack → causal transformer → FSQ. Decoder: transformer whose queries are the
    fixed sinusoidal positions of the T actions, cross-attending to the token codes → Linear.
    """

    def __init__(
        self,
        action_dim: int,
        chunk_size: int,
        dim: int,
        conv_kernels: list[int],
        conv_strides: list[int],
        encoder_layers: int,
        decoder_layers: int,
        heads: int,
        dropout: float,
        fsq_levels: list[int],
    ) -> None:
        super().__init__()
        self.chunk_size = chunk_size
        self.input_proj = nn.Linear(action_dim, dim)
        self.convs = nn.Sequential(
            *[CausalConvBlock(dim, k, s) for k, s in zip(conv_kernels, conv_strides, strict=True)]
        )
        self.encoder = nn.TransformerEncoder(
            _transformer_layer(nn.TransformerEncoderLayer, dim, heads, dropout),
            encoder_layers,
            enable_nested_tensor=False,
        )
        self.quantizer = FSQ(levels=list(fsq_levels), dim=dim)
        self.decoder = nn.TransformerDecoder(
            _transformer_layer(nn.TransformerDecoderLayer, dim, heads, dropout), decoder_layers
        )
        self.action_head = nn.Linear(dim, action_dim)
        self.n_tokens = chunk_size // math.prod(conv_strides)
        self.register_buffer("token_positions", sinusoidal_positions(self.n_tokens, dim), persistent=False)
        self.register_buffer("action_queries", sinusoidal_positions(chunk_size, dim), persistent=False)

    def encode(self, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Actions (B, T, A) → quantized codes (B, n, dim) and token ids (B, n) int64."""
        x = self.convs(self.input_proj(actions).transpose(1, 2)).transpose(1, 2)
        x = self.encoder(x + self.token_positions, mask=causal_mask(x.shape[1], x.device), is_causal=True)
        codes, indices = self.quantizer(x)
        return codes, indices.long()

    def decode_codes(self, codes: Tensor, n_actions: int | None = None) -> Tensor:
        """Token codes (B, n, dim) → the first ``n_actions`` (default all T) actions (B, n_actions, A).

        The decoder's self-attention is causal and its queries are fixed, so action i depends only on the
        codes and queries 0..i: decoding a prefix gives exactly the first actions of the full chunk.
        """
        n_actions = self.chunk_size if n_actions is None else n_actions
        queries = self.action_queries[:n_actions].expand(codes.shape[0], -1, -1)
        mask = causal_mask(n_actions, codes.device)
        return self.action_head(self.decoder(queries, codes, tgt_mask=mask, tgt_is_causal=True))

    def decode_tokens(self, tokens: Tensor, n_actions: int | None = None) -> Tensor:
        """Token ids (B, n) → actions (B, n_actions or T, A)."""
        return self.decode_codes(self.quantizer.indices_to_codes(tokens), n_actions)

    def forward(self, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Reconstruct a chunk; returns (reconstruction, token ids)."""
        codes, indices = self.encode(actions)
        return self.decode_codes(codes), indices
