"""Rewrite the code deps of every stage in dvc.yaml from the source (the derivation of
tests/test_dvc_deps.py); data deps (datasets/, models/, reports/, dvclive/ and "${param}" paths) are kept in their
order.

Run after adding a stage or changing what a stage imports: `python scripts/update_dvc_deps.py`.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import test_dvc_deps as derive  # noqa: E402

WIDTH = 118


def deps_block(deps: list[str]) -> str:
    """`    deps: [...]` wrapped at WIDTH characters."""
    lines, cur = [], "    deps: ["
    for i, d in enumerate(deps):
        item = (f'"{d}"' if d.startswith("${") else d) + (", " if i < len(deps) - 1 else "]")
        if len(cur) + len(item) > WIDTH:
            lines.append(cur.rstrip())
            cur = " " * 11
        cur += item
    return "\n".join(lines + [cur]) + "\n"


def main() -> None:
    for name in derive.PIPELINES:
        path = derive.REPO / name
        text = path.read_text()
        stages = yaml.safe_load(text)["stages"]
        for stage_name, stage in stages.items():
            data = [
                d
                for d in stage.get("deps", [])
                if d.split("/")[0] in ("datasets", "models", "reports", "dvclive") or d.startswith("${")
            ]
            code = sorted(str(f.relative_to(derive.REPO)) for f in derive.stage_files(stage_name))
            m = re.search(rf"(\n  {stage_name}:\n(?:    (?!deps:).*\n)*?)    deps: \[[^\]]*\]\n", text)
            if m is None:
                raise SystemExit(f"{name}: stage {stage_name} has no `deps: [...]` list to rewrite")
            text = text[: m.start()] + m.group(1) + deps_block(data + code) + text[m.end() :]
        path.write_text(text)
        print(f"{path}: code deps of {len(stages)} stages rewritten")


if __name__ == "__main__":
    main()
