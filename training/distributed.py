"""Distributed training under ``torchrun``: the process group (torch.distributed; nothing home-made), the rank's
view of it and a sampler that resumes in the middle of an epoch."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch.utils.data import Sampler


@dataclass
class DistContext:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()

    def sum(self, values: list[float]) -> list[float]:
        """Element-wise sum over ranks (identity when not distributed)."""
        if not self.distributed:
            return values
        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
        return t.tolist()

    def agree(self, flags: list[bool]) -> list[bool]:
        """Rank 0's decisions, shared with every rank (so all stop or checkpoint at the same batch)."""
        if not self.distributed:
            return flags
        t = torch.tensor([float(f) for f in flags], device=self.device)
        dist.broadcast(t, src=0)
        return [bool(v) for v in t.tolist()]


def setup_distributed() -> DistContext:
    """Join the torchrun process group when WORLD_SIZE > 1; pick the device."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    cuda = torch.cuda.is_available()
    device = torch.device(f"cuda:{local_rank}") if cuda else torch.device("cpu")
    if cuda:
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if cuda else "gloo")
    return DistContext(rank, world, local_rank, device)


def teardown_distributed(ctx: DistContext) -> None:
    """Leave the process group together: a rank that destroys its gloo group while a peer is still writing the
    last checkpoint or plot can abort at exit ("terminate called without an active exception", seen in CI)."""
    if ctx.distributed and dist.is_initialized():
        try:
            if sys.exc_info()[0] is None:  # on failure no barrier: the peer may be inside another collective
                dist.barrier()
        finally:
            dist.destroy_process_group()


class SkipSampler(Sampler[int]):
    """The wrapped sampler's order minus its first ``skip`` items: resuming in the middle of an epoch."""

    def __init__(self, inner: Sampler[int], skip: int) -> None:
        self.inner = inner
        self.skip = skip

    def __iter__(self) -> Iterator[int]:
        for i, index in enumerate(self.inner):
            if i >= self.skip:
                yield index

    def __len__(self) -> int:
        return max(0, len(self.inner) - self.skip)  # type: ignore[arg-type]
