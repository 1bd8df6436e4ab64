"""recognition_by_lead: the counts per lead, which leads an episode is too short for, and the ceiling
row (real video) beside the imagined one, on the tiny world model and an untrained reflector whose
threshold makes it fire always (eta 0) or never (eta 1)."""
import numpy as np
import torch
from hydra.utils import instantiate

from stages.train_reflector.horizon import lead_table, plot_by_lead, recognition_by_lead
from tests.conftest import synthetic_episode
from tests.worldenv_core.imagination.conftest import REFLECTOR, TINY, camera
from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.kinematics import NextStateModel
from worldenv_core.models.worldsim import WorldSimulator


def _setup():
    torch.manual_seed(0)
    sims = {t: ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0)) for t in (0, 1)}
    rng = np.random.default_rng(0)
    # successes at steps 12 and 30 (leads 8 fit both, 16 only the second), one failure of 40 steps
    eps = [synthetic_episode(rng, size=32, length=40, colour=0, succeed_at=12),
           synthetic_episode(rng, size=32, length=56, colour=1, succeed_at=30),
           synthetic_episode(rng, size=32, length=40, colour=0)]
    encoder = lambda texts: torch.stack([torch.full((16,), float(len(t))) for t in texts])  # noqa: E731
    return instantiate(REFLECTOR).eval(), encoder, sims, eps


def test_counts_per_lead_and_the_leads_an_episode_is_too_short_for(tmp_path):
    model, encoder, sims, eps = _setup()
    always = recognition_by_lead(model, encoder, sims, eps, eta=0.0, stride=4, camera="agentview", leads=(8, 16, 32))
    assert always["after"] == 24
    # the failure is started before its last 24 steps (step 16): lead 8 fits it, 16 does not
    assert always["leads"]["8"] == {"successes": 2, "recognised": 2, "recognised_real": 2, "failures": 1,
                                    "false_fires": 1, "false_fires_real": 1}
    assert always["leads"]["16"] == {"successes": 1, "recognised": 1, "recognised_real": 1, "failures": 0,
                                     "false_fires": 0, "false_fires_real": 0}
    assert always["leads"]["32"]["successes"] == 0
    never = recognition_by_lead(model, encoder, sims, eps, eta=1.0, stride=4, camera="agentview", leads=(8, 16, 32))
    assert never["leads"]["8"] == {"successes": 2, "recognised": 0, "recognised_real": 0, "failures": 1,
                                   "false_fires": 0, "false_fires_real": 0}
    header, rows = lead_table(always)
    assert len(header) == len(rows[0]) == 5 and rows[0][1] == "2 / 2 (100 %)" and rows[2][1] == "0 / 0"
    plot_by_lead(always, tmp_path / "by_lead.png")
    assert (tmp_path / "by_lead.png").stat().st_size > 0
