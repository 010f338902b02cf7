"""reports/dataset.md, the dataset card of `rpod label`: counts, ranges, sequences, render settings."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.geometry.labels import POSITION, QUAT

RENDER_SETTINGS = (
    "samples",
    "denoiser",
    "denoise_quality",
    "threads",
    "mesh",
    "mesh_scale",
    "sun_direction",
    "sun_strength",
    "pointing_jitter_deg",
    "max_target_rotation_deg",
    "chunk",
)


def _spread(quantity: str, values: Any) -> dict[str, Any]:
    """A table row: min, mean and max of `values` (an array or a column)."""
    return {"quantity": quantity, "min": float(values.min()), "mean": float(values.mean()), "max": float(values.max())}


def _backgrounds(labels: Any, settings: dict[str, Any]) -> list[str]:
    """The card's section on what lies behind the target (the labels' `background` column): frames per kind and
    split, and the `render.background` settings."""
    from pipeline.report.markdown import markdown_table

    rows = [
        {
            "background": kind,
            "frames": len(g),
            "train": int((g.split == "train").sum()),
            "test": int((g.split == "test").sum()),
        }
        for kind, g in labels.groupby("background")
    ]
    return [
        "## Backgrounds",
        "",
        "`render.background` (pipeline/render/backgrounds.py): black = as without it; space = stars, the sensor's "
        "black offset and read noise; earth = also the sunlit Earth in view. Settings: "
        + ", ".join(f"{k} = {v}" for k, v in settings.items())
        + ".",
        "",
        markdown_table(rows),
    ]


def dataset_card(labels: Any, meta: dict[str, Any], previews: list[Path], card_dir: Path) -> str:
    """reports/dataset.md: counts, ranges (m, px), attitude and pointing spread (deg), settings, where the time
    per image is kept; `previews` are PNG files shown relative to the card's folder `card_dir`."""
    from pipeline.geometry.camera import Intrinsics, project
    from pipeline.pose.metrics import attitude_error_deg

    q = labels[QUAT].to_numpy()
    t = labels[POSITION].to_numpy()
    cam = Intrinsics.from_K(meta["K"], meta["width"], meta["height"])
    uv = project(t, cam)
    angle = attitude_error_deg(q, np.tile([1.0, 0, 0, 0], (len(q), 1)))  # rotation angle from camera axes
    r, source = meta["render"], meta.get("source")
    if not source:
        seqs = _sequences(labels, angle)
    lines = [
        *_counts(labels, meta, source),
        *(_backgrounds(labels, r["background"]) if "background" in labels else []),
        *_ranges(labels, t, uv, angle),
        *(_source_section(source) if source else _render_section(seqs, r)),
        *_camera_notes(meta, cam, source),
    ]
    if previews:
        lines += ["## Preview", "", *[f"![{p.stem}]({os.path.relpath(p, card_dir)})" for p in previews[:2]], ""]
    return "\n".join(lines)


def _sequences(labels: Any, angle: Any) -> Any:
    """Per sequence: frames, train frames, first and last tz (m) and mean attitude angle (deg), a DataFrame."""
    seqs = labels.groupby("sequence").agg(
        frames=("index", "size"),
        train=("split", lambda s: int((s == "train").sum())),
        tz_start=("tz", "max"),
        tz_end=("tz", "min"),
        attitude_mean_deg=("index", lambda i: float(angle[i.to_numpy()].mean())),
    )
    return seqs.reset_index()


def _counts(labels: Any, meta: dict[str, Any], source: dict[str, Any] | None) -> list[str]:
    """The card's title, what its columns mean, and the counts table (images, split, sequences, size in px)."""
    from pipeline.report.markdown import markdown_table

    return [
        "# Dataset card: " + ("imported SPEED/SPEED+ set" if source else "synthetic Jason-1-like target, 60 m to 10 m"),
        "",
        "Written by `rpod label` from `datasets/render/` (`rpod render`). Frames and labels: "
        "`t` = target origin in the OpenCV camera frame (m), `q` = (qw, qx, qy, qz) rotating target-frame "
        "vectors into the camera frame, `r0..r5` = 6-D rotation (first two columns of R).",
        "",
        "## Counts",
        "",
        markdown_table(
            [
                {
                    "images": len(labels),
                    "train": int((labels.split == "train").sum()),
                    "test": int((labels.split == "test").sum()),
                    "sequences": int(labels.sequence.nunique()),
                    "size": f"{meta['width']}x{meta['height']}",
                }
            ]
        ),
    ]


def _ranges(labels: Any, t: Any, uv: Any, angle: Any) -> list[str]:
    """The card's section on ranges: min, mean and max of position (m), image position (px) and attitude (deg)."""
    from pipeline.report.markdown import markdown_table

    return [
        "## Ranges",
        "",
        markdown_table(
            [
                _spread(name, v)
                for name, v in (
                    ("tz (m)", t[:, 2]),
                    ("range = norm of t (m)", labels["range"]),
                    ("tx (m)", t[:, 0]),
                    ("ty (m)", t[:, 1]),
                    ("target centre u (px)", uv[:, 0]),
                    ("target centre v (px)", uv[:, 1]),
                    ("attitude angle from camera axes (deg)", angle),
                )
            ]
        ),
        "The attitude angle is the rotation angle of `q`: it combines the camera's look-at rotation towards "
        "laterally offset chasers, the pointing jitter, and (sequences 5-12) the random target rotation.",
        "",
    ]


def _render_section(seqs: Any, r: dict[str, Any]) -> list[str]:
    """The card's sections on a rendered set: the per-sequence table and the render settings."""
    from pipeline.report.markdown import markdown_table

    return [
        "## Sequences",
        "",
        markdown_table(seqs, decimals=1),
        "## Render settings",
        "",
        markdown_table([{"setting": k, "value": str(r[k])} for k in RENDER_SETTINGS]),
    ]


def _camera_notes(meta: dict[str, Any], cam: Any, source: dict[str, Any] | None) -> list[str]:
    """The card's lines on the camera K (px), its pixel aspect, and where the rendering time is kept."""
    return [
        f"Camera K at {meta['width']}x{meta['height']}: fx={cam.fx:.3f}, fy={cam.fy:.3f}, cx={cam.cx:.3f}, "
        f"cy={cam.cy:.3f} (scaled from the reference K at {meta['camera']['ref_width']}x"
        f"{meta['camera']['ref_height']}). "
        + (
            "Images resized with an area filter; lens distortion is not removed."
            if source
            else "Renderer: Blender Cycles, CPU."
        ),
        "",
        f"Pixel aspect fy/fx = {cam.fy / cam.fx:.4g} (`camera.fy`). The paper prints K_Blender with fy = 360 beside "
        "fx = 640 at 480x270; 360 = 270 x 48/36 is the sensor-width ratio applied to the image height, a common "
        "slip: Blender renders square pixels unless told otherwise and the lab's ZED camera has square pixels. "
        "The default is therefore fy = fx; `camera.fy: 360.0` renders the printed K (0.5625-aspect pixels, which "
        "squash the target vertically).",
        "",
        "Rendering time per image: `reports/metrics/render.json` (`seconds_per_image`) and reports/benchmarks.md.",
        "",
    ]


def _source_section(source: dict[str, Any]) -> list[str]:
    """The card's section on an imported SPEED/SPEED+ folder: which label files made which split."""
    from pipeline.report.markdown import markdown_table

    return [
        "## Source",
        "",
        f"Imported by `rpod render` from `render.source` = {source['folder']} (each image is "
        "its own sequence; the folder's own train/test split is kept).",
        "",
        markdown_table(
            [
                {"split": "train", "labels": source["train"], "images": source["train_images"]},
                {"split": "test", "labels": source["test"], "images": source["test_images"]},
            ]
        ),
    ]
