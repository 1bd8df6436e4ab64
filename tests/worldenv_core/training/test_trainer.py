"""The shared training loop on a tiny model: phases, running means, checkpoints, evaluations, and
a run interrupted mid-phase that resumes to exactly the weights and history of one that was not."""
import pytest
import torch

from worldenv_core.training import Phase, Trainer, optimize, per_step, step_seed


class Boom(RuntimeError):
    pass


def _run(work, steps=(6, 4), crash_at=None, evaluate=None, evaluate_every=0, deadline=None, after_save=None):
    """A two-phase fit of a linear model on per-step seeded batches, with dropout (global RNG)."""
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Dropout(0.3), torch.nn.Linear(8, 1))
    opts = {"a": torch.optim.Adam(model[0].parameters(), lr=1e-2), "b": torch.optim.SGD(model[2].parameters(), lr=1e-2)}
    trainer = Trainer(work, model, opts, model_config={"_target_": "torch.nn.Identity"}, meta={"kind": "test"},
                      log_every=2, checkpoint_every=3, progress=False)

    def draw(start):
        return per_step(lambda s: torch.randn(5, 4, generator=torch.Generator().manual_seed(step_seed(7, s))), start)

    def update(name):
        def step(x):
            if crash_at is not None and trainer.step == crash_at:
                raise Boom
            loss = model(x).pow(2).mean()
            optimize(loss, opts[name], clip=1.0)
            return {f"loss_{name}": loss.item()}
        return step

    history = trainer.fit([Phase("a", steps[0], draw, update("a")), Phase("b", steps[1], draw, update("b"))],
                          evaluate=evaluate, evaluate_every=evaluate_every, deadline=deadline, after_save=after_save)
    return trainer, model, history


def test_interrupted_run_resumes_bit_identical(tmp_path):
    _, ref_model, ref_history = _run(tmp_path / "ref")
    with pytest.raises(Boom):
        _run(tmp_path / "cut", crash_at=7)  # inside phase b, one step after the checkpoint at 6
    trainer, model, history = _run(tmp_path / "cut")
    assert trainer.step == 10 and history == ref_history
    for a, b in zip(ref_model.state_dict().values(), model.state_dict().values()):
        assert torch.equal(a, b)
    assert [h["step"] for h in history] == [2, 4, 6, 8, 10]
    assert "loss_a" in history[2] and "loss_b" in history[3]  # each phase logs its own values


def test_a_finished_run_trains_nothing_and_saves_final(tmp_path):
    _, _, history = _run(tmp_path)
    trainer, _, again = _run(tmp_path)
    assert again == history and trainer.wall_s < 1.0
    final = trainer.save_final(tmp_path / "final", extra_key=1)
    assert (final / "model.safetensors").exists()
    assert trainer.checkpoints.last.name == "0000010"


def test_evaluations_before_the_first_step_every_n_and_at_the_end(tmp_path):
    seen = []

    def evaluate(step, checkpoint):
        seen.append((step, None if checkpoint is None else checkpoint.name))
        return {"score": float(step)}

    _, _, history = _run(tmp_path, steps=(3, 2), evaluate=evaluate, evaluate_every=2)
    assert seen == [(0, None), (2, "0000002"), (4, "0000004"), (5, "0000005")]
    scores = {h["step"]: h["score"] for h in history if "score" in h}
    assert scores == {0: 0.0, 2: 2.0, 4: 4.0, 5: 5.0}
    assert next(h for h in history if h["step"] == 2)["loss_a"] > 0  # the evaluation joins the step's entry


def test_after_save_sees_each_checkpoint_with_its_evaluation(tmp_path):
    """A copy of the run's state kept outside its work dir (an ES campaign's ledger) is made after each checkpoint,
    when the checkpoint already holds that step's evaluation."""
    seen = []

    def after_save(done):
        history = torch.load(tmp_path / "checkpoints" / "last" / "training_state.pt", weights_only=False)["history"]
        seen.append((done, any("score" in h for h in history if h["step"] == done)))

    _run(tmp_path, steps=(3, 2), evaluate=lambda step, _: {"score": float(step)}, evaluate_every=2, after_save=after_save)
    assert seen == [(2, True), (3, False), (4, True), (5, True)]  # checkpoints every 3 steps, at evaluations, at the end


def test_a_run_past_its_deadline_saves_evaluates_and_stops_and_a_rerun_goes_on(tmp_path):
    """`--minutes` on a leased machine: a plan that overruns ends saved, not killed."""
    import time

    _, ref_model, ref_history = _run(tmp_path / "ref")
    seen = []

    def evaluate(step, checkpoint):
        seen.append((step, None if checkpoint is None else checkpoint.name))
        return {"score": float(step)}

    trainer, _, _ = _run(tmp_path / "cut", steps=(6, 4), evaluate=evaluate, deadline=time.monotonic() - 1)
    assert trainer.stopped_early and trainer.step == 1
    assert seen == [(0, None), (1, "0000001")]  # the stopping step is measured on its checkpoint
    trainer, model, history = _run(tmp_path / "cut", deadline=time.monotonic() + 3600)
    assert not trainer.stopped_early and trainer.step == 10
    for a, b in zip(ref_model.state_dict().values(), model.state_dict().values()):
        assert torch.equal(a, b)
    assert [h.get("loss_b") for h in history if h["step"] > 6] == [h.get("loss_b") for h in ref_history if h["step"] > 6]


def test_an_evaluation_cut_short_is_done_when_the_run_resumes(tmp_path):
    """A run stopped inside an evaluation (its step already checkpointed) evaluates that step
    first thing when it resumes, instead of resuming past it without the point."""
    seen = []

    def evaluate(step, checkpoint):
        seen.append(step)
        if step == 4 and seen.count(4) == 1:
            raise KeyboardInterrupt  # Ctrl-C during the evaluation at step 4
        return {"score": float(step)}

    with pytest.raises(KeyboardInterrupt) as e:
        _run(tmp_path, steps=(3, 3), evaluate=evaluate, evaluate_every=2)
    assert "at step 4 of 6" in str(e.value) and "last checkpoint, step 4, is kept" in str(e.value)
    _, _, history = _run(tmp_path, steps=(3, 3), evaluate=evaluate, evaluate_every=2)
    assert seen == [0, 2, 4, 4, 6]
    assert {h["step"]: h["score"] for h in history if "score" in h} == {0: 0.0, 2: 2.0, 4: 4.0, 6: 6.0}
    _, _, again = _run(tmp_path, steps=(3, 3), evaluate=evaluate, evaluate_every=2)
    assert seen == [0, 2, 4, 4, 6] and again == history  # a finished run evaluates nothing again
