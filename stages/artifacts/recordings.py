"""The lab recordings of a folder read through the real-data loader (pipeline/formats/recordings.py) with the
params' loader settings (`lab`: bodies, matching, gaps, segmentation) at the network's input size (`render`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from pipeline.formats.recordings import read_recording, recording_folders
from stages.config.schema import Params


def read_recordings(p: Params, source: Path) -> list[Any]:
    """Every recording folder under `source`, read as `read_recording` returns it, in folder order."""
    lab, r = p.lab, p.render
    return [
        read_recording(
            f,
            r.width,
            r.height,
            dataclasses.asdict(lab.bodies),
            lab.match,
            float(lab.max_gap_s),
            float(lab.segment_threshold),
            lab.max_image_pixels,
            float(lab.empty_frame_tolerance),
        )
        for f in recording_folders(source)
    ]
