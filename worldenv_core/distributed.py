"""Data-parallel training on torch.distributed, launched by `torchrun` (one process per GPU, or
several CPU processes on the gloo backend). One code path: a plain `python -m stages.<stage>` is
the world-size-1 case, where every function here does nothing.

How a training stage runs under it (the `Trainer` does all of this; stages are unchanged):
* every rank builds the same model from the same seed, and rank 0's weights are broadcast;
* every rank draws the same *global* batch (batches are a function of the step alone) and trains
  on its own contiguous slice of it (`shard`), so the effective batch is the configured one
  whatever the world size, and a run resumes at any world size;
* gradients are averaged over ranks in `optimize` before clipping and the optimizer step (what
  DDP's all-reduce does; done here because stages call their models through methods such as
  `flow_loss`, not only `forward`, which DDP's hooks would miss);
* rank 0 alone writes checkpoints, curves, reports and the manifest record; the other ranks leave
  once training is done (`Trainer.fit`).

Gradient accumulation (`Trainer(accumulate=n)`) splits each rank's slice into n micro-batches
whose gradients add up before one synchronised step.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist

from worldenv_core.errors import ConfigError


_LEFT = False  # this process has left its process group: whatever it trains next, it trains alone


def launched() -> int:
    """The world size torchrun launched this process into (1: a plain run, or after `leave`)."""
    return 1 if _LEFT else int(os.environ.get("WORLD_SIZE", "1"))


def world_size() -> int:
    """Ranks training together now (1 outside a data-parallel `Trainer.fit`)."""
    return dist.get_world_size() if dist.is_initialized() else 1


def rank() -> int:
    return int(os.environ.get("RANK", "0"))


def is_main() -> bool:
    """Rank 0, or no distributed run at all: the process that writes files and records."""
    return rank() == 0


def init(device: torch.device) -> None:
    """Join the process group torchrun describes in the environment (no-op for one process): nccl
    on the rank's GPU (`training.pick_device` gives each rank its LOCAL_RANK one), gloo on CPUs."""
    if launched() <= 1 or dist.is_initialized():
        return
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=timedelta(hours=2))


def leave() -> None:
    """End the process group after training (every rank calls it): what follows (evaluation,
    reports, the manifest) is rank 0's alone, and the other ranks exit."""
    global _LEFT
    if dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()
    _LEFT = True


def broadcast_model(model: torch.nn.Module) -> None:
    """Every rank starts from rank 0's weights and buffers."""
    if world_size() > 1:
        for t in [*model.parameters(), *model.buffers()]:
            dist.broadcast(t.data, src=0)


def trainer_options(cfg, *batch_keys: str) -> dict:
    """A training stage's `accumulate` and `precision` settings, checked (with every batch named by
    `batch_keys` splitting evenly over the ranks and micro-batches, so the effective batch is the
    configured one) before any heavy work -> the `Trainer`'s keyword arguments."""
    from omegaconf import OmegaConf

    accumulate, precision = cfg.get("accumulate", 1), cfg.get("precision", "fp32")
    if not isinstance(accumulate, int) or accumulate < 1:
        raise ConfigError(f"accumulate must be an integer >= 1 (micro-batches per step), got {accumulate!r}")
    if precision not in ("fp32", "bf16"):
        raise ConfigError(f"precision must be fp32 or bf16, got {precision!r}")
    parts = launched() * accumulate
    for key in batch_keys:
        size = OmegaConf.select(cfg, key)
        if size % parts:
            raise ConfigError(f"{key}={size} does not split over {launched()} rank(s) x {accumulate} micro-batch(es): "
                              f"use a multiple of {parts}")
    return {"accumulate": accumulate, "precision": precision}


def shard(batch, index: int, parts: int):
    """This part's contiguous slice of a batch: tensors and lists along their first dimension,
    dicts and tuples element by element, anything else (a step number) as it is."""
    if parts == 1:
        return batch
    if isinstance(batch, dict):
        return {k: shard(v, index, parts) for k, v in batch.items()}
    if isinstance(batch, tuple):
        return tuple(shard(v, index, parts) for v in batch)
    if isinstance(batch, (torch.Tensor, list)):
        n = len(batch)
        return batch[index * n // parts:(index + 1) * n // parts]
    return batch


@dataclass
class _Accumulation:
    micro: int = 0  # this micro-batch's index
    count: int = 1  # micro-batches per optimizer step


_ACC = _Accumulation()


@contextmanager
def micro_batch(index: int, count: int):
    """Inside it, `optimize` adds this micro-batch's gradient (scaled by 1/count) and steps only
    on the last one."""
    previous = (_ACC.micro, _ACC.count)
    _ACC.micro, _ACC.count = index, count
    try:
        yield
    finally:
        _ACC.micro, _ACC.count = previous


def last_micro_batch() -> bool:
    """Whether the optimizer steps after this micro-batch (always, without accumulation): what
    runs once per step besides it (an EMA update) checks this."""
    return _ACC.micro == _ACC.count - 1


def backward(loss: torch.Tensor, optimizer: torch.optim.Optimizer) -> bool:
    """Accumulate `loss`'s gradient; True when this is the micro-batch that steps, with the
    gradients already averaged over ranks."""
    if _ACC.micro == 0:
        optimizer.zero_grad(set_to_none=True)
    (loss / _ACC.count if _ACC.count > 1 else loss).backward()
    if not last_micro_batch():
        return False
    average_gradients([p for g in optimizer.param_groups for p in g["params"]])
    return True


def average_gradients(params) -> None:
    """All-reduce the gradients of `params` (mean over ranks) in one flat buffer."""
    if world_size() <= 1:
        return
    params = [p for p in params if p.requires_grad]
    for p in params:
        if p.grad is None:  # a parameter this rank's micro-batches did not reach still takes part
            p.grad = torch.zeros_like(p)
    flat = torch.cat([p.grad.reshape(-1) for p in params])
    dist.all_reduce(flat)
    flat /= world_size()
    offset = 0
    for p in params:
        n = p.grad.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p.grad))
        offset += n


def random_rows(sample, shape, generator, **kwargs) -> torch.Tensor:
    """`sample(shape, generator=..., **kwargs)` (torch.rand, torch.randn, ...) where `generator` is
    one generator or a list of them, one per equal block of rows (a context's N rollouts): each
    block's numbers then depend on its own generator alone, so a batch split over ranks draws
    exactly what the whole batch would."""
    if not isinstance(generator, (list, tuple)):
        return _on_generator(sample, shape, generator, **kwargs)
    rows, rest = divmod(shape[0], len(generator))
    if rest:
        raise ValueError(f"{shape[0]} rows do not split into {len(generator)} equal blocks")
    return torch.cat([_on_generator(sample, (rows, *shape[1:]), g, **kwargs) for g in generator])


def _on_generator(sample, shape, generator, device=None, **kwargs) -> torch.Tensor:
    """Draw on the generator's device, then move: torch refuses a CPU generator for a CUDA tensor,
    and drawing where the generator lives keeps a seeded run's numbers the same on any device."""
    if device is None:  # where `sample` puts it (it need not take a device)
        return sample(shape, generator=generator, **kwargs)
    if generator is None or torch.device(device) == generator.device:
        return sample(shape, generator=generator, device=device, **kwargs)
    return sample(shape, generator=generator, device=generator.device, **kwargs).to(device)


def gather(obj) -> list:
    """Every rank's `obj` (any picklable value, tensors included), in rank order; [obj] alone."""
    if world_size() <= 1:
        return [obj]
    out = [None] * world_size()
    dist.all_gather_object(out, obj)
    return out


def mean_over_ranks(values: dict) -> dict:
    """Logged step values (losses) averaged over ranks, so rank 0's history is the global one."""
    if world_size() <= 1 or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64,
                     device="cuda" if dist.get_backend() == "nccl" else "cpu")
    dist.all_reduce(t)
    return {k: v / world_size() for k, v in zip(keys, t.tolist())}
