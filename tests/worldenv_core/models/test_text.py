import numpy as np
import pytest
import torch

from worldenv_core.models import text
from worldenv_core.models.text import InstructionEncoder

INSTRUCTION = "pick up the alphabet soup and place it in the basket"


def _no_model():
    raise AssertionError("the model was loaded although the embedding was on disk")


def test_an_embedding_kept_on_disk_is_read_back_by_a_new_process_without_the_model(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLDENV_CACHE", str(tmp_path))
    first = InstructionEncoder()([INSTRUCTION, "open the drawer", INSTRUCTION])
    assert first.shape == (3, text.EMBED_DIM) and torch.equal(first[0], first[2])
    assert torch.allclose(first.norm(dim=1), torch.ones(3), atol=1e-5)
    kept = sorted(p.name for p in text.cache_dir().glob("*.npy"))
    assert len(kept) == 2 and text.cache_dir().parent.name == "instructions"

    monkeypatch.setattr(text, "_minilm", _no_model)  # a new process: nothing in memory, the model unloadable
    again = InstructionEncoder()([INSTRUCTION, "open the drawer"])
    assert torch.equal(again, first[:2])  # bit for bit


def test_each_instruction_is_encoded_on_its_own_so_its_embedding_does_not_depend_on_the_others(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLDENV_CACHE", "off")
    alone = InstructionEncoder()([INSTRUCTION])
    beside = InstructionEncoder()(["put the bowl on the plate", INSTRUCTION, "a much longer instruction " * 8])
    assert torch.equal(alone[0], beside[1])
    assert not any(tmp_path.iterdir())


def test_a_torn_or_foreign_cache_file_is_encoded_again_and_replaced(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLDENV_CACHE", str(tmp_path))
    want = InstructionEncoder()([INSTRUCTION])[0]
    path = text._path(text.cache_dir(), INSTRUCTION)
    for bad in (b"\x93NUMPY torn", None):
        if bad is None:  # a well-formed file of the wrong shape (another model's)
            np.save(path, np.zeros(7, dtype=np.float32))
        else:
            path.write_bytes(bad)
        assert torch.equal(InstructionEncoder()([INSTRUCTION])[0], want)
        assert torch.equal(torch.from_numpy(np.load(path)), want)


def test_an_unwritable_cache_still_encodes(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("WORLDENV_CACHE", str(blocker))  # its instructions/ folder cannot be made
    out = InstructionEncoder()([INSTRUCTION])
    assert out.shape == (1, text.EMBED_DIM)


@pytest.mark.parametrize("value", ["", None])
def test_the_default_cache_lives_under_the_users_cache_folder(tmp_path, monkeypatch, value):
    if value is None:
        monkeypatch.delenv("WORLDENV_CACHE", raising=False)
    else:
        monkeypatch.setenv("WORLDENV_CACHE", value)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert text.cache_dir().is_relative_to(tmp_path / "worldenv" / "instructions")
    assert text.MODEL_PACKAGE in text.cache_dir().name
