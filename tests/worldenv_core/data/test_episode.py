import numpy as np
import pytest

from worldenv_core.data.episode import Episode, EpisodeMeta, episode_differences


def _kwargs(ep: Episode) -> dict:
    return dict(meta=ep.meta, images=dict(ep.images), proprio=ep.proprio, joint_pos=ep.joint_pos,
                sim_state=ep.sim_state, success=ep.success, actions=ep.actions,
                step_extras=dict(ep.step_extras))


def test_length_and_dtypes(episode):
    assert episode.length == 10 and episode.num_frames == 11
    assert episode.proprio.dtype == np.float32 and episode.actions.dtype == np.float32
    assert episode.joint_pos.dtype == np.float64 and episode.sim_state.dtype == np.float64
    assert episode.success.dtype == np.bool_


def test_numeric_inputs_are_cast_to_schema_dtypes(episode):
    kw = _kwargs(episode)
    kw["proprio"] = episode.proprio.astype(np.float64)
    kw["actions"] = episode.actions.tolist()
    ep = Episode(**kw)
    assert ep.proprio.dtype == np.float32 and ep.actions.dtype == np.float32
    assert not episode_differences(ep, episode)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("proprio", np.zeros((10, 7), np.float32), r"proprio must have T\+1=11 frames"),
        ("proprio", np.zeros((11, 8), np.float32), r"proprio must be \(11, 7\)"),
        ("joint_pos", np.zeros((11, 6)), r"joint_pos must be \(11, 7\)"),
        ("sim_state", np.zeros(11), r"sim_state must be \(11, S\)"),
        ("success", np.zeros(11, np.int64), "success must be bool"),
        ("success", np.zeros(12, bool), "success must have T\\+1=11 frames"),
        ("actions", np.zeros((10, 6), np.float32), r"actions must be \(T, 7\)"),
    ],
)
def test_shape_errors_name_the_field(episode, field, value, message):
    kw = _kwargs(episode)
    kw[field] = value
    with pytest.raises(ValueError, match=message):
        Episode(**kw)


def test_image_checks(episode):
    kw = _kwargs(episode)
    kw["images"]["wrist"] = episode.images["wrist"].astype(np.float32)
    with pytest.raises(ValueError, match=r"images\['wrist'\] must be uint8"):
        Episode(**kw)
    kw = _kwargs(episode)
    kw["images"]["wrist"] = episode.images["wrist"][:-1]
    with pytest.raises(ValueError, match=r"images\['wrist'\] must be \(11, H, W, 3\)"):
        Episode(**kw)
    kw = _kwargs(episode)
    del kw["images"]["wrist"]
    with pytest.raises(ValueError, match="do not match meta.cameras"):
        Episode(**kw)


def test_step_extras_must_have_T_rows(episode):
    kw = _kwargs(episode)
    kw["step_extras"]["mu"] = np.zeros((11, 7), np.float32)
    with pytest.raises(ValueError, match=r"step_extras\['mu'\] must have T=10 rows"):
        Episode(**kw)


def test_meta_validation():
    base = dict(suite="s", task_id=0, task_name="t", instruction="i", init_state_index=-1, seed=0,
                success=False)
    with pytest.raises(ValueError, match="source"):
        EpisodeMeta(**base, source="robot")
    with pytest.raises(ValueError, match="extra must map str -> str"):
        EpisodeMeta(**base, source="expert", extra={"n": 3})
    with pytest.raises(ValueError, match="fps"):
        EpisodeMeta(**base, source="expert", fps=0.0)


def test_zero_step_episode_is_valid(make_ep):
    ep = make_ep(T=0)
    assert ep.length == 0 and ep.actions.shape == (0, 7) and ep.proprio.shape == (1, 7)


def test_differences_detects_sign_of_zero(episode):
    other = episode.copy()
    other.actions[0, 0] = 0.0  # was -0.0: equal as numbers, different bits
    assert episode_differences(episode, other) == ["actions"]


def test_meta_normalises_numpy_scalars():
    m = EpisodeMeta(suite="s", task_id=np.int64(2), task_name="t", instruction="i",
                    init_state_index=np.int32(-1), seed=np.uint32(5), source="policy",
                    success=np.bool_(True), fps=np.float32(20))
    assert type(m.task_id) is int and type(m.seed) is int and m.success is True and type(m.fps) is float


def test_video_is_one_cameras_frames_channels_first(episode):
    cam = next(iter(episode.images))
    video = episode.video(cam)
    assert video.shape == (episode.num_frames, 3, *episode.images[cam].shape[1:3])
    assert (video.permute(0, 2, 3, 1).numpy() == episode.images[cam]).all()
