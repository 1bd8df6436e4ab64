"""How close to an outcome imagination must start for the reflector to see it.

The reflector scores a held-out episode's real video and the world model's open-loop replay of it
from the first frame; when the replay is judged differently, either the reflector does not read
imagined video or the world model never draws the outcome. This splits the two: the world model
starts `lead` steps before the episode's first success (its real frames up to there, then its
recorded actions, open loop) and the reflector scores the whole video, real prefix and imagined
rest, up to `after` steps past the success. A recognised success at a short lead, lost at longer
ones, says the reflector reads imagined video and the world model's dynamics forget the outcome
over the lead; the real video scored on the same steps is the ceiling. Failed episodes are
started the same way before their last `after` steps: a fire there is a false success.
"""

from __future__ import annotations

import numpy as np
import torch

from worldenv_core.imagination.simulator import replay_from_steps
from worldenv_core.rl.termination import check_steps, first_success

LEADS = (8, 16, 32, 64)  # steps before the outcome that imagination starts at
AFTER = 24  # steps scored past it: the reflector's label delay (a chunk) and two chunks more


def recognition_by_lead(model, encoder, sims: dict, episodes, eta: float, stride: int, camera: str,
                        leads=LEADS, after: int = AFTER, generator: torch.Generator | None = None) -> dict:
    """`sims`: task id -> ImaginedSimulator. Per lead: how many successful episodes the reflector
    recognises (fires above eta past the start) in imagination and in the real video, and how many
    failed episodes it fires on. Leads an episode is too short for are left out for it."""
    leads = sorted(int(h) for h in leads)
    rows = {h: dict.fromkeys(("successes", "recognised", "recognised_real", "failures", "false_fires",
                              "false_fires_real"), 0) for h in leads}
    for ep in episodes:
        imgs = ep.video(camera)
        ts = first_success(ep.success)
        end = ts if ts is not None else ep.length - after
        usable = [h for h in leads if end - h >= 1]
        if not usable:
            continue
        sim = sims[ep.meta.task_id]
        starts = [end - h for h in usable]
        n_chunks = -(-(max(usable) + after) // sim.model.chunk)
        frames = replay_from_steps(sim, imgs, torch.from_numpy(ep.proprio), torch.from_numpy(ep.actions), starts,
                                   n_chunks, generator, torch.from_numpy(ep.joint_pos))
        stop = min(end + after, ep.length)  # scored up to this step, real and imagined alike
        steps = np.asarray(check_steps(stop + 1, stride))
        real = model.score_prefixes(imgs[: stop + 1], ep.meta.instruction, steps, encoder).numpy()
        for h, s, imagined in zip(usable, starts, frames):
            video = torch.cat([imgs[: s + 1], imagined[: stop - s]])
            score = model.score_prefixes(video, ep.meta.instruction, steps, encoder).numpy()
            after_start = steps > s
            fired, fired_real = bool((score[after_start] > eta).any()), bool((real[after_start] > eta).any())
            row = rows[h]
            if ts is not None:
                row["successes"] += 1
                row["recognised"] += fired
                row["recognised_real"] += fired_real
            else:
                row["failures"] += 1
                row["false_fires"] += fired
                row["false_fires_real"] += fired_real
    return {"after": after, "leads": {str(h): r for h, r in rows.items()}}


def lead_table(by_lead: dict) -> tuple[list[str], list[list]]:
    """(header, rows) for the report: recognised successes and false fires per lead."""
    frac = lambda k, n: f"{k} / {n}" + (f" ({100 * k / n:.0f} %)" if n else "")  # noqa: E731
    rows = [[h, frac(r["recognised"], r["successes"]), frac(r["recognised_real"], r["successes"]),
             frac(r["false_fires"], r["failures"]), frac(r["false_fires_real"], r["failures"])]
            for h, r in by_lead["leads"].items()]
    return (["imagination starts (steps before the outcome)", "successes recognised, imagined",
             "successes recognised, real", "failures fired on, imagined", "failures fired on, real"], rows)


def plot_by_lead(by_lead: dict, path) -> None:
    from worldenv_core.viz import figure, save_figure

    leads = [int(h) for h in by_lead["leads"]]
    share = lambda k, n: [r[k] / r[n] if r[n] else float("nan") for r in by_lead["leads"].values()]  # noqa: E731
    fig, axes = figure(1, 1, figsize=(4.6, 3.2), squeeze=False)
    ax = axes[0][0]
    ax.plot(leads, share("recognised", "successes"), "o-", label="successes recognised, imagined")
    ax.plot(leads, share("recognised_real", "successes"), "o--", color="gray", label="successes recognised, real")
    ax.plot(leads, share("false_fires", "failures"), "x-", color="tab:red", label="failures fired on, imagined")
    ax.set_xscale("log", base=2)
    ax.set_xticks(leads, [str(h) for h in leads])
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("imagination starts this many steps before the outcome")
    ax.set_ylabel("share of held-out episodes")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
