"""Shared fixtures: a tiny synthetic dataset in the renderer's format and tiny training configurations."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("torch")

from gradsep.model.network import NetworkConfig  # noqa: E402
from gradsep.training.train import TrainConfig  # noqa: E402
from tests.training.synthetic import make_synthetic_dataset  # noqa: E402

#: Small enough that an epoch takes well under a second on one core.
TINY_NETWORK = NetworkConfig(width=4, residual_blocks=1, gbranch_width=8)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 frames of 64×48 (direct + indirect + features) with manifest.json, as `gradsep dataset` writes."""
    return make_synthetic_dataset(tmp_path_factory.mktemp("dataset"), frames=6, width=64, height=48)


def tiny_config(data: Path, output: Path, **overrides: object) -> TrainConfig:
    """A TrainConfig whose epoch is 5 steps of 4 patches of 32² (5 training frames × 4 patches)."""
    values: dict[str, object] = {"data": str(data), "layer": "direct", "output": str(output),
                                 "network": TINY_NETWORK, "patch": 32, "batch": 4, "patches_per_frame": 4,
                                 "val_patches_per_frame": 1, "epochs": 2}
    values.update(overrides)
    return TrainConfig(**values)  # type: ignore[arg-type]


@pytest.fixture
def make_config(tiny_dataset: Path, tmp_path: Path):  # noqa: ANN201 - returns a factory
    """``make_config(name="run", **overrides)`` → a tiny TrainConfig writing to tmp_path/name."""

    def make(name: str = "run", **overrides: object) -> TrainConfig:
        return tiny_config(tiny_dataset, tmp_path / name, **overrides)

    return make


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tiny networks run fastest on one thread, and the suite shares 2 cores between xdist workers:
    oversubscribed OpenMP threads spin and slow everything down."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
