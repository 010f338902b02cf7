"""The paper's detector protocol (clean = pose-test + pose-training images, attacked = attacked pose-test images,
random per-sample split) shares source images between training and test: leaky, by design. Ours does not."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation.protocols import neighbour_fraction, paper_plan, random_split, shared_fraction
from pipeline.evaluation.splits import grouped_split
from pipeline.shap import sample_plan

EPS = [0.01, 0.05]


def _table(n_seq: int = 13, frames: int = 300, test_fraction: float = 0.2, seed: int = 0):
    """A label table's sequence, frame and per-frame train/test split columns, as `rpod label` makes them."""
    rng = np.random.default_rng(seed)
    sequence, frame = np.repeat(np.arange(n_seq), frames), np.tile(np.arange(frames), n_seq)
    split = np.where(rng.random(n_seq * frames) < test_fraction, "test", "train")
    return sequence, frame, split


def test_the_paper_plan_is_test_images_topped_up_with_training_images_and_attacked_test_images():
    _, _, split = _table()
    plan = paper_plan(split, normal=1000, per_eps=500, eps=EPS, rng=np.random.default_rng(1))
    clean, attacked = plan["index"][plan["eps"] == 0], plan["index"][plan["eps"] > 0]
    n_test = int((split == "test").sum())
    assert len(clean) == 1000 and len(attacked) == 1000
    assert (split[clean] == "test").sum() == n_test and len(np.unique(clean)) == 1000  # every test image, once
    assert (split[attacked] == "test").all()
    for e in EPS:
        assert len(np.unique(plan["index"][np.isclose(plan["eps"], e)])) == 500
    with pytest.raises(ValueError, match="need as many test images"):
        paper_plan(split, 100, n_test + 1, EPS, np.random.default_rng(0))


def test_the_paper_protocol_shares_source_images_across_its_split():
    sequence, frame, split = _table()
    plan = paper_plan(split, 1000, 500, EPS, np.random.default_rng(1))
    tr, va, te = random_split(len(plan["index"]), 0.2, 0.2, seed=2)
    assert len(te) == 400 and len(va) == 320 and len(tr) == 1280
    assert len(np.intersect1d(np.r_[tr, va], te)) == 0
    src = plan["index"]
    leak = shared_fraction(src, tr, te)
    assert leak > 0.3  # most test samples' images are also training samples: leaky
    assert neighbour_fraction(sequence[src], frame[src], tr, te) > leak


def test_our_strict_protocol_shares_no_source_image():
    sequence, frame, _ = _table(n_seq=25, frames=100)
    plan = sample_plan(1000, 500, EPS, np.arange(len(sequence)), np.random.default_rng(1))
    tr, va, te = grouped_split(plan["index"], np.round(plan["eps"], 6), 0.2, 0.2, seed=2)
    assert shared_fraction(plan["index"], np.r_[tr, va], te) == 0.0
    # a random per-sample split of the very same samples would leak
    rtr, _, rte = random_split(len(plan["index"]), 0.2, 0.2, seed=2)
    assert shared_fraction(plan["index"], rtr, rte) > 0.3


def test_random_split_refuses_bad_fractions():
    with pytest.raises(ValueError, match="test fraction"):
        random_split(100, 0.0, 0.2, 0)
    with pytest.raises(ValueError, match="cannot be split"):
        random_split(2, 0.2, 0.2, 0)
