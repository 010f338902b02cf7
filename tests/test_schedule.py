import numpy as np
import pytest

from pipeline.attacks.schedule import attack_schedule, bursts, schedule_bursts
from pipeline.detectors.metrics import detection_delays, frame_metrics, mean_over, undetected_mask


@pytest.mark.parametrize("p, length", [(0.2, 5), (0.05, 10), (0.5, 3)])
def test_bursts_have_the_configured_length_and_start_probability(p, length):
    n = 60_000
    attacked = attack_schedule(n, p, length, seed=3)
    b = schedule_bursts(attacked, length)
    # every attack lasts exactly `length` frames, except possibly one cut by the sequence end
    lengths = np.array([stop - start for start, stop in b])
    assert np.all(lengths[:-1] == length)
    assert lengths[-1] == length or b[-1][1] == n
    assert set(range(n)) >= {i for s, e in b for i in range(s, e)}
    assert sum(lengths) == attacked.sum()
    # a start decision is drawn on every frame outside an attack: starts / decisions ~ p
    decisions = n - (length - 1) * (len(b) - 1) - (b[-1][1] - b[-1][0] - 1)
    p_hat = len(b) / decisions
    sigma = np.sqrt(p * (1 - p) / decisions)
    assert abs(p_hat - p) < 4 * sigma
    # and the attacked fraction matches the renewal-process value p L / (1 + p (L - 1))
    assert attacked.mean() == pytest.approx(p * length / (1 + p * (length - 1)), abs=0.02)


def test_schedule_is_seeded_and_edge_cases():
    a = attack_schedule(500, 0.2, 5, seed=1)
    assert np.array_equal(a, attack_schedule(500, 0.2, 5, seed=1))
    assert not np.array_equal(a, attack_schedule(500, 0.2, 5, seed=2))
    assert not attack_schedule(100, 0.0, 5, seed=0).any()
    assert attack_schedule(100, 1.0, 5, seed=0).all()
    assert len(schedule_bursts(attack_schedule(100, 1.0, 5, seed=0), 5)) == 20
    with pytest.raises(ValueError, match="p_start"):
        attack_schedule(10, 1.5, 5, seed=0)
    with pytest.raises(ValueError, match="length"):
        attack_schedule(10, 0.2, 0, seed=0)


def test_metrics_on_a_hand_made_sequence():
    #            0  1  2  3  4  5  6  7  8  9 10 11
    attacked = [0, 1, 1, 1, 0, 0, 0, 1, 1, 1, 0, 0]
    flagged = [0, 0, 1, 1, 1, 0, 0, 0, 0, 0, 0, 1]
    m = frame_metrics(np.array(attacked, bool), np.array(flagged, bool))
    # correct: frames 0,2,3,5,6,10 -> 6 of 12
    assert m.accuracy == pytest.approx(6 / 12)
    assert m.tpr == pytest.approx(2 / 6)  # frames 2, 3 of 1,2,3,7,8,9
    assert m.fpr == pytest.approx(2 / 6)  # frames 4, 11 of 0,4,5,6,10,11
    assert (m.frames, m.attacked, m.flagged) == (12, 6, 4)
    assert (m.bursts, m.missed_bursts) == (2, 1)
    assert m.mean_delay == pytest.approx(1.0)  # first burst starts at 1, first flag at 2
    und = undetected_mask(np.array(attacked, bool), np.array(flagged, bool))
    assert np.flatnonzero(und).tolist() == [1, 7, 8, 9]
    err = np.arange(12, dtype=float)
    assert mean_over(err, und) == pytest.approx((1 + 7 + 8 + 9) / 4)
    assert np.isnan(mean_over(err, np.zeros(12, bool)))


def test_rates_undefined_without_attacks_and_touching_bursts():
    m = frame_metrics(np.zeros(4, bool), np.array([0, 1, 0, 0], bool))
    assert np.isnan(m.tpr) and m.fpr == pytest.approx(0.25) and m.accuracy == pytest.approx(0.75)
    touching = np.array([1, 1, 1, 1, 0], bool)
    assert bursts(touching) == [(0, 4)]
    assert schedule_bursts(touching, 2) == [(0, 2), (2, 4)]
    d = detection_delays(schedule_bursts(touching, 2), np.array([0, 0, 0, 1, 0], bool))
    assert np.isnan(d[0]) and d[1] == 1
