"""The latent flow world simulator: overfits real frames, samples with 1 and 4 steps, and its
checkpoint refuses another resolution or chunk size."""
import numpy as np
import pytest
import torch

from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.envs.recording import expert_attempt, to_episode
from worldenv_core.kinematics import NextStateModel, PinholeCamera, draw_action_maps
from worldenv_core.metrics import psnr, ssim
from worldenv_core.contract import ContractError
from worldenv_core.models.checkpoint import load_checkpoint, save_model
from worldenv_core.models.worldsim import Autoencoder, WorldSimulator
from worldenv_core.models.worldsim_data import LatentChunks, encode_episode_frames

TINY = dict(image_size=64, chunk=4, memory_offsets=(0, 2), latent_size=16, latent_channels=4, ae_widths=(8, 16),
            width=16, map_channels=4, use_raw_actions=True, sampling_steps=4)
TINY_CFG = {"_target_": "worldenv_core.models.worldsim.WorldSimulator", **TINY, "memory_offsets": [0, 2],
            "ae_widths": [8, 16]}


def test_metrics_on_known_images():
    x = torch.rand(2, 3, 32, 32)
    assert torch.all(psnr(x, x) > 90) and torch.allclose(ssim(x, x), torch.ones(2))
    noisy = (x + 0.2 * torch.randn_like(x)).clamp(0, 1)
    assert torch.all(ssim(noisy, x) < 0.9) and torch.all(psnr(noisy, x) < 20)
    np.testing.assert_allclose(psnr(torch.zeros(1, 3, 4, 4), torch.full((1, 3, 4, 4), 0.1)).item(), 20.0, atol=1e-4)


def test_bad_sizes_are_rejected():
    with pytest.raises(ValueError, match="power of two"):
        Autoencoder(image_size=48, latent_size=16)
    with pytest.raises(ValueError, match="sampling_steps"):
        WorldSimulator(**{**TINY, "sampling_steps": 0})
    with pytest.raises(ValueError, match="memory_offsets"):
        WorldSimulator(**{**TINY, "memory_offsets": (2, 4)})


@pytest.fixture(scope="module")
def real_episode(tiny_env):
    traj = expert_attempt(tiny_env, 0, seed=0, max_steps=60)
    ep = to_episode(tiny_env, traj, init_state_index=0, seed=0, source="expert")
    cam = PinholeCamera.from_sim(tiny_env.sim, "agentview", 64)
    return ep, cam


@pytest.mark.sim
@pytest.mark.timeout(300)
def test_tiny_world_model_overfits_real_frames_and_samples_with_1_and_4_steps(real_episode, tmp_path, contract):
    ep, cam = real_episode
    torch.manual_seed(0)
    model = WorldSimulator(**TINY)
    frames = torch.from_numpy(ep.images["agentview"]).permute(0, 3, 1, 2).contiguous()
    opt = torch.optim.Adam(model.autoencoder.parameters(), lr=2e-3)
    for _ in range(150):
        recon = model.autoencoder.decode(model.autoencoder.encode(frames[::3]))
        loss = (recon - frames[::3].float() / 255).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert psnr(recon.detach(), frames[::3].float() / 255).mean() > 22  # the autoencoder reproduces the scene

    latents = encode_episode_frames(model, ep.images["agentview"])
    model.latent_scale.fill_(float(latents.std()))
    data = LatentChunks([latents], [ep], model.memory_offsets, model.chunk)
    batch = {k: torch.stack([data[i][k] for i in range(0, len(data), 4)]) for k in ("memory", "target", "proprio", "actions", "valid")}
    maps = draw_action_maps(batch["proprio"], cam, size=model.map_size)
    opt = torch.optim.Adam(model.velocity.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(200):
        loss = model.flow_loss(batch["memory"] / model.latent_scale, maps, batch["target"] / model.latent_scale,
                               batch["actions"], batch["valid"], generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-20:]) < 0.5 * np.mean(losses[:20])

    model.eval()
    mem = batch["memory"][:3] / model.latent_scale
    for steps in (1, 4):
        z = model.predict_latents(mem, maps[:3], batch["actions"][:3], steps=steps, generator=g)
        assert z.shape == batch["target"][:3].shape and torch.isfinite(z).all()
        err = (z - batch["target"][:3] / model.latent_scale).pow(2).mean()
        copy = (mem[:, :1] - batch["target"][:3] / model.latent_scale).pow(2).mean()
        assert err < copy, f"{steps}-step samples are no closer to the real latents than copying the last one"

    # imagined rollouts through kinematics + action maps, batched
    sim = ImaginedSimulator(model, NextStateModel.fit([ep]), cam, sampling_steps=1)
    sim.reset(frames[None, :3].expand(2, -1, -1, -1, -1), torch.from_numpy(ep.proprio[2:3]).expand(2, -1),
              torch.from_numpy(ep.proprio[1:2]).expand(2, -1))
    out = sim.step(torch.from_numpy(ep.actions[2:6])[None].expand(2, -1, -1))
    assert out.frames.shape == (2, 4, 3, 64, 64) and out.frames.dtype == torch.uint8
    assert sim.latents.shape[1] == 3 + 4
    with pytest.raises(ValueError, match="actions must be"):
        sim.step(torch.zeros(2, 3, 7))

    # the checkpoint is self-describing and refuses another task contract
    path = save_model(tmp_path / "ws", model, TINY_CFG, {"kind": "worldsim", "image_size": 64, "chunk": 4})
    loaded, _ = load_checkpoint(path, "worldsim", contract(image_size=64, chunk=4))
    torch.testing.assert_close(loaded.encode(frames[:2]), model.encode(frames[:2]))
    with pytest.raises(ContractError, match="image_size=64.*image_size=128"):
        load_checkpoint(path, "worldsim", contract(image_size=128, chunk=4))
    with pytest.raises(ContractError, match="chunk=4.*chunk=8"):
        load_checkpoint(path, "worldsim", contract(image_size=64, chunk=8))


def test_imagined_simulator_refuses_a_camera_of_another_resolution():
    cam = PinholeCamera("agentview", 128, 100.0, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="128 px.*64 px"):
        ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), cam)


def test_detail_transfer_restores_the_real_frame_where_nothing_changed():
    torch.manual_seed(0)
    cam = PinholeCamera("agentview", 64, 100.0, np.zeros(3), np.eye(3))
    model = WorldSimulator(**{**TINY, "detail_gate": 0.3}).eval()
    frames = (torch.rand(2, 1, 3, 64, 64) * 255).to(torch.uint8)
    sim = ImaginedSimulator(model, NextStateModel(), cam)
    assert sim.detail_gate == 0.3  # the checkpoint's setting unless the caller overrides it
    sim.reset(frames, torch.zeros(2, 7))
    same = sim.render(sim.latents[:, -1:])  # the content did not change: the real frame comes back exactly
    torch.testing.assert_close(same[:, 0], frames[:, -1].float() / 255, atol=1e-5, rtol=0)
    other = sim.latents[:, -1:] + 1.0  # decodes to something else: beyond a tiny gate the model's pixels stand
    strict = ImaginedSimulator(model, NextStateModel(), cam, detail_gate=1e-6)
    strict.reset(frames, torch.zeros(2, 7))
    torch.testing.assert_close(strict.render(other), model.decode(other))
    plain = ImaginedSimulator(model, NextStateModel(), cam, detail_gate=0.0)
    plain.reset(frames, torch.zeros(2, 7))
    torch.testing.assert_close(plain.render(plain.latents[:, -1:]), model.decode(plain.latents[:, -1:]))
    with pytest.raises(ValueError, match="detail_gate"):
        WorldSimulator(**{**TINY, "detail_gate": -1.0})


def test_zero_temperature_one_step_sampling_is_the_flow_mean():
    torch.manual_seed(0)
    model = WorldSimulator(**{**TINY, "noise_scale": 0.0}).eval()
    torch.nn.init.normal_(model.velocity.out[-1].weight, std=0.1)  # the zero-initialised head would predict nothing
    mem, maps, acts = torch.randn(2, 2, 4, 16, 16), torch.rand(2, 4, 3, 32, 32), torch.randn(2, 4, 7)
    a = model.predict_latents(mem, maps, acts, steps=1, generator=torch.Generator().manual_seed(1))
    b = model.predict_latents(mem, maps, acts, steps=1, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(a, b)  # no noise: the same answer whatever the generator
    m, mp, idx, act = model._condition(mem, maps, acts)
    with torch.no_grad():  # one Euler step from x0 = 0 at t = 0 is the velocity there: E[x1] - 0
        v = model.velocity(torch.zeros(8, 4, 16, 16), torch.zeros(8), m, mp, idx, act)
    torch.testing.assert_close(a, mem[:, :1] + v.view(2, 4, 4, 16, 16) * model.delta_scale)
    noisy = model.predict_latents(mem, maps, acts, steps=1, noise_scale=1.0, generator=torch.Generator().manual_seed(1))
    assert not torch.allclose(a, noisy)
    with pytest.raises(ValueError, match="noise_scale"):
        WorldSimulator(**{**TINY, "noise_scale": 1.5})


def test_static_snap_returns_small_changes_to_the_last_real_latent():
    from worldenv_core.models.worldsim import snap_static

    anchor = torch.zeros(1, 4, 8, 8)
    z = torch.full((1, 2, 4, 8, 8), 0.05)  # drift everywhere ...
    z[0, :, :, 0, 0] = 1.0  # ... and a real change in one corner
    out = snap_static(z, anchor, threshold=0.15)
    torch.testing.assert_close(out[0, :, :, 0, 0], z[0, :, :, 0, 0])  # the change stands
    torch.testing.assert_close(out[0, :, :, 0, 1], z[0, :, :, 0, 1])  # and so does its neighbour (dilation)
    assert (out[0, :, :, 4:, 4:] == 0).all()  # far from it, drift below the threshold is gone
    z[0, :, :, 4, 4] = 0.225  # halfway up the ramp (1.5x the threshold): half the change is kept
    torch.testing.assert_close(snap_static(z, anchor, 0.15)[0, :, :, 4, 4], torch.full((2, 4), 0.1125))
    with pytest.raises(ValueError, match="static_snap"):
        WorldSimulator(**{**TINY, "static_snap": -0.1})


def test_latent_windows_for_open_loop_training_hold_the_real_past_and_several_chunks():
    from types import SimpleNamespace

    model = WorldSimulator(**{**TINY, "memory_offsets": (0, 2, 5)}).eval()
    T, k = 20, model.chunk
    z = torch.arange(T + 1, dtype=torch.float32)[:, None, None, None].expand(T + 1, 4, 16, 16).contiguous()
    ep = SimpleNamespace(proprio=np.zeros((T + 1, 7), np.float32), actions=np.arange(T * 7, dtype=np.float32).reshape(T, 7),
                         meta=SimpleNamespace(task_id=3), length=T)
    one = LatentChunks([z], [ep], model.memory_offsets, k)
    three = LatentChunks([z], [ep], model.memory_offsets, k, chunks_ahead=3)
    assert len(one) == T and len(three) == T - 2 * k  # starts whose last chunk still has a step in the episode
    item = three[3]  # t = 3
    assert item["target"].shape[0] == item["actions"].shape[0] == item["valid"].shape[0] == 3 * k
    assert item["past"][:, 0, 0, 0].tolist() == [0, 0, 0, 1, 2, 3]  # t-5 .. t, edge-padded at the start
    torch.testing.assert_close(model.memory(item["past"][None])[0], item["memory"])  # depth 0 = teacher forcing
    assert item["target"][:, 0, 0, 0].tolist() == list(range(4, 4 + 3 * k))
    assert item["actions"][0, 0] == 3 * 7  # the action taken at t leads to frame t + 1
    last = three[len(three) - 1]
    assert last["valid"][2 * k:].tolist() == [True] + [False] * (k - 1)  # the last chunk: one step in, the rest masked
    with pytest.raises(ValueError, match="chunks_ahead"):
        LatentChunks([z], [ep], model.memory_offsets, k, chunks_ahead=0)


def test_demo_share_weights_draw_demos_at_the_share_asked_whatever_their_number():
    from types import SimpleNamespace

    def ep(T, source):
        return SimpleNamespace(proprio=np.zeros((T + 1, 7), np.float32), actions=np.zeros((T, 7), np.float32),
                               meta=SimpleNamespace(task_id=0, source=source), length=T)

    eps = [ep(10, "expert"), ep(30, "policy"), ep(40, "policy"), ep(20, "import")]
    data = LatentChunks([torch.zeros(len(e.proprio), 1, 1, 1) for e in eps], eps, (0,), 4)
    w = data.demo_weights(0.5)
    demo = torch.tensor([eps[e].meta.source != "policy" for e, _ in data.index])
    torch.testing.assert_close(w[demo].sum() / w.sum(), torch.tensor(0.5))
    assert len(set(w[demo].tolist())) == len(set(w[~demo].tolist())) == 1  # uniform within each kind
    only_demos = LatentChunks([torch.zeros(11, 1, 1, 1)], [ep(10, "expert")], (0,), 4)
    assert only_demos.demo_weights(0.3).tolist() == [1.0] * 10
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        data.demo_weights(1.0)
    unknown = LatentChunks([torch.zeros(11, 1, 1, 1)], [SimpleNamespace(**{**vars(ep(10, "x")),
                                                                           "meta": SimpleNamespace(task_id=0)})], (0,), 4)
    with pytest.raises(ValueError, match="source.*pack again"):
        unknown.demo_weights(0.5)


def test_next_chunk_is_the_flow_prediction_from_the_history_with_the_static_snap():
    torch.manual_seed(0)
    model = WorldSimulator(**{**TINY, "noise_scale": 0.0, "sampling_steps": 1, "static_snap": 0.15}).eval()
    torch.nn.init.normal_(model.velocity.out[-1].weight, std=0.1)
    history, maps, acts = torch.randn(2, 5, 4, 16, 16), torch.rand(2, 4, 3, 32, 32), torch.randn(2, 4, 7)
    anchor = history[:, 2]
    z = model.next_chunk(history, anchor, maps, acts)
    from worldenv_core.models.worldsim import snap_static

    want = snap_static(model.predict_latents(history[:, [4, 2]], maps, acts), anchor, 0.15)
    torch.testing.assert_close(z, want)
    assert not z.requires_grad  # an input of the open-loop loss, not part of its graph


def test_arm_refiner_starts_as_the_plain_decoder_and_learns_to_draw_where_the_map_says():
    """Zero-initialised, a refiner leaves decoded frames as they are; trained on frames whose only
    content is a disc that the action map alone places, it draws the disc at a held-out position."""
    torch.manual_seed(0)
    cam = PinholeCamera("agentview", 64, 60.0, np.array([0.0, 0.0, 1.0]), np.eye(3))  # looking down at z = 0
    model = WorldSimulator(**{**TINY, "refiner_width": 8}).eval()
    z = torch.randn(3, 4, 16, 16)
    states = torch.zeros(3, 7)
    states[:, 0] = torch.tensor([-0.1, 0.0, 0.1])
    maps = draw_action_maps(states, cam, size=model.map_size)
    torch.testing.assert_close(model.decode(z, maps), model.decode(z))
    with pytest.raises(ValueError, match="refiner_width"):
        WorldSimulator(**{**TINY, "refiner_width": -1})

    def batch(n, gen):  # grey frames with a white disc where the gripper projects: only the map says where
        s = torch.zeros(n, 7)
        s[:, :2] = (torch.rand(n, 2, generator=gen) - 0.5) * 0.5
        s[:, 6] = 1.0
        disc = draw_action_maps(s, cam, size=64)[:, :1].amax(1, keepdim=True) > 0.5
        return torch.full((n, 3, 64, 64), 0.5), draw_action_maps(s, cam, size=model.map_size), torch.where(disc, 1.0, 0.5).expand(-1, 3, -1, -1)

    gen = torch.Generator().manual_seed(1)
    held_images, held_maps, held_target = batch(8, torch.Generator().manual_seed(99))
    on_disc = held_target > 0.75
    before = (model.refiner(held_images, held_maps) - held_target).abs()[on_disc].mean().item()
    opt = torch.optim.Adam(model.refiner.parameters(), lr=3e-3)
    for _ in range(200):
        images, m, target = batch(16, gen)
        loss = ((model.refiner(images, m) - target).abs() * (1 + 20 * (target > 0.75))).mean()  # the arm weight
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = (model.refiner(held_images, held_maps) - held_target).abs()[on_disc].mean().item()
    assert before == pytest.approx(0.5) and after < 0.2, (before, after)


def test_imagined_frames_are_refined_with_their_own_action_maps(tmp_path, contract):
    """The simulator hands each decoded frame's action map to the refiner (the anchor's too), and the
    refiner travels in the checkpoint."""
    torch.manual_seed(0)
    cam = PinholeCamera("agentview", 64, 60.0, np.array([0.0, 0.0, 1.0]), np.eye(3))  # looking down at z = 0
    model = WorldSimulator(**{**TINY, "refiner_width": 8, "detail_gate": 0.0}).eval()
    torch.nn.init.normal_(model.refiner.out[-2].weight, std=0.5)
    frames = (torch.rand(2, 1, 3, 64, 64) * 255).to(torch.uint8)
    proprio = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [0.05, -0.05, 0.0, 0.0, 0.0, 0.0, 0.0]])
    sim = ImaginedSimulator(model, NextStateModel(), cam)
    sim.reset(frames, proprio)
    out = sim.step(torch.zeros(2, 4, 7), decode="all")
    expect = model.decode(out.latents, out.action_maps)
    torch.testing.assert_close(out.frames, (expect * 255).round().to(torch.uint8))
    assert not torch.equal(out.frames, (model.decode(out.latents) * 255).round().to(torch.uint8))
    last = sim.step(torch.zeros(2, 4, 7), decode="last")
    torch.testing.assert_close(last.frames[:, 0], (model.decode(last.latents[:, -1], last.action_maps[:, -1]) * 255)
                               .round().to(torch.uint8))
    cfg = {**TINY_CFG, "refiner_width": 8, "detail_gate": 0.0}
    path = save_model(tmp_path / "ws", model, cfg, {"kind": "worldsim", "image_size": 64, "chunk": 4})
    loaded, _ = load_checkpoint(path, "worldsim", contract(image_size=64, chunk=4))
    torch.testing.assert_close(loaded.decode(out.latents, out.action_maps), expect)
