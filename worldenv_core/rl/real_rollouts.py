"""LOOP's rollouts in the real simulator: the reference that says what RL can do at all.

The same Algorithm 1 as in imagination (the frozen behaviour policy, Laplace-sampled chunks, N
rollouts per context, RLOO on the reward at termination), with the real LIBERO simulator as the
environment and its success oracle as the reward: a rollout ends at the first success (reward
1) or at the horizon (reward 0). Run side by side with the imagined route at an equal number of
rollouts, it separates "RL cannot lift this policy at this scale" from "the imagined
environment misleads it"; at an equal number of real episodes it says whether the world model
is worth having.

Each rollout is one real episode and one worker job (`real_rollout`): the behaviour policy is
saved once per iteration and loaded by the workers; they return what PPO needs (the observation
each chunk was chosen from and the sampled chunk, in the policy's normalised space), and the
behaviour log-probabilities are computed here in one batch, so PPO's first ratio is exactly 1.
With a `journal` folder every finished rollout is also kept on disk as it arrives (`RolloutJournal`),
so an iteration cut short (a session's end, a crash) resumes with the real episodes it had: they are
the resource this route spends, and an iteration of 256 of them is most of an hour on 2 cores.
"""

from __future__ import annotations

import functools
import pickle
import shutil
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from worldenv_core.distributed import random_rows

from worldenv_core.contract import TaskContract
from worldenv_core.envs.replay import RealStart
from worldenv_core.files import write_bytes_atomic
from worldenv_core.manifest import sha256_file
from worldenv_core.rl.loop import RolloutBatch, rloo_advantages


@dataclass(frozen=True)
class RealRolloutJob:
    contract: TaskContract
    start: RealStart
    policy_path: str  # the behaviour policy of this iteration (a checkpoint folder)
    seed: int  # the Laplace draws of this rollout
    instruction: np.ndarray  # (D,) its embedding, as the trainer encodes it (the same input on both sides)
    horizon: int  # steps, rounded up to whole chunks (as the imagined env does)
    noise_scale: float = 1.0
    index: int = 0  # its place in the batch
    exploration: str = "step"  # a Laplace draw per step, or one per chunk (`laplace.laplace_sample`)
    perturbation: tuple[int, float] | None = None  # an ES member: the behaviour's weights + coef * direction(seed)
    es_parameters: str = "mean"  # which weights the perturbation moves (`es.es_parameters`)
    keep_frames: bool = True  # False: only the outcome comes back (an ES member's rollout trains nothing)


@functools.lru_cache(maxsize=1)
def _policy(path: str, contract: TaskContract):
    """The behaviour policy, loaded once per worker and iteration."""
    from worldenv_core.models.checkpoint import load_checkpoint

    return load_checkpoint(path, "policy", contract)[0].eval()


@functools.lru_cache(maxsize=1)
def _member(path: str, contract: TaskContract, perturbation: tuple[int, float], which: str):
    """An ES member: the behaviour policy moved along its seed's direction (`es.perturb`), built once
    per worker for consecutive rollouts of the same member."""
    import copy

    from worldenv_core.rl.es import perturb

    return perturb(copy.deepcopy(_policy(path, contract)), *perturbation, which).eval()


@torch.no_grad()
def real_rollout(job: RealRolloutJob) -> dict:
    """One rollout from the context's start: a chunk is chosen from the camera rendered at its
    boundary, executed step by step, and the rollout stops at the oracle's first success or
    once `horizon` steps are done. A physics failure ends it as a failure, with the error."""
    from worldenv_core.envs.recording import cached_env
    from worldenv_core.envs.replay import restore
    from worldenv_core.models.laplace import laplace_sample

    c = job.contract
    camera = c.cameras[0]
    clock = {"env_build": 0.0, "reset": 0.0, "render": 0.0, "policy": 0.0, "physics": 0.0}
    t0 = time.perf_counter()
    env = cached_env(c.suite, job.start.task_id, c.cameras, c.image_size, render=True)
    policy = (_member(job.policy_path, c, job.perturbation, job.es_parameters) if job.perturbation is not None
              else _policy(job.policy_path, c))
    clock["env_build"] = time.perf_counter() - t0  # ~0 once the worker has this task's env and iteration's policy
    lang = torch.as_tensor(job.instruction, dtype=torch.float32)[None]
    g = torch.Generator().manual_seed(int(job.seed))
    frames, proprio, chunks, executed = [], [], [], []
    first_success, error = None, None

    def timed(part, fn, *args):
        t = time.perf_counter()
        out = fn(*args)
        clock[part] += time.perf_counter() - t
        return out
    try:
        frame = timed("reset", restore, env, job.start)
        t = 0
        while t < job.horizon and first_success is None:
            image = timed("render", env.render, [camera])[camera]
            mu, beta = timed("policy", policy, {camera: torch.from_numpy(image).permute(2, 0, 1)[None]},
                             torch.as_tensor(frame.proprio, dtype=torch.float32)[None], lang)
            a = laplace_sample(mu, beta, g, job.noise_scale, job.exploration)
            if job.keep_frames:
                frames.append(image), proprio.append(frame.proprio.astype(np.float32)), chunks.append(a[0].numpy())
            n = 0
            for action in policy.unnormalize_actions(a)[0].numpy():
                frame = timed("physics", env.step, action)
                t, n = t + 1, n + 1
                if frame.success:
                    first_success = t
                    break
            executed.append(n)
    except Exception as e:  # noqa: BLE001 - a physics failure is a failed rollout, not a dead worker
        error = f"{type(e).__name__}: {e}"
        frames, proprio, chunks = frames[:len(executed)], proprio[:len(executed)], chunks[:len(executed)]
    clock["total"] = time.perf_counter() - t0
    return {"index": job.index, "start": job.start, "seed": job.seed, "frames": frames, "proprio": proprio, "actions": chunks,
            "executed": executed, "first_success": first_success, "error": error, "seconds": clock,
            "steps": sum(executed)}


class RolloutJournal:
    """The finished rollouts of one behaviour policy, one file each (written whole, then renamed), in
    `folder/<weights digest>/`. A rollout is taken back only for the same job: the same policy
    weights, place in the batch, seed, start, horizon and noise (a resumed iteration draws them all
    again from its seed, so they match exactly; anything else is run afresh). Opening a journal
    removes those of other policies: the iterations before this one are finished. With `keep` (a
    folder) they are moved there instead, each beside a copy of its behaviour policy
    (`<digest>_behaviour`): every rollout a run paid for, for analyses that refit on them
    (`analysis.critic_probe`)."""

    def __init__(self, folder: str | Path, behaviour_path: str | Path, keep: str | Path | None = None):
        folder = Path(folder)
        digest = sha256_file(Path(behaviour_path) / "model.safetensors")[:16]
        for old in folder.glob("*"):
            if old.name != digest:
                retire(old, keep)
        self.folder = folder / digest
        self.folder.mkdir(parents=True, exist_ok=True)
        if keep is not None and not (kept := Path(keep) / f"{digest}_behaviour").exists():
            kept.parent.mkdir(parents=True, exist_ok=True)
            shutil.copytree(behaviour_path, kept.with_name(kept.name + ".tmp"), dirs_exist_ok=True)
            kept.with_name(kept.name + ".tmp").rename(kept)

    @staticmethod
    def _job_key(job: RealRolloutJob) -> tuple:
        key = job.index, job.seed, job.start.key, job.horizon, job.noise_scale
        key = key if job.exploration == "step" else (*key, job.exploration)  # journals from before it still match
        return key if job.perturbation is None else (*key, job.perturbation, job.es_parameters)

    def _path(self, job: RealRolloutJob) -> Path:
        return self.folder / _rollout_name(job.index)

    def get(self, job: RealRolloutJob) -> dict | None:
        """The job's rollout, if this journal holds it (and it is whole)."""
        found = _read_rollout(self._path(job))
        return found[1] if found is not None and found[0] == self._job_key(job) else None

    def add(self, job: RealRolloutJob, result: dict) -> None:
        _write_rollout(self._path(job), self._job_key(job), result)


def _rollout_name(index: int) -> str:
    return f"{int(index):05d}.rollout"


def _read_rollout(path: Path) -> tuple | None:
    """A journal file's (job key, result), or None where it is missing or torn (the rollout is run again)."""
    try:
        return pickle.loads(zlib.decompress(Path(path).read_bytes()))
    except (OSError, zlib.error, pickle.UnpicklingError, EOFError, ValueError):
        return None


def _write_rollout(path: Path, key: tuple, result: dict) -> None:
    write_bytes_atomic(path, zlib.compress(pickle.dumps((key, result)), 1))


def _tuples(x):
    """JSON's lists back to the tuples a job key is made of."""
    return tuple(_tuples(v) for v in x) if isinstance(x, list) else x


OUTCOME_FIELDS = ("index", "seed", "first_success", "error", "steps")


def journal_outcomes(journal: str | Path) -> list[dict]:
    """The outcomes in a journal's folders (the iteration under way) as JSON-able records, for rollouts that kept
    no frames (ES members: only their outcome is read): what another machine needs to take them back
    (`restore_outcomes`), a few hundred bytes each where a rollout costs seconds of physics."""
    out = []
    for f in sorted(Path(journal).glob("*/*.rollout")):
        found = _read_rollout(f)
        if found is None or found[1]["frames"] or found[1]["actions"]:  # torn (run again), or not an outcome only
            continue
        key, r = found
        out.append({"behaviour": f.parent.name, "key": list(key), "start": asdict(r["start"]),
                    "seconds": {k: round(v, 3) for k, v in r["seconds"].items()},
                    **{k: r[k] for k in OUTCOME_FIELDS}})
    return out


def restore_outcomes(journal: str | Path, records: list[dict]) -> int:
    """`journal_outcomes`' records written back as journal files. Each is taken back only by the job of the same
    key under the same behaviour weights (`RolloutJournal.get`), so a record that no longer fits is run again.
    -> how many were written."""
    for rec in records:
        result = {**{k: rec[k] for k in OUTCOME_FIELDS}, "start": RealStart(**rec["start"]), "frames": [],
                  "proprio": [], "actions": [], "executed": [], "seconds": rec["seconds"]}
        path = Path(journal) / rec["behaviour"] / _rollout_name(rec["index"])
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_rollout(path, _tuples(rec["key"]), result)
    return len(records)


def retire(journal: Path, keep: str | Path | None) -> None:
    """A finished iteration's journal folder: removed, or moved into `keep`."""
    if keep is None:
        shutil.rmtree(journal, ignore_errors=True)
        return
    Path(keep).mkdir(parents=True, exist_ok=True)
    target = Path(keep) / journal.name
    if target.exists():  # a resumed run that finished this iteration before: the same rollouts
        shutil.rmtree(journal, ignore_errors=True)
    else:
        shutil.move(str(journal), str(target))


def collect_real_rollouts(behaviour, behaviour_path: str | Path, contract: TaskContract, starts: list[RealStart],
                          instructions: list[str], n_rollouts: int, encoder, horizon: int,
                          generator: torch.Generator | list[torch.Generator], workers: int | None = None, launcher: str = "local",
                          ray_address: str | None = None, progress: bool = False,
                          noise_scale: float = 1.0, journal: str | Path | None = None,
                          keep: str | Path | None = None, exploration: str = "step") -> RolloutBatch:
    """N real rollouts per context (context-major, as `collect_rollouts` draws them) by the
    behaviour policy saved at `behaviour_path` (whose weights are `behaviour`'s), as a
    `RolloutBatch`: reward 1 for a success, 0 otherwise; `by_reflector` marks the successes.
    `generator`: one, or one per context (`distributed.random_rows`). `journal`: a folder keeping
    every finished rollout (`RolloutJournal`); the ones it holds already are not run again; `keep`:
    where finished iterations' journals go instead of being removed; `exploration`: a draw per step
    or per chunk."""
    if n_rollouts < 2:
        raise ValueError(f"RLOO needs at least 2 rollouts per context, got N={n_rollouts}")
    chunk = contract.chunk
    horizon = -(-int(horizon) // chunk) * chunk
    seeds = random_rows(lambda shape, generator: torch.randint(2**31 - 1, shape, generator=generator),
                        (len(starts) * n_rollouts,), generator).tolist()
    lang = encoder([instructions[i // n_rollouts] for i in range(len(seeds))]).float().cpu()
    jobs = [RealRolloutJob(contract, starts[i // n_rollouts], str(behaviour_path), s, lang[i].numpy(), horizon, noise_scale,
                           index=i, exploration=exploration) for i, s in enumerate(seeds)]
    runs = run_journaled(jobs, behaviour_path, journal, keep, workers, launcher, ray_address, progress)
    return batch_from_runs(runs, behaviour, contract, lang, n_rollouts, noise_scale, exploration)


def by_task(jobs: list[RealRolloutJob]) -> list[RealRolloutJob]:
    """The jobs in the order they should run: one task after another, in index order within a task. A worker keeps
    two tasks' envs and each env its recent scenes, so jobs that cycle through ten tasks (ES members over keyframes
    or placements of several tasks) rebuilt an env and its scene for every rollout: 20-70 s of a 16-step keyframe
    rollout's 30-110 s on a busy machine, where the same jobs grouped by task build each env once per worker.
    Indices (the journal's keys) are unchanged, and `run_journaled` returns the results in index order."""
    return sorted(jobs, key=lambda j: (j.start.task_id, j.index))


def run_journaled(jobs: list[RealRolloutJob], behaviour_path: str | Path, journal: str | Path | None,
                  keep: str | Path | None = None, workers: int | None = None, launcher: str = "local",
                  ray_address: str | None = None, progress: bool = False) -> list[dict]:
    """`real_rollout` of every job (indexed 0..n-1), in index order; with a `journal` folder those it
    holds are taken back and each new one is kept as it finishes (`RolloutJournal`). The rest run one task after
    another (`by_task`)."""
    from worldenv_core.parallel import run_jobs

    book = RolloutJournal(journal, behaviour_path, keep) if journal is not None else None
    runs = [r for r in (book.get(j) for j in jobs) if r is not None] if book else []
    kept = {r["index"] for r in runs}
    todo = by_task([j for j in jobs if j.index not in kept])
    desc = f"real rollouts ({len(kept)} kept from before)" if kept else "real rollouts"
    for r in run_jobs(real_rollout, todo, workers=workers, launcher=launcher, desc=desc, ray_address=ray_address,
                      progress=progress, unit="rollout"):
        if book:
            book.add(jobs[r["index"]], r)
        runs.append(r)
    return sorted(runs, key=lambda r: r["index"])


def collect_member_outcomes(behaviour_path: str | Path, contract: TaskContract, starts: list[RealStart],
                            instructions: list[str], members: list[tuple[int, float]], encoder, horizon: int,
                            which: str = "mean", workers: int | None = None, progress: bool = False,
                            journal: str | Path | None = None, keep: str | Path | None = None) -> dict:
    """Every ES member (`es.antithetic_members`: the behaviour policy at `behaviour_path` moved by
    (seed, coef)) from every start, with its mean actions: the same starts for every member, so their
    returns differ by what the member does. Member-major jobs: a worker rebuilds a member once for its
    consecutive rollouts. -> success and steps (contexts, members), the episodes, the time split."""
    chunk = contract.chunk
    horizon = -(-int(horizon) // chunk) * chunk
    lang = encoder(list(instructions)).float().cpu()
    jobs = [RealRolloutJob(contract, starts[c], str(behaviour_path), 0, lang[c].numpy(), horizon, 0.0,
                           index=m * len(starts) + c, perturbation=members[m], es_parameters=which, keep_frames=False)
            for m in range(len(members)) for c in range(len(starts))]
    runs = run_journaled(jobs, behaviour_path, journal, keep, workers, progress=progress)
    shape = (len(members), len(starts))
    success = torch.tensor([r["error"] is None and r["first_success"] is not None for r in runs]).view(shape).T
    steps = torch.tensor([r["first_success"] or r.get("steps", horizon) for r in runs]).view(shape).T
    return {"success": success, "steps": steps, "episodes": len(runs), "errors": sum(r["error"] is not None for r in runs),
            "timing": {k: sum(r["seconds"][k] for r in runs) for k in runs[0]["seconds"]} if runs else {}}


def batch_from_runs(runs: list[dict], behaviour, contract: TaskContract, lang: torch.Tensor, n_rollouts: int,
                    noise_scale: float = 1.0, exploration: str = "step") -> RolloutBatch:
    """The `RolloutBatch` of finished real rollouts (`real_rollout`'s results in batch order, N per
    context; a journal's files are these): the behaviour log-probabilities in one batch, reward 1
    for a success. `lang` (R, D): each rollout's instruction embedding."""
    from worldenv_core.models.laplace import chunk_log_prob

    chunk = contract.chunk
    n_chunks = max(1, max(len(r["actions"]) for r in runs))
    rows, size = len(runs), contract.image_size
    frames = torch.zeros(rows, n_chunks, 3, size, size, dtype=torch.uint8)
    proprio = torch.zeros(rows, n_chunks, contract.proprio_dim)
    actions = torch.zeros(rows, n_chunks, chunk, contract.action_dim)
    mask = torch.zeros(rows, n_chunks, chunk)
    for i, r in enumerate(runs):
        for k, (img, prop, act, n) in enumerate(zip(r["frames"], r["proprio"], r["actions"], r["executed"])):
            frames[i, k] = torch.from_numpy(img).permute(2, 0, 1)
            proprio[i, k], actions[i, k] = torch.from_numpy(prop), torch.from_numpy(act)
            mask[i, k, :n] = 1
    dev = next(behaviour.parameters()).device  # the batch lives where PPO trains
    frames, proprio, actions, mask, lang = (x.to(dev) for x in (frames, proprio, actions, mask, lang))
    live = mask[:, :, 0] > 0
    rr, cc = live.nonzero(as_tuple=True)
    logp = torch.zeros(rows, n_chunks, chunk, device=dev)
    with torch.no_grad():
        camera = behaviour.cameras[0]
        mu, beta = behaviour.eval()({camera: frames[rr, cc]}, proprio[rr, cc], lang[rr])
        logp[rr, cc] = chunk_log_prob(actions[rr, cc], mu, beta, noise_scale, exploration)  # as the actions were drawn
        betas = beta.mean() if len(rr) else torch.tensor(float("nan"))
        mu_old, beta_old = torch.zeros_like(actions), torch.zeros_like(actions)
        mu_old[rr, cc], beta_old[rr, cc] = mu, beta
    success = torch.tensor([r["error"] is None and r["first_success"] is not None for r in runs], device=dev)
    rewards = success.float()
    return RolloutBatch(frames=frames, proprio=proprio, instruction=lang, actions=actions, logp_old=logp * mask,
                        mask=mask, rewards=rewards,
                        advantages=rloo_advantages(rewards.view(-1, n_rollouts)).reshape(-1),
                        t_end=mask.sum((1, 2)).long(), by_reflector=success, beta_mean=float(betas),
                        mu_old=mu_old, beta_old=beta_old, noise_scale=float(noise_scale), exploration=exploration,
                        timing={k: sum(r["seconds"][k] for r in runs) for k in runs[0]["seconds"]} if runs else {})
