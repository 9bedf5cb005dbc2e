"""Encoder, decoder, preprocessing and the temporal embedding: shapes, dtypes and the embedding's conventions."""

from __future__ import annotations

import math

import pytest
import torch

from model.networks import Decoder, Encoder, preprocess
from model.temporal import TemporalEmbedding


def test_preprocess_maps_uint8_to_centred_float():
    frames = torch.tensor([0, 128, 255], dtype=torch.uint8)
    out = preprocess(frames)
    assert out.dtype == torch.float32
    assert torch.allclose(out, torch.tensor([-0.5, 128 / 255 - 0.5, 0.5]))
    with pytest.raises(TypeError, match="uint8"):
        preprocess(frames.float())


def test_encoder_decoder_shapes_with_leading_dims():
    encoder, decoder = Encoder(width=8, embed_dim=40), Decoder(feat_dim=30, width=8)
    images = preprocess(torch.randint(0, 256, (2, 5, 3, 64, 64), dtype=torch.uint8))
    embed = encoder(images)
    assert embed.shape == (2, 5, 40) and embed.dtype == torch.float32
    out = decoder(torch.randn(2, 5, 30))
    assert out.shape == (2, 5, 3, 64, 64) and out.dtype == torch.float32


def test_networks_have_three_residual_blocks_each():
    from model.networks import ResidualBlock

    for net in (Encoder(width=8), Decoder(feat_dim=10, width=8)):
        assert sum(isinstance(m, ResidualBlock) for m in net.modules()) == 3


def vaswani_row(position: float, dim: int) -> torch.Tensor:
    row = torch.zeros(dim)
    for i in range(0, dim, 2):
        angle = position / 10000 ** (i / dim)
        row[i], row[i + 1] = math.sin(angle), math.cos(angle)
    return row


def test_absolute_embedding_is_the_vaswani_row():
    embedding = TemporalEmbedding(dim=16, mode="absolute")
    out = embedding(torch.tensor([1, 3]))
    assert out.shape == (2, 16) and out.dtype == torch.float32
    assert torch.allclose(out[0], vaswani_row(1, 16), atol=1e-6)
    assert torch.allclose(out[1], vaswani_row(3, 16), atol=1e-6)


def test_relative_embedding_encodes_k_over_t():
    embedding = TemporalEmbedding(dim=16, mode="relative", reference_length=60)
    gaps = torch.tensor([[0, 2, 4]])
    out = embedding(gaps, torch.tensor([[30]]))  # positions 0, 4, 8
    assert out.shape == (1, 3, 16)
    assert torch.allclose(out[0, 2], vaswani_row(8.0, 16), atol=1e-5)
    # the same proportion k / T gives the same embedding whatever the clip length
    assert torch.allclose(embedding(torch.tensor([3]), torch.tensor([45])), embedding(torch.tensor([2]), torch.tensor([30])))
    assert not torch.allclose(embedding(torch.tensor([2]), torch.tensor([45])), embedding(torch.tensor([2]), torch.tensor([30])))


def test_temporal_embedding_refuses_bad_settings():
    with pytest.raises(ValueError, match="mode"):
        TemporalEmbedding(16, mode="learned")
    with pytest.raises(ValueError, match="even"):
        TemporalEmbedding(15)
    with pytest.raises(ValueError, match="num_frames"):
        TemporalEmbedding(16, mode="relative")(torch.tensor([1]))
