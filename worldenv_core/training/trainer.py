"""The one training loop (tdmpc2's Trainer): every training stage hands it a model, its
optimizers and one or more `Phase`s (a stretch of steps with its own batches and update), and it
does the rest the same way for all: restore from the work dir's newest checkpoint, a progress bar
with ETA, running means into the history and the tracker, periodic and final checkpoints,
evaluations at fixed points, the curves plot and the manifest outputs.

Resume is bit-identical: a phase's batches are a function of its step alone (`batches`,
`per_step`), the RNG states travel in the checkpoint, and `extra_state` carries anything else
(EMA weights, mined hard negatives are re-derived by the stage from the step).

Launched by torchrun, the same loop trains data-parallel (`worldenv_core.distributed`): each rank
takes its slice of every global batch, gradients are averaged in `optimize`, rank 0 alone writes,
and the other ranks leave when training ends. `accumulate` micro-batches per step and bf16
autocast on GPU (`precision`) work the same at any world size."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from worldenv_core.models.checkpoint import save_model
from worldenv_core import distributed
from worldenv_core.errors import Interrupted
from worldenv_core.files import write_text_atomic
from worldenv_core.training.checkpoints import Checkpoints
from worldenv_core.tracking import Tracker
from worldenv_core.viz import plot_history

log = logging.getLogger(__name__)


@dataclass
class Phase:
    """`steps` optimisation steps of one kind. `batches(start)` yields the phase's batches from its
    own step `start` on (0 when it begins, more when a run resumes inside it); `step(batch)` makes
    one update and returns the values to log (losses, diagnostics)."""

    name: str
    steps: int
    batches: Callable[[int], Iterator]
    step: Callable[[Any], dict]


def optimize(loss: torch.Tensor, optimizer: torch.optim.Optimizer, clip: float | None = None, params=None) -> None:
    """One gradient step on `loss`, its gradient norm clipped to `clip` over `params` (default:
    every parameter the optimizer updates). In a data-parallel run the gradients are averaged over
    ranks first; inside gradient accumulation only the last micro-batch steps."""
    if not distributed.backward(loss, optimizer):
        return
    if clip is not None:
        params = params if params is not None else [p for g in optimizer.param_groups for p in g["params"]]
        torch.nn.utils.clip_grad_norm_(params, clip)
    optimizer.step()


class RunningMeans:
    """Per-step values (losses, diagnostics) averaged into one `history` entry every `every`
    steps and at the last, shown on the progress bar and sent to the tracker (TensorBoard, ...)."""

    def __init__(self, history: list[dict], every: int, bar=None, tracker=None, postfix: tuple[str, ...] | None = None):
        self.history, self.every, self.bar, self.tracker = history, int(every), bar, tracker
        self.postfix = postfix  # the keys the bar shows (None: all)
        self.values: dict[str, list[float]] = {}

    def add(self, **values: float) -> None:
        for k, v in values.items():
            self.values.setdefault(k, []).append(float(v))

    def end_step(self, done: int, total: int) -> None:
        if done % self.every and done != total:
            return
        entry = {"step": done, **{k: sum(v) / len(v) for k, v in self.values.items()}}
        self.history.append(entry)
        self.values.clear()
        if self.tracker is not None:
            self.tracker.log(entry, done)
        if self.bar is not None:
            self.bar.set_postfix({k: f"{v:.4f}" for k, v in entry.items()
                                  if k != "step" and (self.postfix is None or k in self.postfix)})


class Trainer:
    """Trains `model` in `work` (its `checkpoints/` are what a re-run resumes from).

    model_config, meta: what the saved checkpoints rebuild the model from and say about it.
    extra_state: () -> dict of more state to checkpoint (restored into `self.extra`).
    overall: a progress bar over several trainings (cross-validation folds) this one advances.
    parallel: train data-parallel when launched by torchrun (False: rank 0 alone, e.g. the extra
        trainings a stage runs after its model's, once the other ranks have left).
    accumulate: micro-batches per optimizer step (each rank's slice of a batch split again).
    precision: "fp32", or "bf16" (autocast on a GPU; CPU runs stay fp32)."""

    def __init__(self, work: str | Path, model: torch.nn.Module, optimizers: dict[str, torch.optim.Optimizer], *,
                 model_config: dict, meta: dict, log_every: int, checkpoint_every: int, tracker: Tracker | None = None,
                 desc: str = "train", extra_state: Callable[[], dict] | None = None, progress: bool = True,
                 overall=None, postfix: tuple[str, ...] | None = None, keep: int = 2, parallel: bool = True,
                 accumulate: int = 1, precision: str = "fp32"):
        if accumulate < 1:
            raise ValueError(f"accumulate must be >= 1, got {accumulate}")
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be 'fp32' or 'bf16', got {precision!r}")
        self.work, self.model, self.optimizers = Path(work), model, optimizers
        self.model_config, self.meta = model_config, meta
        self.log_every, self.checkpoint_every = int(log_every), int(checkpoint_every)
        self.main = distributed.is_main()
        self.tracker = tracker if tracker is not None and self.main else Tracker()
        self.desc, self.extra_state, self.progress, self.overall, self.postfix = desc, extra_state, progress, overall, postfix
        self.accumulate, self.precision = int(accumulate), precision
        self.parallel = parallel and distributed.launched() > 1
        self.ranks = distributed.launched() if self.parallel else 1  # what the run trains over (recorded)
        device = next(model.parameters()).device
        self.bf16 = precision == "bf16" and device.type == "cuda"  # CPU runs stay fp32
        if self.parallel:
            distributed.init(device)
        self.checkpoints = Checkpoints(self.work, keep)
        self.step, self.history = self.checkpoints.restore(model, optimizers)
        self.evaluated: set[int] = set((self.checkpoints.trainer or {}).get("evaluated", []))
        self.extra = self.checkpoints.extra
        if self.parallel:
            distributed.broadcast_model(model)
        self.wall_s = 0.0  # this sitting's training time

    def save(self, done: int) -> Path | None:
        """A resumable checkpoint at step `done` (the model, optimizers, RNG states, history); rank 0's."""
        if not self.main:
            return None
        return self.checkpoints.save(done, self.model, self.model_config, self.meta, self.optimizers, self.history,
                                     extra=self.extra_state() if self.extra_state else None,
                                     trainer={"evaluated": sorted(self.evaluated)})

    def _train_step(self, phase: Phase, batch) -> dict:
        """This rank's slice of the global batch, in `accumulate` micro-batches -> the step's values,
        averaged over micro-batches and ranks."""
        mine = distributed.shard(batch, distributed.rank(), self.ranks) if self.parallel else batch
        values: dict[str, float] = {}
        for i in range(self.accumulate):
            autocast = torch.autocast("cuda", dtype=torch.bfloat16) if self.bf16 else nullcontext()
            with distributed.micro_batch(i, self.accumulate), autocast:
                part = phase.step(distributed.shard(mine, i, self.accumulate))
            for k, v in part.items():
                values[k] = values.get(k, 0.0) + float(v) / self.accumulate
        return distributed.mean_over_ranks(values) if self.parallel else values

    def fit(self, phases: list[Phase], after_step: Callable[[int], None] | None = None,
            evaluate: Callable[[int, Path | None], dict] | None = None, evaluate_every: int = 0,
            deadline: float | None = None, after_save: Callable[[int], None] | None = None) -> list[dict]:
        """Run `phases` one after another from the restored step to the end. `after_step(done)` runs
        after every step (before its checkpoint). `evaluate(done, checkpoint)` measures the model
        before the first step (checkpoint None: the starting model), every `evaluate_every` steps
        and at the end, on the checkpoint just saved; its values join that step's history entry
        and go to the tracker's "eval" group. `deadline` (a `time.monotonic()` instant): the first
        step that ends past it is the last of this sitting, checkpointed and evaluated as the end is
        (`self.stopped_early`), so a run on a leased machine ends with its model saved rather than
        killed; a re-run resumes to the planned total. `after_save(done)` runs once a step's checkpoint
        (with its evaluation) is written: a copy of the run's state outside the work dir stays current.
        -> the history."""
        total = sum(p.steps for p in phases)
        self.stopped_early = False
        if self.overall is not None:
            self.overall.update(self.step)  # what earlier sittings (or a finished fold) did
        bar = tqdm(range(self.step, total), initial=self.step, total=total, desc=self.desc, dynamic_ncols=True,
                   disable=not (self.progress and self.main), position=0 if self.overall is None else 1,
                   leave=self.overall is None)
        running = RunningMeans(self.history, self.log_every, bar, self.tracker, self.postfix)
        if self.parallel:  # the same restored RNG on every rank, then each its own stream (noise, dropout)
            torch.manual_seed(int(torch.randint(2 ** 62, (1,))) + distributed.rank())
        evaluate = evaluate if self.main else None  # measurements are rank 0's
        if evaluate is not None and self.step == 0 and not self.history:
            self._record_eval(0, evaluate(0, None))
        elif evaluate is not None and self._evaluation_cut_short(total, evaluate_every):
            # the last sitting checkpointed this step and was stopped inside its evaluation: do it now
            log.info("%s: step %d's evaluation did not finish in the last sitting; evaluating it now", self.desc, self.step)
            self._record_eval(self.step, evaluate(self.step, self.checkpoints.last))
            self.save(self.step)
        t0 = time.perf_counter()
        current, batches = None, None
        try:
            for step in bar:
                phase, start = _phase_at(phases, step)
                if phase is not current:  # entering a phase, or resuming inside one
                    batches = None  # the last phase's data goes before the next one's is made
                    current, batches = phase, iter(phase.batches(step - start))
                self.model.train()
                running.add(**self._train_step(phase, next(batches)))
                done = self.step = step + 1
                running.end_step(done, total)
                if self.overall is not None:
                    self.overall.update(1)
                if after_step is not None:
                    after_step(done)
                late = deadline is not None and done < total and time.monotonic() >= deadline
                if deadline is not None and self.parallel:  # every rank stops at the same step: rank 0's clock decides
                    late = distributed.gather(late)[0]
                last = done == total or late
                evaluating = evaluate is not None and (last or (evaluate_every and done % evaluate_every == 0))
                saving = evaluating or done % self.checkpoint_every == 0 or last
                if saving:
                    path = self.save(done)
                if evaluating:
                    self._record_eval(done, evaluate(done, path))
                    self.save(done)  # again, with the evaluation in its history
                if saving and after_save is not None and self.main:
                    after_save(done)
                if late:
                    self.stopped_early = True
                    log.info("%s: past the deadline at step %d of %d; checkpointed, a re-run goes on", self.desc, done, total)
                    break
        except KeyboardInterrupt as e:  # Ctrl-C or SIGTERM: say how far it got; the checkpoints are complete
            bar.close()
            last = self.checkpoints.last
            kept = f"its last checkpoint, step {int(last.name)}, is kept" if last else "no checkpoint was written yet"
            raise Interrupted(getattr(e, "signum", 2), f"{self.desc} at step {self.step} of {total} ({kept})") from None
        bar.close()
        self.wall_s += time.perf_counter() - t0
        if self.parallel:
            distributed.leave()
            if not self.main:
                log.info("rank %d: training done, leaving the rest to rank 0", distributed.rank())
                raise SystemExit(0)
            self.parallel = False
        return self.history

    def _evaluation_cut_short(self, total: int, evaluate_every: int) -> bool:
        """Whether the restored step was due an evaluation its checkpoint does not hold (a run
        stopped during it). A checkpoint written before this bookkeeping says nothing: False."""
        restored = self.checkpoints.trainer
        due = self.step == total or bool(evaluate_every and self.step % evaluate_every == 0)
        return bool(self.step and restored is not None and due and self.step not in self.evaluated)

    def _record_eval(self, step: int, values: dict) -> None:
        self.evaluated.add(step)
        entry = next((h for h in reversed(self.history) if h.get("step") == step), None)
        if entry is None:
            entry = {"step": step}
            self.history.append(entry)
        entry.update(values)
        self.tracker.log(values, step, group="eval")

    def save_final(self, path: str | Path, model: torch.nn.Module | None = None, **meta) -> Path:
        """The trained model (or another one, e.g. its EMA) as a self-describing checkpoint folder; a
        LeRobot policy (`save_lerobot`) also in LeRobot's own layout inside it (`lerobot/`), for its loaders."""
        return save_model(path, (model or self.model).cpu(), self.model_config, {**self.meta, "step": self.step, **meta},
                          native=True)

    def finish(self, stage, final: Path, title: str, plot: str = "losses.png") -> Path:
        """Close the tracker, draw the curves and record the final checkpoint and the plot as the
        stage's outputs. -> the plot."""
        self.tracker.close()
        stage.metrics.update(ranks=self.ranks, accumulate=self.accumulate)
        record_checkpoint(stage, final)
        figure = plot_history(self.history, self.work / plot, title)
        stage.add_output(figure, kind="plot")
        return figure


def planned_total(work: Path, minutes: float, time_steps: Callable[[float], int]) -> int:
    """The total steps of a run sized by time (`minutes=`): timed on this machine (`time_steps(seconds)`,
    e.g. `planned_steps` on copies of the model), and written to the work dir so that a re-run resumes
    to the total it first planned."""
    plan = Path(work) / "plan.json"
    if plan.exists():
        return json.loads(plan.read_text())["steps"]
    total = time_steps(minutes * 60)
    plan.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(plan, json.dumps({"steps": total, "minutes": minutes}))
    return total


def planned_steps(step_fn, batches, seconds: float, probe: int = 12, warm: int = 3) -> int:
    """How many steps fit in `seconds`, from the median of `probe` timed steps after `warm` untimed
    ones (`minutes=` of the stages; run it on copies of the model and optimizer)."""
    times = []
    for i in range(probe + warm):
        t0 = time.perf_counter()
        step_fn(next(batches))
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        if i >= warm:
            times.append(time.perf_counter() - t0)
    return max(1, int(seconds / sorted(times)[len(times) // 2]))


def record_checkpoint(stage, folder: Path) -> None:
    """Every file of a checkpoint folder as a `checkpoint` output of the stage's manifest record."""
    files = sorted(Path(folder).rglob("*"), key=lambda p: (len(p.parts), p))  # its own files first
    for f in (p for p in files if p.is_file()):
        # a LeRobot layout inside it (`lerobot/`) is recorded too, as its own kind: the folder's own files
        # are what stages take for the checkpoint
        stage.add_output(f, kind="checkpoint" if f.parent == Path(folder) else "lerobot_checkpoint")


def _phase_at(phases: list[Phase], step: int) -> tuple[Phase, int]:
    """The phase global `step` falls in, and the global step it starts at."""
    start = 0
    for phase in phases:
        if step < start + phase.steps:
            return phase, start
        start += phase.steps
    raise IndexError(f"step {step} is past the last phase")
