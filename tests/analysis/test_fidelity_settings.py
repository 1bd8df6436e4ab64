"""Re-measuring a world model's fidelity: what it needs is named before any model is loaded."""
import pytest

from analysis.fidelity_settings import main


@pytest.mark.parametrize("argv, message", [
    ([], "name an experiment directory with a train_worldsim record, or --model and --data"),
    (["--data", "data/x"], "--data measures a released checkpoint: name it with --model"),
    (["--model", "no/such/folder", "--data", "data/x"], "--model no/such/folder: no model.safetensors there"),
])
def test_a_missing_input_is_one_line_naming_it(argv, message, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err
