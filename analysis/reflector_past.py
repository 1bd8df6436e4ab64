"""Does the reward model need a mid-episode context's recorded past? An `evaluate_imagination` run's stored pairs
re-scored with and without it, on both sides.

R(o_{1:t}, g) is trained on whole prefixes from an episode's first frame. A rollout started at a keyframe has the
recorded frames before it (`Context.history`, shown to the reward model since pairing 3); this scores the kept
frames of every pair (imagined and its real replay) once with that past and once from the keyframe on, at the
run's eta, against the real outcome: recall, precision and F1 of "R crossed eta at some check" per side.

    python -m analysis.reflector_past +task=libero_spatial --pairs outputs/libero_spatial-small/evaluate_imagination/<work> \\
        [--reflector checkpoints/libero_spatial/reflector] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from worldenv_core.cli import user_errors
from worldenv_core.files import write_text_atomic


def verdict_scores(outcome: np.ndarray, said: np.ndarray) -> dict:
    """Real outcomes and verdicts (bool arrays) -> how often the verdict said success, its recall, precision, F1."""
    tp = int((said & outcome).sum())
    precision = tp / int(said.sum()) if said.any() else float("nan")
    recall = tp / int(outcome.sum()) if outcome.any() else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if tp else 0.0
    return {"said_success": float(said.mean()), "recall": recall, "precision": precision, "f1": f1}


def best_score(reflector, instruction: torch.Tensor, frames: torch.Tensor, past: torch.Tensor | None) -> float:
    """The highest R over a pair side's checks after its first frame (the rollout's verdict is R > eta at any),
    scored as the pairs' further judges are (`verdict.rescored`); `instruction` embedded, frames (K, 3, H, W)."""
    from worldenv_core.imagination.verdict import rescored

    scores = rescored(reflector, instruction, frames.permute(0, 2, 3, 1).numpy(), lambda _: instruction[None], past)
    return max(scores[1:], default=0.0)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=Path, required=True, help="an evaluate_imagination work dir (store_frames=true)")
    ap.add_argument("--reflector", help="reflector checkpoint (default: checkpoints/<suite>/reflector)")
    ap.add_argument("--eta", type=float, default=None, help="the verdict's threshold (default: the reflector's)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("overrides", nargs="*", help="Hydra overrides naming the task (+task=...)")
    args = ap.parse_args(argv)
    with user_errors():
        from worldenv_core.data.mcap_io import read_episode
        from worldenv_core.imagination.pairs import pair_past, paired_rows
        from worldenv_core.models.checkpoint import load_checkpoint
        from worldenv_core.models.text import InstructionEncoder
        from worldenv_core.rl.termination import reflector_eta
        from worldenv_core.stage import compose_config, task_contract

        contract = task_contract(compose_config("post_train_loop", ["scale=small", *args.overrides]))
        path = args.reflector or f"checkpoints/{contract.suite}/reflector"
        reflector, _ = load_checkpoint(path, "reflector", contract, device="cpu")
        eta, encoder, camera = reflector_eta(path, args.eta), InstructionEncoder(), contract.cameras[0]
        rows = [(row, f) for row, f in paired_rows(args.pairs) if row.get("context_kind") == "episode"]
        if not rows:
            raise FileNotFoundError(f"{args.pairs}: no pair starts in a recorded episode (init states have no past)")
        best: dict[tuple[str, bool], list[float]] = {}
        instructions = {}
        for row, frames_file in rows:
            episode = row["start"].rsplit("@", 1)[0]  # the recorded episode's path, then the frame
            if episode not in instructions:
                instructions[episode] = encoder([read_episode(Path(episode), cameras=[], load_sim_state=False)
                                                 .meta.instruction])[0]
            past = pair_past(row, camera, contract.chunk)
            stored = np.load(frames_file)
            for side in ("imagined", "real"):
                video = torch.from_numpy(stored[side]).permute(0, 3, 1, 2)
                for with_past in (True, False):
                    best.setdefault((side, with_past), []).append(best_score(
                        reflector, instructions[episode], video, past if with_past else None))
        outcome = np.array([row["real_first_success"] is not None for row, _ in rows])
        result = {"pairs": str(args.pairs), "reflector": path, "eta": eta, "rollouts": len(rows),
                  "real_success": float(outcome.mean()),
                  "verdicts": {f"{side}_{'with' if p else 'without'}_past": verdict_scores(outcome, np.array(s) > eta)
                               for (side, p), s in best.items()}}
        for name, v in result["verdicts"].items():
            print(f"{name}: said success {v['said_success']:.2f}, recall {v['recall']:.2f}, "
                  f"precision {v['precision']:.2f}, F1 {v['f1']:.2f}")
        if args.json:
            write_text_atomic(args.json, json.dumps(result, indent=1))
        return result


if __name__ == "__main__":
    main()
