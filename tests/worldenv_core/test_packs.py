"""The packs' shared file handling: written whole, the format checked before any tensor is read."""
import pytest
import torch

from worldenv_core.errors import ConfigError
from worldenv_core.packs import open_pack, write_pack


def test_a_pack_is_written_whole_and_opened_only_as_its_own_format(tmp_path):
    path = write_pack(tmp_path / "a" / "p.st", {"x": torch.arange(3)}, {"format": "fmt-1", "k": "v"})
    assert [p.name for p in path.parent.iterdir()] == ["p.st"]
    with open_pack(path, "fmt-1", "a test pack", "make it") as (f, meta):
        assert meta["k"] == "v" and torch.equal(f.get_tensor("x"), torch.arange(3))
    with pytest.raises(KeyError, match="is not a test pack .*'fmt-1'.*'fmt-2'"):
        with open_pack(path, "fmt-2", "a test pack", "make it", wrong=KeyError):
            pass
    with pytest.raises(ConfigError, match="no test pack at .*: write one with `make it`"):
        with open_pack(tmp_path / "none.st", "fmt-1", "a test pack", "make it"):
            pass
