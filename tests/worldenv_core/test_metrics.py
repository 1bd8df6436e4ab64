"""The paired SFT-vs-post-trained test against hand-computed values."""
import math

from worldenv_core.metrics import paired_success_test


def test_paired_success_test_by_hand():
    a = {0: True, 1: True, 2: False, 3: False, 4: False, 5: False, 6: False, 7: True, 8: False}
    b = {0: True, 1: False, 2: True, 3: True, 4: True, 5: True, 6: True, 7: True, 99: True}  # 8 and 99 unpaired
    t = paired_success_test(a, b)
    assert (t["episodes"], t["only_a"], t["only_b"]) == (8, 1, 5)
    assert math.isclose(t["p_value"], 2 * (1 + 6) / 2 ** 6)  # two-sided exact binomial on 6 discordant, k <= 1


def test_paired_success_test_without_disagreement_is_uninformative():
    same = {i: i % 2 == 0 for i in range(10)}
    assert paired_success_test(same, same) == {"episodes": 10, "only_a": 0, "only_b": 0, "p_value": 1.0}
    balanced = paired_success_test({0: True, 1: False}, {0: False, 1: True})
    assert balanced["p_value"] == 1.0
