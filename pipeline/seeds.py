"""Every random stream's seed, in one place: `seed_for(base, stream, index)`.

A stage's streams start from its base seed (params `seed`; `lab.seed` for lab and lab_models; the evaluation's,
the validation trajectories' and the final held-out set's bases, `run_base(seed, "evaluate" | "validation" |
"heldout")`, for their renders and attack schedules) plus the stream's offset below, plus the index of the item
drawn (a trajectory, an eps, a batch) when a stream has several. Only this module holds a seed offset
(tests/test_architecture.py checks that no other module adds a literal number to a seed).

`run_base` gives the base of a set of trajectories that must differ from one seed run to the next (issue 39, item
5: seed runs pool to independent trajectories): the stream's offset plus RUN_STRIDE times the run's `seed`. The
items drawn from a base (base + the item's stream offset + its index) stay within RUN_STRIDE of the evaluation base
for sets of fewer than 80,000 trajectories, so they never meet another seed run's; seed 0 keeps the bases the
committed outputs were made with (1000, 3000).

These offsets are the values the committed outputs (dvc.lock) were made with, including the known collision of
"guidance" and "shap" (both 500: the closed loop's attacks and the SHAP background draw share a stream of the same
base seed). The switch to seeds derived from hashed stream names (issue 36) changes every output, so it is made
with the next output-changing run, not before.
"""

from __future__ import annotations

STREAMS: dict[str, int] = {
    # the stages' own streams, on their base seed
    "render": 100,
    "label": 200,
    "train": 300,
    "attack": 400,
    "guidance": 500,
    "shap": 500,
    "detect": 600,
    "lab_models": 700,
    "robustness": 1500,
    "lab": 0,
    "robust": 1600,
    "ablation": 1700,
    "background": 1800,  # render.background draws (Earth, stars, sensor noise); index: none, per frame inside
    "suite": 2000,  # the strongest-attack suite on the pose models: its test sample and attack draws
    "bound": 2100,  # rpod bound's targeted attacks that realise the worst sequences in images; index: chain x eps
    "evaluate.schedule": 17,  # on the evaluation's base; index: the trajectory
    "evaluate.black_level": 41,  # on the evaluation's base: the clamp's held-out check (frames, simulated lab shift)
    "evaluate": 1000,  # run_base: the evaluation trajectories' base (was the param evaluate.seed)
    "validation": 3000,  # run_base: the defense's validation trajectories' base (was defense.val_seed)
    "heldout": 7000,  # run_base: the final held-out trajectories (rpod heldout), read by no choice or calibration
    "heldout.lab": 95000,  # on the held-out base, past its trajectories' items: the lab-like recordings' draws; index: draw
    "execution": 1900,  # the closed loop's execution errors (pipeline/guidance/dynamics.py), on `seed`
    # streams within a stage or a library step, on the seed it was given
    "eval_render.trajectory": 1,  # index: the trajectory of the set
    "eval_render.envelope": 500,  # datasets/val_envelope on the validation base: no draw shared with val_render
    "eval_render.execution": 10000,  # index: the trajectory; its execution errors, on the set's base
    "robustness.fgsm": 0,  # the FGSM rows' generator: the robustness seed itself
    "robustness.pgd": 100,  # index: the eps (PGD and the adaptive attack at lambda = 0 share it)
    "robustness.transfer": 200,  # index: 10 x the attack + the eps
    "robustness.surrogate": 500,  # index: 10 x the attack + the eps
    "robustness.burst": 800,
    "robustness.drift": 900,
    "lab.schedule": 31,  # index: the lab sequence
    "splits.validation": 1,  # the validation fold, on the split's seed
    "lid.reference": 1,  # LID's reference minibatches, on the detector's seed
    "suite.check": 1,  # the suite's stability-check subsample, on the suite's seed
    "suite.full": 2,  # the suite's lean-vs-full subsample, on the suite's seed
    "suite.capacity": 3,  # the capacity's validation frames and attack draws, on the suite's seed
}


RUN_STRIDE = 100_000  # run_base: seed runs' trajectory bases lie this far apart
RUN_STREAMS = ("evaluate", "validation", "heldout")  # the trajectory sets with a base per seed run


def run_base(seed: int, stream: str) -> int:
    """The base seed of `stream` (one of RUN_STREAMS) in the seed run `seed`: STREAMS[stream] + RUN_STRIDE
    * seed (module docstring), so every seed run draws its own trajectories."""
    if stream not in RUN_STREAMS:
        raise KeyError(f"run_base is for the trajectory sets {', '.join(RUN_STREAMS)}, not {stream!r}")
    return STREAMS[stream] + RUN_STRIDE * int(seed)


def seed_for(base: int, stream: str, index: int = 0) -> int:
    """The seed of `stream` (a key of STREAMS) for item `index` on the base seed `base`."""
    if stream not in STREAMS:
        raise KeyError(f"unknown random stream {stream!r}; declare it in pipeline/seeds.py STREAMS")
    return int(base) + STREAMS[stream] + int(index)
