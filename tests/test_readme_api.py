"""The README's Python examples (section "Use the trained chain on your own images", whose text is now docs/api.md: the
README keeps its heading and a link) run as written on the shipped weights, and what the README and that page say of
those weights holds (they hold the camera matrix K)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parent.parent / "README.md"
API = README.parent / "docs" / "api.md"  # the section's text, moved out of README.md
SECTION = "# Use the trained chain on your own images"  # the page's title (a "##" heading in README.md)


def _examples() -> list[str]:
    assert "#" + SECTION in README.read_text() and "(docs/api.md)" in README.read_text()
    text = API.read_text()
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    section = text[start : end if end >= 0 else len(text)]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_the_readme_python_examples_run():
    """Before issue 42 the README showed `chain.track(images, commands, camera)`: no such signature."""
    examples = _examples()
    assert len(examples) == 2 and "chain.track(images, commands, attitudes)" in examples[1]
    n = 3
    images = np.zeros((n, 90, 160, 3), np.uint8)
    images[:, 35:55, 70:90] = 180  # a lit target in view
    scope = {
        "images": images,
        "commands": np.tile([0.0, 0.0, -0.5], (n, 1)),
        "attitudes": np.tile(np.eye(3), (n, 1, 1)),
    }
    for code in examples:
        exec(compile(code, str(API), "exec"), scope)  # noqa: S102  (the page's own code)
    assert scope["out"].position.shape == (n, 3)
    assert scope["trusted"].shape == (n, 3) and scope["pl"].shape == (n,) and scope["available"].dtype == bool


def test_the_shipped_weights_hold_the_camera_matrix():
    """The README said the shipped weights predate K in pose.pt; they hold it."""
    from pipeline.formats.models import read_pose
    from rpodguard.api import BUNDLE

    assert np.asarray(read_pose(BUNDLE / "pose.pt")["K"]).shape == (3, 3)
    assert "predate" not in README.read_text() and "predate" not in API.read_text()
