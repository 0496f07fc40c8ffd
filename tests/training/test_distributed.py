"""training/distributed.py outside torchrun: one process is its own group, and a resumed epoch skips what it
already trained on."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from torch.utils.data import SequentialSampler  # noqa: E402

from gradsep.training.distributed import DistContext, SkipSampler, setup_distributed, teardown_distributed  # noqa: E402


def test_skip_sampler_resumes_an_epoch_in_the_middle() -> None:
    inner = SequentialSampler(range(7))
    assert list(SkipSampler(inner, 3)) == [3, 4, 5, 6] and len(SkipSampler(inner, 3)) == 4
    assert list(SkipSampler(inner, 0)) == list(range(7))
    assert list(SkipSampler(inner, 9)) == [] and len(SkipSampler(inner, 9)) == 0


def test_a_single_process_is_rank_zero_and_its_collectives_are_identities(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    ctx = setup_distributed()
    try:
        assert isinstance(ctx, DistContext) and ctx.main and not ctx.distributed
        assert ctx.sum([1.5, 2.0]) == [1.5, 2.0] and ctx.agree([True, False]) == [True, False]
        ctx.barrier()
    finally:
        teardown_distributed(ctx)
