from worldenv_core.files import write_text_atomic


def test_a_file_is_replaced_whole_and_no_temporary_is_left(tmp_path):
    path = tmp_path / "report.md"
    path.write_text("old")
    assert write_text_atomic(path, "new\n") == path
    assert path.read_text() == "new\n" and [p.name for p in tmp_path.iterdir()] == ["report.md"]
