"""Every random stream's seed, in one place: `seed_for(base, stream, index)`.

A stage's streams start from its base seed (params `seed`; `lab.seed` for lab and lab_models; `evaluate.seed` for
the evaluation's attack schedules; `defense.val_seed` for the validation renders) plus the stream's offset below,
plus the index of the item drawn (a trajectory, an eps, a batch) when a stream has several. Only this module holds
a seed offset (tests/test_architecture.py checks that no other module adds a literal number to a seed).

These offsets are the values the committed outputs (dvc.lock) were made with, including the known collision of
"guidance" and "shap" (both 500: the closed loop's attacks and the SHAP background draw share a stream of the same
base seed). The switch to seeds derived from hashed stream names (issue 36) changes every output, so it is made
with the next output-changing run, not before.
"""
from __future__ import annotations

STREAMS: dict[str, int] = {
    # the stages' own streams, on their base seed
    "render": 100, "label": 200, "train": 300, "attack": 400, "guidance": 500, "shap": 500, "detect": 600,
    "lab_models": 700, "robustness": 1500, "lab": 0, "robust": 1600, "ablation": 1700,
    "background": 1800,             # render.background draws (Earth, stars, sensor noise); index: none, per frame inside
    "suite": 1900,                  # the strongest-attack suite on the pose models: its test sample and attack draws
    "evaluate.schedule": 17,        # on evaluate.seed; index: the trajectory
    # streams within a stage or a library step, on the seed it was given
    "eval_render.trajectory": 1,    # index: the trajectory of the set
    "eval_render.envelope": 500,    # datasets/val_envelope on defense.val_seed: no draw shared with val_render
    "robustness.fgsm": 0,           # the FGSM rows' generator: the robustness seed itself
    "robustness.pgd": 100,          # index: the eps (PGD and the adaptive attack at lambda = 0 share it)
    "robustness.transfer": 200,     # index: 10 x the attack + the eps
    "robustness.surrogate": 500,    # index: 10 x the attack + the eps
    "robustness.burst": 800,
    "robustness.drift": 900,
    "lab.schedule": 31,             # index: the lab sequence
    "splits.validation": 1,         # the validation fold, on the split's seed
    "lid.reference": 1,             # LID's reference minibatches, on the detector's seed
    "suite.check": 1,               # the suite's stability-check subsample, on the suite's seed
    "suite.full": 2,                # the suite's lean-vs-full subsample, on the suite's seed
    "suite.capacity": 3,            # the capacity's validation frames and attack draws, on the suite's seed
}


def seed_for(base: int, stream: str, index: int = 0) -> int:
    """The seed of `stream` (a key of STREAMS) for item `index` on the base seed `base`."""
    if stream not in STREAMS:
        raise KeyError(f"unknown random stream {stream!r}; declare it in pipeline/seeds.py STREAMS")
    return int(base) + STREAMS[stream] + int(index)
