"""`gradsep train`: unsupervised training of one layer's network, resumable, CPU or `torchrun` DDP.

One run folder (RUN_DIR) holds everything: ``config.json``, ``checkpoints/last.pt`` (the full state, written
atomically at every epoch end, every few minutes and when the budget runs out), the last few
``checkpoints/epoch_NNNN.pt`` weight snapshots, ``log.jsonl`` (a record every few steps and one per epoch),
``losses.png`` and ``cache/`` (decoded frames; delete it to reclaim disk once the run is final).

Re-running the same command continues where the last run stopped — after a kill, or with a larger
``--minutes``/``--epochs`` — because patch positions and the shuffling order are pure functions of
(seed, epoch, index) and the checkpoint records the epoch, the phase and the batch within it.

Each epoch follows GradNet's training loop: (1) the main network is trained with the G-branch frozen, on
L = α·L_data + L_grad + β(epoch)·L_1st; (2) the G-branch is trained for one pass on its own first-order loss
with the main network untouched; (3) validation on fixed crops of the held-out frames; (4) both learning
rates decay ×0.95 every other epoch.

Distributed: under ``torchrun`` (WORLD_SIZE > 1) every process joins a torch.distributed group (gloo on CPU,
NCCL on GPUs), wraps both networks in DistributedDataParallel and reads its share through a
DistributedSampler; rank 0 writes the run folder and decides when to stop, and the decision is shared.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler, Sampler

from gradsep.model.network import DualBranchNet, GBranch, NetworkConfig, describe
from gradsep.model.preprocess import (
    PREPROCESS_VERSION,
    PRIOR_ALPHA,
    PRIOR_CHANNELS,
    PRIOR_KINDS,
    UNRECORDED_PRIOR_ALPHA,
    describe_preprocessing,
    network_inputs,
)
from gradsep.model.progress import ProgressBar
from gradsep.training.dataset import (
    TRAINABLE_LAYERS,
    DatasetError,
    PatchDataset,
    build_cache,
    load_manifest,
    split_frames,
    usable,
)
from gradsep.training.distributed import DistContext, SkipSampler, setup_distributed, teardown_distributed
from gradsep.training.losses import BetaSchedule, gbranch_loss, loss_terms
from gradsep.training.runlog import append_log, atomic_torch_save, atomic_write_text, code_version, plot_curves

#: Paper §4.5: 151 epochs. Used when neither --epochs nor --minutes is given.
DEFAULT_EPOCHS = 151
CHECKPOINT = "last.pt"


class TrainingError(RuntimeError):
    """Training cannot continue; the message says why and what to do."""


@dataclass
class TrainConfig:
    """Everything that defines a run; saved as RUN_DIR/config.json and embedded in the exported model."""

    data: str
    layer: str
    output: str
    network: NetworkConfig = field(default_factory=NetworkConfig)
    patch: int = 128                  # CPU default; the paper used 256 on a GPU
    batch: int = 16                   # CPU default; the paper used 32
    patches_per_frame: int = 8        # random crops per training frame per epoch (defines an epoch)
    val_patches_per_frame: int = 2    # fixed crops per validation frame
    val_fraction: float = 0.1         # 90/10 split by frame
    epochs: int | None = None
    minutes: float | None = None
    seed: int = 0
    lr: float = 1e-4
    adam_betas: tuple[float, float] = (0.5, 0.999)
    lr_decay: float = 0.95
    lr_decay_every: int = 2
    alpha: float = 1.0
    beta: BetaSchedule = field(default_factory=BetaSchedule)
    checkpoint_minutes: float = 5.0
    plot_minutes: float = 2.0          # redraw losses.png at an epoch end at most this often (and at the end)
    log_every: int = 10
    keep_epoch_checkpoints: int = 3
    prior: str = "l1"                 # what the network refines: model.preprocess.PRIOR_KINDS (only l1)
    prior_alpha: float = PRIOR_ALPHA  # the prior's screening α, recorded in the model (gradsep.prior_alpha)
    init: str | None = None           # start from these weights (an exported .onnx or a run's .pt), not at random

    # fields a resumed run may change: everything else must match the run folder's config.json
    RESUMABLE_CHANGES = ("epochs", "minutes", "output", "data", "checkpoint_minutes", "plot_minutes", "log_every",
                         "keep_epoch_checkpoints")

    def __post_init__(self) -> None:
        if self.prior not in PRIOR_KINDS:
            raise ValueError(f"prior must be one of {PRIOR_KINDS}, got {self.prior!r}")
        if not (math.isfinite(self.prior_alpha) and self.prior_alpha > 0):
            raise ValueError(f"prior_alpha must be a finite number > 0, got {self.prior_alpha!r}")
        if self.layer not in TRAINABLE_LAYERS:
            raise ValueError(f"layer must be one of {TRAINABLE_LAYERS}, got {self.layer!r}")
        for name in ("patch", "batch", "patches_per_frame", "val_patches_per_frame", "lr_decay_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.patch % self.network.alignment:
            raise ValueError(f"patch {self.patch} must be a multiple of the network alignment "
                             f"{self.network.alignment}")
        if self.epochs is not None and self.epochs < 1:
            raise ValueError(f"epochs must be >= 1, got {self.epochs}")
        if self.minutes is not None and not self.minutes > 0:
            raise ValueError(f"minutes must be > 0, got {self.minutes}")

    @property
    def max_epochs(self) -> int:
        if self.epochs is not None:
            return self.epochs
        return sys.maxsize if self.minutes is not None else DEFAULT_EPOCHS

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["adam_betas"] = list(self.adam_betas)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        d = dict(d)
        d["network"] = NetworkConfig.from_dict(d.get("network", {}))
        d["beta"] = BetaSchedule(**d.get("beta", {}))
        d["adam_betas"] = tuple(d.get("adam_betas", (0.5, 0.999)))
        d.setdefault("prior_alpha", UNRECORDED_PRIOR_ALPHA)  # recorded since the key exists; before, always this
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


# ---------------------------------------------------------------------------------------------------------------
# Run folder: config
# ---------------------------------------------------------------------------------------------------------------


def prepare_run_dir(cfg: TrainConfig, manifest_sha256: str) -> dict[str, Any]:
    """Create RUN_DIR with config.json, or check that an existing one describes the same run."""
    run = Path(cfg.output)
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    path = run / "config.json"
    fresh = {"train": cfg.to_dict(), "preprocessing": describe_preprocessing(prior_alpha=cfg.prior_alpha),
             "dataset_manifest_sha256": manifest_sha256, "code_version": code_version(),
             "torch": torch.__version__}
    if path.is_file():
        old = json.loads(path.read_text())
        old_train = {"prior_alpha": UNRECORDED_PRIOR_ALPHA, **old.get("train", {})}  # a run from before the key
        new_train = fresh["train"]
        changed = sorted(k for k in set(old_train) | set(new_train)
                         if k not in TrainConfig.RESUMABLE_CHANGES and old_train.get(k) != new_train.get(k))
        if old.get("dataset_manifest_sha256") != manifest_sha256:
            changed.append("dataset (manifest.json differs)")
        if old.get("preprocessing", {}).get("version") != PREPROCESS_VERSION:
            changed.append("preprocessing version")
        if changed:
            raise TrainingError(f"{run} holds a different run ({', '.join(changed)} changed); "
                                "use a new output folder or the original settings")
        fresh["history_of_budgets"] = [*old.get("history_of_budgets", []),
                                       {"epochs": cfg.epochs, "minutes": cfg.minutes}]
    else:
        fresh["history_of_budgets"] = [{"epochs": cfg.epochs, "minutes": cfg.minutes}]
    atomic_write_text(path, json.dumps(fresh, indent=2))
    return fresh


# ---------------------------------------------------------------------------------------------------------------
# The trainer
# ---------------------------------------------------------------------------------------------------------------

TERMS = ("data", "grad", "first", "total")


@dataclass
class Progress:
    """Where training stands; saved in every checkpoint."""

    epoch: int = 0
    phase: str = "main"        # "main" (network) or "gbranch"
    batch: int = 0             # batches of the current phase done
    step: int = 0              # main-network optimiser steps, all epochs
    elapsed: float = 0.0       # training seconds, all sessions
    sums: dict[str, float] = field(default_factory=dict)   # running sums of the current epoch
    skipped_frames: list[str] = field(default_factory=list)


def _unwrap(module: nn.Module) -> nn.Module:
    return module.module if isinstance(module, DistributedDataParallel) else module


class Trainer:
    def __init__(self, cfg: TrainConfig, ctx: DistContext, quiet: bool = False) -> None:
        self.cfg = cfg
        self.ctx = ctx
        self.quiet = quiet or not ctx.main
        self.run = Path(cfg.output)
        self.progress = Progress()
        torch.manual_seed(cfg.seed)
        self.model: nn.Module = DualBranchNet(cfg.network).to(ctx.device)
        self.gbranch: nn.Module = GBranch(cfg.network).to(ctx.device)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, betas=cfg.adam_betas)
        self.opt_g = torch.optim.Adam(self.gbranch.parameters(), lr=cfg.lr, betas=cfg.adam_betas)
        self.sched = torch.optim.lr_scheduler.StepLR(self.opt, cfg.lr_decay_every, cfg.lr_decay)
        self.sched_g = torch.optim.lr_scheduler.StepLR(self.opt_g, cfg.lr_decay_every, cfg.lr_decay)
        self.session_start = time.monotonic()
        self.elapsed_at_start = 0.0
        self.last_save = time.monotonic()
        self.last_plot = time.monotonic()

    # -- setup -------------------------------------------------------------------------------------------------

    def prepare_data(self) -> None:
        cfg, ctx = self.cfg, self.ctx
        manifest = load_manifest(cfg.data)
        self.manifest_sha256 = manifest.sha256
        if ctx.main:
            prepare_run_dir(cfg, manifest.sha256)
            self._say(f"dataset {cfg.data}: {len(manifest.frames)} frames; building the {cfg.layer} cache")
            _, warnings = build_cache(manifest, cfg.layer, self.run / "cache", prior_alpha=cfg.prior_alpha)
            for w in warnings:
                self._say(f"warning: {w}")
        ctx.barrier()
        files, warnings = build_cache(manifest, cfg.layer, self.run / "cache",  # all valid now: no decoding
                                      prior_alpha=cfg.prior_alpha)
        train_idx, val_idx = split_frames(len(files), cfg.seed, cfg.val_fraction)
        train_files, notes = usable(files, train_idx, cfg.patch)
        val_files, val_notes = usable(files, val_idx, cfg.patch)
        if not train_files:
            raise DatasetError(f"no usable training frames for layer {cfg.layer!r} at patch {cfg.patch}: "
                               + "; ".join([*warnings, *notes, *val_notes][:5]))
        self.train_set = PatchDataset(train_files, cfg.patch, cfg.patches_per_frame, cfg.seed)
        self.val_set = (PatchDataset(val_files, cfg.patch, cfg.val_patches_per_frame, cfg.seed, fixed=True)
                        if val_files else None)
        self.train_sampler = DistributedSampler(self.train_set, num_replicas=ctx.world, rank=ctx.rank,
                                                shuffle=True, seed=cfg.seed, drop_last=True)
        self.steps_per_epoch = len(self.train_sampler) // cfg.batch
        if self.steps_per_epoch < 1:
            raise DatasetError(f"an epoch has {len(self.train_set)} patches, fewer than one batch of "
                               f"{cfg.batch} per process; raise patches_per_frame or lower --batch")
        self._say(f"{len(train_files)} training / {len(val_files)} validation frames, "
                  f"{self.steps_per_epoch} steps per epoch (patch {cfg.patch}, batch {cfg.batch}, "
                  f"{ctx.world} process(es))")
        paired = self.train_set.paired
        self._say("targets: " + ("an independent second realization of each frame (Noise2Noise)" if paired
                                 else "the input's own measurements (no --pairs in the dataset)"))
        self._say(describe(cfg.network))

    def wrap_distributed(self) -> None:
        if self.ctx.distributed:
            ids = [self.ctx.device.index] if self.ctx.device.type == "cuda" else None
            self.model = DistributedDataParallel(self.model, device_ids=ids)
            self.gbranch = DistributedDataParallel(self.gbranch, device_ids=ids)

    # -- checkpoints -------------------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        return {
            "format": 1,
            "config": self.cfg.to_dict(),
            "preprocess_version": PREPROCESS_VERSION,
            "dataset_manifest_sha256": self.manifest_sha256,
            "model": _unwrap(self.model).state_dict(),
            "gbranch": _unwrap(self.gbranch).state_dict(),
            "opt": self.opt.state_dict(), "opt_g": self.opt_g.state_dict(),
            "sched": self.sched.state_dict(), "sched_g": self.sched_g.state_dict(),
            "progress": dataclasses.asdict(self.progress) | {"elapsed": self.elapsed()},
        }

    def save(self) -> None:
        if self.ctx.main:
            atomic_torch_save(self.state(), self.run / "checkpoints" / CHECKPOINT)
        self.last_save = time.monotonic()

    def try_resume(self) -> bool:
        path = self.run / "checkpoints" / CHECKPOINT
        if not path.is_file():
            return False
        state = torch.load(path, map_location=self.ctx.device, weights_only=True)
        _unwrap(self.model).load_state_dict(state["model"])
        _unwrap(self.gbranch).load_state_dict(state["gbranch"])
        self.opt.load_state_dict(state["opt"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.sched.load_state_dict(state["sched"])
        self.sched_g.load_state_dict(state["sched_g"])
        self.progress = Progress(**state["progress"])
        self.elapsed_at_start = self.progress.elapsed
        p = self.progress
        self._say(f"resuming {self.run}: epoch {p.epoch + 1}, {p.phase} phase, batch {p.batch}, step {p.step}, "
                  f"{p.elapsed / 60:.1f} min spent")
        return True

    def warm_start(self) -> None:
        """Load ``cfg.init``'s main-network weights (a fresh run only: a resumed run keeps its own)."""
        if self.cfg.init is None:
            return
        state = initial_weights(self.cfg.init, self.cfg)
        _unwrap(self.model).load_state_dict(state)
        self._say(f"starting from the weights of {self.cfg.init}")

    def save_epoch_snapshot(self) -> None:
        if not self.ctx.main:
            return
        folder = self.run / "checkpoints"
        atomic_torch_save({"config": self.cfg.to_dict(), "model": _unwrap(self.model).state_dict(),
                            "epoch": self.progress.epoch, "step": self.progress.step},
                           folder / f"epoch_{self.progress.epoch + 1:04d}.pt")
        snapshots = sorted(folder.glob("epoch_*.pt"))
        for old in snapshots[: max(0, len(snapshots) - self.cfg.keep_epoch_checkpoints)]:
            old.unlink(missing_ok=True)

    # -- time ---------------------------------------------------------------------------------------------------

    def elapsed(self) -> float:
        return self.elapsed_at_start + (time.monotonic() - self.session_start)

    def _out_of_time(self) -> bool:
        """Before the next batch, decided by rank 0 and shared: True when the budget is spent; otherwise a
        checkpoint is saved first when one is due."""
        stop = self.cfg.minutes is not None and self.elapsed() >= self.cfg.minutes * 60
        save = time.monotonic() - self.last_save >= self.cfg.checkpoint_minutes * 60
        stop, save = self.ctx.agree([stop, save])
        if save and not stop:
            self.save()
        return stop

    def _say(self, text: str) -> None:
        if not self.quiet:
            print(text, file=sys.stderr, flush=True)

    # -- phases -------------------------------------------------------------------------------------------------

    def _loader(self, dataset: PatchDataset, sampler: Sampler[int]) -> DataLoader:
        return DataLoader(dataset, batch_size=self.cfg.batch, sampler=sampler, drop_last=True, num_workers=0)

    def _bar(self, total: int, initial: int, desc: str) -> ProgressBar:
        return ProgressBar(total, enabled=not self.quiet, desc=desc, initial=initial, leave=False)

    def _batches(self) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """The current epoch's batches of one phase (planes, features, targets), skipping those a previous
        session already did."""
        self.train_set.set_epoch(self.progress.epoch)
        self.train_sampler.set_epoch(self.progress.epoch)
        skip = self.progress.batch * self.cfg.batch
        for planes, feats, targets in self._loader(self.train_set, SkipSampler(self.train_sampler, skip)):
            yield planes.to(self.ctx.device), feats.to(self.ctx.device), targets.to(self.ctx.device)

    def main_phase(self) -> bool:
        """Train the network for the rest of this epoch; False when the budget ran out first."""
        cfg, p = self.cfg, self.progress
        beta = cfg.beta(p.epoch)
        self.model.train()
        self.gbranch.eval()
        bar = self._bar(self.steps_per_epoch, p.batch, f"epoch {p.epoch + 1} network")
        try:
            for planes, feats, targets in self._batches():
                if self._out_of_time():
                    return False
                data, grad = network_inputs(planes, feats)
                pred = self.model(data, grad)
                with torch.no_grad():
                    coeffs = self.gbranch(data, grad)
                terms = loss_terms(pred, coeffs, planes, feats, targets)
                loss = terms.total(cfg.alpha, beta)
                if not torch.isfinite(loss):
                    raise TrainingError(f"the loss became non-finite at epoch {p.epoch + 1}, step {p.step}; "
                                        f"terms {terms.as_floats()}")
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                self.opt.step()
                values = terms.as_floats() | {"total": float(loss.detach())}
                for k in TERMS:
                    p.sums[k] = p.sums.get(k, 0.0) + values[k]
                p.sums["n"] = p.sums.get("n", 0.0) + 1
                p.batch += 1
                p.step += 1
                if self.ctx.main and p.step % cfg.log_every == 0:
                    append_log(self.run, {"kind": "step", "epoch": p.epoch + 1, "step": p.step, **values,
                                          "beta": beta, "lr": self.opt.param_groups[0]["lr"],
                                          "elapsed": round(self.elapsed(), 2)})
                bar.update(1)
                bar.postfix(data=f"{values['data']:.4f}", grad=f"{values['grad']:.4f}",
                                first=f"{values['first']:.4f}", beta=f"{beta:.2f}")
        finally:
            bar.close()
        p.phase, p.batch = "gbranch", 0
        return True

    def gbranch_phase(self) -> bool:
        """One pass of the G-branch on its own loss, the main network frozen (GradNet's alternation)."""
        p = self.progress
        self.gbranch.train()
        bar = self._bar(self.steps_per_epoch, p.batch, f"epoch {p.epoch + 1} G-branch")
        try:
            for planes, feats, _ in self._batches():
                if self._out_of_time():
                    return False
                data, grad = network_inputs(planes, feats)
                loss = gbranch_loss(self.gbranch(data, grad), planes, feats)
                self.opt_g.zero_grad(set_to_none=True)
                loss.backward()
                self.opt_g.step()
                p.sums["gbranch"] = p.sums.get("gbranch", 0.0) + float(loss.detach())
                p.sums["gn"] = p.sums.get("gn", 0.0) + 1
                p.batch += 1
                bar.update(1)
                bar.postfix(first=f"{float(loss.detach()):.4f}")
        finally:
            bar.close()
        p.phase, p.batch = "done", 0
        return True

    @torch.no_grad()
    def validate(self, beta: float) -> dict[str, float] | None:
        """Mean loss terms on the fixed validation crops, for the network and (keys ``prior_*``) for the Poisson
        prior it refines scored the same way. With paired data the targets are independent of the input, so
        ``data`` and ``prior_data`` are unbiased estimates of each one's relative error up to one shared
        constant (the target's noise): the network helps where its value is below the prior's."""
        if self.val_set is None:
            return None
        self.model.eval()
        self.gbranch.eval()
        sampler = DistributedSampler(self.val_set, num_replicas=self.ctx.world, rank=self.ctx.rank,
                                     shuffle=False)
        keys = [*TERMS, *(f"prior_{k}" for k in TERMS)]
        sums = [0.0] * (len(keys) + 1)
        loader = DataLoader(self.val_set, batch_size=self.cfg.batch, sampler=sampler, num_workers=0)
        for planes, feats, targets in loader:
            planes, feats, targets = planes.to(self.ctx.device), feats.to(self.ctx.device), targets.to(self.ctx.device)
            data, grad = network_inputs(planes, feats)
            coeffs = _unwrap(self.gbranch)(data, grad)
            terms = loss_terms(_unwrap(self.model)(data, grad), coeffs, planes, feats, targets)
            prior = loss_terms(data[:, PRIOR_CHANNELS], coeffs, planes, feats, targets)  # C(prior): the net's start
            values = (terms.as_floats() | {"total": float(terms.total(self.cfg.alpha, beta))}
                      | {f"prior_{k}": v for k, v in prior.as_floats().items()}
                      | {"prior_total": float(prior.total(self.cfg.alpha, beta))})
            n = planes.shape[0]
            for i, k in enumerate(keys):
                sums[i] += values[k] * n
            sums[-1] += n
        sums = self.ctx.sum(sums)
        return {k: sums[i] / max(sums[-1], 1.0) for i, k in enumerate(keys)}

    def end_epoch(self, epoch_started: float) -> None:
        cfg, p = self.cfg, self.progress
        beta = cfg.beta(p.epoch)
        sums = self.ctx.sum([p.sums.get(k, 0.0) for k in (*TERMS, "n", "gbranch", "gn")])
        n, gn = max(sums[4], 1.0), max(sums[6], 1.0)
        val = self.validate(beta)
        seconds = time.monotonic() - epoch_started
        record = {"kind": "epoch", "epoch": p.epoch + 1, "step": p.step,
                  "train": {k: sums[i] / n for i, k in enumerate(TERMS)}, "val": val,
                  "gbranch": sums[5] / gn, "beta": beta, "lr": self.opt.param_groups[0]["lr"],
                  "elapsed": round(self.elapsed(), 2), "session_epoch_seconds": round(seconds, 2)}
        self.sched.step()
        self.sched_g.step()
        if self.ctx.main:
            append_log(self.run, record)
            v = (f", val total {val['total']:.4f} data {val['data']:.4f} (prior alone {val['prior_total']:.4f} / "
                 f"{val['prior_data']:.4f})" if val else "")
            self._say(f"epoch {p.epoch + 1}: train data {record['train']['data']:.4f} grad "
                      f"{record['train']['grad']:.4f} 1st {record['train']['first']:.4f} (beta {beta:.2f}), "
                      f"G {record['gbranch']:.4f}{v}; {p.step} steps, {self.elapsed() / 60:.1f} min")
        self.save_epoch_snapshot()
        p.epoch += 1
        p.phase, p.batch, p.sums = "main", 0, {}
        self.save()
        if self.ctx.main and time.monotonic() - self.last_plot >= self.cfg.plot_minutes * 60:
            plot_curves(self.run)
            self.last_plot = time.monotonic()

    def fit(self) -> Progress:
        """Train until the epoch count or the time budget is reached; returns the final progress."""
        p = self.progress
        session_steps = p.step
        t0 = time.monotonic()
        finished = False
        while p.epoch < self.cfg.max_epochs:
            epoch_started = time.monotonic()
            if p.phase == "main" and not self.main_phase():
                break
            if p.phase == "gbranch" and not self.gbranch_phase():
                break
            self.end_epoch(epoch_started)
        else:
            finished = True
        self.save()
        p.elapsed = self.elapsed()
        if self.ctx.main:
            plot_curves(self.run)
            rate = (p.step - session_steps) / max(time.monotonic() - t0, 1e-9)
            where = (f"finished {p.epoch} epochs" if finished else
                     f"time budget reached in epoch {p.epoch + 1} ({p.phase} phase)")
            self._say(f"{where}: step {p.step}, {p.elapsed / 60:.1f} min in total; {rate:.2f} network steps/s "
                      f"this session (G-branch passes and validation included); run folder {self.run}")
        return p


def initial_weights(path: str | os.PathLike[str], cfg: TrainConfig) -> dict[str, torch.Tensor]:
    """The main network's state dict from an exported model (``gradsep export``'s .onnx: its initializers carry
    the parameter names) or a run's checkpoint (.pt, ``last.pt`` or an epoch snapshot), checked against ``cfg``:
    the same layer, network shape and prior, every parameter present with its shape. A mismatch is a
    TrainingError naming it, never a partial load."""
    source = Path(path)
    if not source.is_file():
        raise TrainingError(f"--init {source}: no such file")
    expected = DualBranchNet(cfg.network).state_dict()
    if source.suffix == ".onnx":
        import onnx
        from onnx import numpy_helper

        try:
            graph = onnx.load(str(source))
        except Exception as exc:  # noqa: BLE001 - onnx raises several types for a bad file
            raise TrainingError(f"--init {source}: not a readable ONNX model ({exc})") from exc
        meta = {p.key: p.value for p in graph.metadata_props}
        trained = json.loads(meta.get("gradsep.training", "{}"))
        facts = {"layer": meta.get("gradsep.layer"), "prior": meta.get("gradsep.prior") or trained.get("prior", "l1"),
                 "network": json.loads(meta.get("gradsep.network", "null"))}
        state = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in graph.graph.initializer
                 if i.name in expected}
    else:
        try:
            blob = torch.load(source, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - torch raises several types for a bad file
            raise TrainingError(f"--init {source}: not a readable checkpoint ({exc})") from exc
        if not isinstance(blob, dict) or not isinstance(blob.get("model"), dict):
            raise TrainingError(f"--init {source}: a checkpoint holds a 'model' state dict; this file has none")
        trained = blob.get("config") or {}
        facts = {"layer": trained.get("layer"), "prior": trained.get("prior", "l1"),
                 "network": trained.get("network")}
        state = blob["model"]
    wanted = {"layer": cfg.layer, "prior": cfg.prior, "network": cfg.network.to_dict()}
    for name, value in wanted.items():
        if facts[name] is not None and facts[name] != value:
            raise TrainingError(f"--init {source}: its {name} is {facts[name]!r}, this run's is {value!r}")
    missing = [k for k in expected if k not in state]
    wrong = [k for k in expected if k in state and tuple(state[k].shape) != tuple(expected[k].shape)]
    if missing or wrong:
        raise TrainingError(f"--init {source}: does not fit this network ({len(missing)} parameters missing, "
                            f"{len(wrong)} of another shape; first: {(missing + wrong)[0]})")
    return {k: state[k] for k in expected}


def train(cfg: TrainConfig, quiet: bool = False) -> Progress:
    """Run (or resume) training described by ``cfg``; the library entry point behind `gradsep train`."""
    from gradsep.model.cleanup import undone_on_failure

    ctx = setup_distributed()
    try:
        trainer = Trainer(cfg, ctx, quiet=quiet)
        # a start that fails (no usable frames at this patch, a bad --init...) leaves no run folder behind to
        # refuse the corrected command as "a different run"; rank 0 made the folder, rank 0 undoes it
        fresh = not (Path(cfg.output) / "config.json").exists()  # a resume that fails keeps its run as it was
        with undone_on_failure(cfg.output, enabled=ctx.main and fresh):
            trainer.prepare_data()
            if not trainer.try_resume():
                trainer.warm_start()
            trainer.wrap_distributed()
        return trainer.fit()
    finally:
        teardown_distributed(ctx)

