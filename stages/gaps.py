"""`rpod gaps`: issue 38's "differences from the paper" table -> reports/gaps.md, reports/metrics/gaps.json.

Reads the metrics of `rpod attitude` (the pose trials), `rpod ablation` (the paper's FGSM and detector protocol) and
`rpod detect`, and writes, per headline number far from the paper's, each measured cause's contribution with its
interval, the causes together, the share of the gap and what is left (stages/pages/gaps.py). `--sync-readme` copies
the table into README.md (between the `gaps` markers) on the default profile; `rpod report --check` fails when the two
drift apart.
"""

from __future__ import annotations

import typer

from pipeline.io.atomic import atomic_write_text, read_json
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import ABLATION_METRICS, ATTITUDE_METRICS, DETECT_METRICS, GAPS_METRICS, GAPS_REPORT, README
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.gaps import CAUSES, gaps, gaps_page

BLOCK = "gaps"
README_PROFILE = "default"  # the only profile whose numbers README.md publishes


def main(
    params: Params,
    sync_readme: bool = typer.Option(
        False, "--sync-readme", help="Also copy the table into README.md (default profile)."
    ),
) -> None:
    """Tabulate the measured causes of each gap to the paper (from the attitude, ablation and detect metrics)."""
    sources = {}
    for path, stage in ((ATTITUDE_METRICS, "attitude"), (ABLATION_METRICS, "ablation"), (DETECT_METRICS, "detect")):
        if not path.exists():
            raise StageError(f"{path} not found: run `rpod {stage}` first (dvc repro optional/dvc.yaml:{stage})")
        sources[stage] = read_json(path)
    for stage, m in sources.items():
        if m.get("profile") != params.profile_name:
            raise StageError(
                f"{stage}'s metrics were made on profile {m.get('profile')!r}, params.yaml is {params.profile_name!r}: "
                f"re-run `rpod {stage}`"
            )
    rows = gaps(sources["attitude"], sources["ablation"], sources["detect"])
    write_metrics(GAPS_METRICS, {"gaps": rows, "causes": CAUSES}, params.profile_name)
    page = gaps_page(rows, BLOCK, sources["attitude"].get("changes", {}))
    atomic_write_text(GAPS_REPORT, page)
    typer.echo(
        "gaps: "
        + "; ".join(f"{g['headline']}: {100 * g['explained'][0]:.0f}% of the gap measured" for g in rows)
        + f" -> {GAPS_REPORT}"
    )
    if sync_readme and params.profile_name == README_PROFILE:
        from pipeline.report.markdown import extract_block, replace_block

        atomic_write_text(README, replace_block(README.read_text(), BLOCK, extract_block(page, BLOCK) or ""))
        typer.echo(f"gaps: table copied into {README}")
