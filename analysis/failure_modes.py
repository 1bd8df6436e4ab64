"""How a policy's recorded rollouts fail, read off the gripper's opening alone (no image is decoded).

Each episode is one of: a success; an **empty grasp** (every grasp the fingers made closed on nothing, the
object was never held); a **lost object** (something was held at least once, and the task was not done: dropped,
or carried and not placed); **no grasp** (the fingers never stayed closed). A grasp is a run of at least
`min_steps` frames with the opening under `grasp_below` (fully open reads about 1); it held something when its
settled opening (the median of its second half) stays at or above `empty_below` (LIBERO's black bowls hold the
Panda's fingers at about 0.13; closed on nothing they settle under 0.03).

Why it matters to the imagined route: after an empty grasp the policy carries nothing to the target as if it
held the object, so from then on its real rollout fails while a world model that reads the arm's pose rather
than the object's can imagine the object carried. `--depth lo hi` also says how many failed episodes had
already missed (their first empty grasp over) before the keyframe window of `rl.context_depth` / `--depth` of
`analysis.imagined_ledger` (fractions of the episode). `--keyframes` reads kept `imagined_ledger --episodes`
runs and puts each keyframe context's real and imagined success beside the gripper's phase at that frame
(before a grasp, holding, closed on nothing, after an empty grasp, after a held one): where imagination is
faithful and where it invents the object.

    python -m analysis.failure_modes --episodes "data/libero_spatial/policy-*/task*/policy_*.mcap" \\
        [--depth 0.35 0.7] [--json modes.json]
    python -m analysis.failure_modes --keyframes results/rl_recipes/imagined_keyframes_<run>.json ...

`--reflector R` (with `--episodes` and `+task=<suite>`) also scores every episode's real frames at the chunk
boundaries, as a rollout is scored, and counts per kind how often R crosses its eta: a success model's false
stops by the way the episode failed (the reward's blind spots, no imagination involved).

`--final-state` (with `--episodes`) puts each episode's last recorded simulator state back in the real simulator and
measures the task's `On` goals there (`envs/goals.py`): a failure that ends with the object resting on its target
but 3 cm or more from its centre (LIBERO's tolerance) is counted as **placed off-centre**, not as lost, and the
median offset of those and of the successes is reported. On libero_spatial most "lost objects" are these.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from worldenv_core.cli import user_errors
from worldenv_core.data.mcap_io.read import glob_episode_files
from worldenv_core.files import write_text_atomic

KINDS = ("success", "empty grasp", "lost object", "no grasp", "placed off-centre")  # the last: --final-state only
PHASES = ("before a grasp", "holding", "closed on nothing", "after an empty grasp", "after a held grasp")


def grasps(opening: np.ndarray, grasp_below: float = 0.3, min_steps: int = 8) -> list[tuple[int, int]]:
    """[(first, end)) frame ranges where the fingers stayed closed (opening < grasp_below) >= min_steps frames."""
    closed = np.concatenate([[False], np.asarray(opening) < grasp_below, [False]])
    edges = np.flatnonzero(np.diff(closed.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2]) if b - a >= min_steps]


def classify(opening: np.ndarray, success: bool, grasp_below: float = 0.3, empty_below: float = 0.05,
             min_steps: int = 8) -> tuple[str, int | None]:
    """-> (kind, the frame where the first empty grasp ended, or None)."""
    runs = grasps(opening, grasp_below, min_steps)
    held = [float(np.median(opening[a + (b - a) // 2:b])) >= empty_below for a, b in runs]
    first_empty = next((b for (a, b), h in zip(runs, held) if not h), None)
    if success:
        return "success", first_empty
    if not runs:
        return "no grasp", None
    return ("lost object" if any(held) else "empty grasp"), first_empty


def phase_at(opening: np.ndarray, k: int, grasp_below: float = 0.3, empty_below: float = 0.05,
             min_steps: int = 8) -> str:
    """The gripper's phase at frame k (one of PHASES). Inside a grasp the opening at k says it: at or above
    empty_below something is between the fingers (still closing counts as holding once the grasp is held)."""
    opening = np.asarray(opening)
    phase = "before a grasp"
    for a, b in grasps(opening, grasp_below, min_steps):
        if a > k:
            break
        held = float(np.median(opening[a + (b - a) // 2:b])) >= empty_below
        if k < b:
            return "holding" if held and opening[k] >= empty_below else "closed on nothing"
        phase = "after a held grasp" if held else "after an empty grasp"
    return phase


def keyframe_phases(run: dict, **thresholds) -> list[dict]:
    """A kept `imagined_ledger --episodes` run -> per keyframe context: episode, frame, the gripper's phase,
    the members' real and imagined success there."""
    from worldenv_core.data.mcap_io.read import read_episode

    rows = []
    for part in run["iterations"].values():
        if not part.get("keyframes"):
            raise ValueError("this run has no keyframes: give an `analysis.imagined_ledger --episodes` json")
        for key, real, imagined in zip(part["keyframes"], part["real_by_context"], part["imagined_by_context"]):
            path, k = key.rsplit("@", 1)
            ep = read_episode(path, cameras=[])
            rows.append({"episode": path, "frame": int(k), "episode_success": bool(ep.meta.success),
                         "phase": phase_at(ep.proprio[:, 6], int(k), **thresholds), "real": real,
                         "imagined": imagined})
    return rows


def phase_table(rows: list[dict]) -> str:
    """Markdown: per phase, contexts, mean real and imagined success, contexts imagined a success (>= half the
    members) that fail for real (< half), and the reverse."""
    head = ["phase", "contexts", "real", "imagined", "invented (imagined, not real)", "missed (real, not imagined)"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for phase in PHASES:
        rs = [r for r in rows if r["phase"] == phase]
        if not rs:
            continue
        invented = sum(r["imagined"] >= 0.5 > r["real"] for r in rs)
        missed = sum(r["real"] >= 0.5 > r["imagined"] for r in rs)
        lines.append(f"| {phase} | {len(rs)} | {np.mean([r['real'] for r in rs]):.2f} | "
                     f"{np.mean([r['imagined'] for r in rs]):.2f} | {invented} | {missed} |")
    return "\n".join(lines)


def reflector_stops(ep, judge) -> bool:
    """Does the success model (`judge`: (model, encoder, eta, camera, chunk)) call the episode's real frames a
    success at any chunk boundary?"""
    import torch

    from worldenv_core.rl.termination import check_steps, first_stop

    model, encoder, eta, camera, chunk = judge
    video = torch.from_numpy(ep.images[camera]).permute(0, 3, 1, 2)
    steps = check_steps(len(video), chunk)
    return first_stop(steps, model.score_prefixes(video, ep.meta.instruction, steps, encoder).numpy(), eta) is not None


def end_goals(ep, envs: dict) -> list:
    """The task's `On` goals (`envs.goals.OnOffset`) in the episode's last recorded state, put back in the real
    simulator started as the episode was (fixtures are placed at reset); `envs`: one physics-only env per task."""
    from worldenv_core.envs.goals import on_offsets
    from worldenv_core.envs.libero_env import LiberoEnv

    key = (ep.meta.suite, ep.meta.task_id)
    if key not in envs:
        envs[key] = [LiberoEnv(*key, cameras=(), render=False), None]
    env, last_start = envs[key]
    start = (ep.meta.init_state_index if ep.meta.init_state_index >= 0 else None, ep.meta.seed)
    if start != last_start:  # the same start places the fixtures the same: no second hard reset
        env.reset(init_state=start[0], seed=start[1])
        envs[key][1] = start
    env.set_sim_state(ep.sim_state[-1])
    return on_offsets(env)


def failure_modes(paths: list[Path], depth: tuple[float, float] | None = None, judge=None, final_state: bool = False,
                  **thresholds) -> dict:
    """Counts of each kind overall, by noise scale and by task; with `depth`, how many failures had their first
    empty grasp over before the window's start / end (fractions of each episode's length); with `judge`
    (`reflector_stops`), per kind how many episodes the success model called a success; with `final_state`, failures
    that end with a goal object set down off its target's centre are "placed off-centre" (`end_goals`), and the
    median offsets of those and of the successes are given."""
    from worldenv_core.data.mcap_io.read import read_episode

    if not paths:
        raise FileNotFoundError("no episode matched --episodes")
    total, by_noise, by_task = Counter(), defaultdict(Counter), defaultdict(Counter)
    missed_by, stopped = Counter(), Counter()
    first_empty_at, offsets, envs = [], defaultdict(list), {}
    for path in paths:
        ep = read_episode(path, cameras=[judge[3]] if judge else [], load_sim_state=final_state)
        kind, first_empty = classify(ep.proprio[:, 6], bool(ep.meta.success), **thresholds)
        if final_state:
            goals = end_goals(ep, envs)
            if kind != "success" and any(g.off_centre for g in goals):
                kind = "placed off-centre"
            if kind in ("success", "placed off-centre"):
                offsets[kind] += [g.offset_m for g in goals]
        if judge is not None:
            stopped[kind] += reflector_stops(ep, judge)
        noise = str(ep.meta.extra.get("noise_scale", "-")) if isinstance(ep.meta.extra, dict) else "-"
        for c in (total, by_noise[noise], by_task[ep.meta.task_id]):
            c[kind] += 1
        if kind != "success" and first_empty is not None:
            frac = first_empty / max(ep.length, 1)
            first_empty_at.append(frac)
            if depth is not None:
                missed_by["window start"] += frac <= depth[0]
                missed_by["window end"] += frac <= depth[1]
    failures = sum(total.values()) - total["success"]
    out = {"episodes": len(paths), "counts": dict(total), "by_noise_scale": {k: dict(v) for k, v in sorted(by_noise.items())},
           "by_task": {k: dict(v) for k, v in sorted(by_task.items())}, "failures": failures,
           "first_empty_grasp_ends": {q: float(np.quantile(first_empty_at, p)) for q, p in
                                      (("q25", 0.25), ("median", 0.5), ("q75", 0.75))} if first_empty_at else None}
    for env, _ in envs.values():
        env.close()
    if final_state:
        out["median_offset_m"] = {k: float(np.median(v)) for k, v in offsets.items() if v}
    if judge is not None:
        out["reflector_says_success"] = {k: stopped[k] / total[k] for k in KINDS if total[k]}
    if depth is not None:
        out["depth"] = list(depth)
        out["failures_missed_before"] = {k: missed_by[k] / failures if failures else float("nan")
                                         for k in ("window start", "window end")}
    return out


def table(modes: dict) -> str:
    """Markdown: one row per noise scale and the total, the share of each kind (and, where the success model
    judged them, the share of each kind it called a success)."""
    kinds = KINDS if "median_offset_m" in modes else KINDS[:-1]
    head = ["noise scale", "episodes", *kinds]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    rows = [*modes["by_noise_scale"].items(), ("all", modes["counts"])]
    for name, counts in rows:
        n = sum(counts.values())
        lines.append("| " + " | ".join([name, str(n), *(f"{counts.get(k, 0) / n:.0%}" for k in kinds)]) + " |")
    said = modes.get("reflector_says_success")
    if said:
        lines.append("| the success model says success | | " + " | ".join(
            f"{said[k]:.0%}" if k in said else "-" for k in kinds) + " |")
    return "\n".join(lines)


def load_judge(path: str, eta: float | None, overrides: list[str]):
    """(model, encoder, eta, camera, chunk) for `reflector_stops`: a reflector checkpoint of the task named."""
    from worldenv_core.models.checkpoint import load_checkpoint
    from worldenv_core.models.text import InstructionEncoder
    from worldenv_core.rl.termination import reflector_eta
    from worldenv_core.stage import compose_config, task_contract

    contract = task_contract(compose_config("post_train_loop", ["scale=small", *overrides]))
    model, meta = load_checkpoint(path, "reflector", contract, device="cpu")
    return model.eval(), InstructionEncoder(), reflector_eta(path, eta), meta["camera"], contract.chunk


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--episodes", nargs="+", help="recorded episodes (globs)")
    source.add_argument("--keyframes", nargs="+", type=Path, help="kept `imagined_ledger --episodes` runs (json)")
    p.add_argument("--depth", type=float, nargs=2, help="a keyframe window (fractions of each episode)")
    p.add_argument("--grasp-below", type=float, default=0.3, help="an opening under this is a closed gripper")
    p.add_argument("--empty-below", type=float, default=0.05, help="a settled grasp under this held nothing")
    p.add_argument("--min-steps", type=int, default=8, help="frames a closure lasts to count as a grasp")
    p.add_argument("--reflector", help="with --episodes: a success model checkpoint judging the real frames")
    p.add_argument("--eta", type=float, help="with --reflector: its threshold (default: the reflector's own)")
    p.add_argument("--final-state", action="store_true",
                   help="with --episodes: measure the goals in each episode's last state (the real simulator)")
    p.add_argument("--json", type=Path, help="also write the counts here")
    p.add_argument("overrides", nargs="*", help="Hydra overrides naming the task (+task=...), for --reflector")
    args = p.parse_args(argv)
    thresholds = {"grasp_below": args.grasp_below, "empty_below": args.empty_below, "min_steps": args.min_steps}
    if args.keyframes:
        runs = {}
        for path in args.keyframes:
            run = json.loads(path.read_text())
            runs[str(path)] = {"worldsim": run.get("worldsim"), "contexts": keyframe_phases(run, **thresholds)}
            print(f"{path} (world model {run.get('worldsim')}):\n{phase_table(runs[str(path)]['contexts'])}\n")
        if args.json:
            write_text_atomic(args.json, json.dumps(runs, indent=1))
        return runs
    if args.depth and not 0 <= args.depth[0] <= args.depth[1] <= 1:
        raise ValueError(f"--depth must be 0 <= lo <= hi <= 1, got {args.depth}")
    paths = glob_episode_files(args.episodes)
    judge = None
    if args.reflector:
        judge = load_judge(args.reflector, args.eta, args.overrides)
    modes = failure_modes(paths, tuple(args.depth) if args.depth else None, judge, args.final_state, **thresholds)
    print(table(modes))
    if modes.get("median_offset_m"):
        print("median distance of the goal object from its target's centre at the end: " + ", ".join(
            f"{k} {v * 100:.1f} cm" for k, v in modes["median_offset_m"].items()))
    if modes.get("failures_missed_before"):
        m = modes["failures_missed_before"]
        print(f"failures whose first empty grasp was over by the window's start / end: "
              f"{m['window start']:.0%} / {m['window end']:.0%}")
    if args.json:
        write_text_atomic(args.json, json.dumps({"episodes": args.episodes, **modes}, indent=1))
    return modes


if __name__ == "__main__":
    with user_errors():
        main()
