"""Shared fixtures: a tiny network config that trains in seconds."""

from __future__ import annotations

import pytest

from mocaprig.process.democap.config import DemocapConfig


@pytest.fixture
def tiny_config() -> DemocapConfig:
    """A very small network on 64×64 renders (16×16 heat maps)."""
    return DemocapConfig(
        name="tiny",
        input_px=64,
        stem_channels=8,
        feature_channels=8,
        width=4,
        stage_branches=(2,),
        stage_modules=(1,),
        stage_units=(1,),
        batch_size=4,
        samples_per_epoch=8,
    )
