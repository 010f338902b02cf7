"""Every random stream's seed, in one place: `seed_for(base, stream, index)`.

A stage's streams start from its base seed (params `seed`; `lab.seed` for lab and lab_models; the evaluation's,
the validation trajectories' and the final held-out set's bases, `run_base(seed, "evaluate" | "validation" |
"heldout")`, for their renders and attack schedules). A stream's seed is derived from the base, the stream's name
and the index of the item drawn (a trajectory, an eps, a batch) by hashing all three (numpy's SeedSequence over
the base, the CRC-32 of the name and the index): two streams never share a seed by construction, where the offset
table this replaced let "guidance" and "shap" share one and let a stream's items run into the next stream's
offset. Only this module derives a seed (tests/test_architecture.py checks that no other module adds a literal
number to a seed); a stream must be declared in STREAMS, so a misspelt name is refused rather than silently
drawing a new stream.

`run_base` gives the base of a set of trajectories that must differ from one seed run to the next (issue 39, item
5: seed runs pool to independent trajectories): the hash of the run's `seed` and the set's name.
"""

from __future__ import annotations

import zlib

import numpy as np

STREAMS: frozenset[str] = frozenset(
    {
        # the stages' own streams, on their base seed
        "render",
        "label",
        "train",
        "attack",
        "guidance",
        "shap",
        "detect",
        "lab_models",
        "robustness",
        "lab",
        "robust",
        "ablation",
        "background",  # render.background draws (Earth, stars, sensor noise); index: none, per frame inside
        "suite",  # the strongest-attack suite on the pose models: its test sample and attack draws
        "bound",  # rpod bound's targeted attacks that realise the worst sequences in images; index: chain x eps
        "evaluate.schedule",  # on the evaluation's base; index: the trajectory
        "evaluate.black_level",  # on the evaluation's base: the clamp's held-out check (frames, simulated lab shift)
        "evaluate",  # run_base: the evaluation trajectories' base (was the param evaluate.seed)
        "validation",  # run_base: the defense's validation trajectories' base (was defense.val_seed)
        "heldout",  # run_base: the final held-out trajectories (rpod heldout), read by no choice or calibration
        "heldout.lab",  # on the held-out base: the lab-like recordings' draws; index: draw
        "execution",  # the closed loop's execution errors (pipeline/guidance/dynamics.py), on `seed`
        # streams within a stage or a library step, on the seed it was given
        "eval_render.trajectory",  # index: the trajectory of the set
        "eval_render.envelope",  # datasets/val_envelope on the validation base: no draw shared with val_render
        "eval_render.execution",  # index: the trajectory; its execution errors, on the set's base
        "robustness.fgsm",  # the FGSM rows' generator
        "robustness.pgd",  # index: the eps (PGD and the adaptive attack at lambda = 0 share it)
        "robustness.transfer",  # index: 10 x the attack + the eps
        "robustness.surrogate",  # index: 10 x the attack + the eps
        "robustness.burst",
        "robustness.drift",
        "lab.schedule",  # index: the lab sequence
        "splits.validation",  # the validation fold, on the split's seed
        "lid.reference",  # LID's reference minibatches, on the detector's seed
        "suite.check",  # the suite's stability-check subsample, on the suite's seed
        "suite.full",  # the suite's lean-vs-full subsample, on the suite's seed
        "suite.capacity",  # the capacity's validation frames and attack draws, on the suite's seed
    }
)


RUN_STREAMS = ("evaluate", "validation", "heldout")  # the trajectory sets with a base per seed run
SEED_BITS = 31  # derived seeds lie in [0, 2**31): every consumer (torch, numpy, Blender, Ray) takes them


def _hashed(base: int, stream: str, index: int) -> int:
    """The seed of (base, stream, index): numpy's SeedSequence over the three (the name as its CRC-32)."""
    if base < 0 or index < 0:
        raise ValueError(f"seeds are non-negative: base {base}, index {index} (stream {stream!r})")
    words = np.random.SeedSequence([int(base), zlib.crc32(stream.encode("utf-8")), int(index)]).generate_state(1)
    return int(words[0]) >> (32 - SEED_BITS)


def run_base(seed: int, stream: str) -> int:
    """The base seed of `stream` (one of RUN_STREAMS) in the seed run `seed` (module docstring), so every seed run
    draws its own trajectories."""
    if stream not in RUN_STREAMS:
        raise KeyError(f"run_base is for the trajectory sets {', '.join(RUN_STREAMS)}, not {stream!r}")
    return _hashed(int(seed), stream, 0)  # = seed_for(seed, stream)


def seed_for(base: int, stream: str, index: int = 0) -> int:
    """The seed of `stream` (declared in STREAMS) for item `index` on the base seed `base`."""
    if stream not in STREAMS:
        raise KeyError(f"unknown random stream {stream!r}; declare it in pipeline/seeds.py STREAMS")
    return _hashed(int(base), stream, int(index))
