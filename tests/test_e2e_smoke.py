"""End to end: `make smoke` (scripts/smoke.py: `dvc repro` of the whole stage graph on the smoke profile, in a
temporary copy of the repo), which must leave this checkout exactly as it was (`git status`), then
`dvc repro --force` in the same copy: the Markdown reports must come out byte for byte the same.

The copy (scripts/smoke.py's `copy_repo`) holds the tracked and untracked-but-not-ignored files (what a clean
clone plus local edits has), so the test sees exactly the working tree. A few minutes on 2 cores.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("smoke_script", REPO / "scripts" / "smoke.py")
smoke_script = importlib.util.module_from_spec(spec)
spec.loader.exec_module(smoke_script)
_run = smoke_script.run
REPORTS = [
    "dataset",
    "pose",
    "pose_robust",
    "attack",
    "guidance",
    "detector",
    "detector_robust",
    "integrated",
    "robustness",
    "lab",
    "benchmarks",
    "README",
]
METRICS = ["train", "robust", "attack", "guidance", "detect", "detect_robust", "evaluate", "robustness", "lab"]
FIGURES = [
    "fgsm_example",
    "guidance_trajectories",
    "guidance_defended",
    "timeline",
    "robustness",
    "pose_errors",
    "error_vs_eps",
    "shap_heatmaps",
    "roc",
    "integrity",
]


def tables(md: str) -> list[tuple[str, list[str], list[str]]]:
    """Markdown tables of a page: (heading above, header cells, first cell of every row)."""
    found, heading, header, rows = [], "", None, []
    for line in md.splitlines() + [""]:
        if line.startswith("#"):
            heading = line.lstrip("# ").strip()
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header = cells
            elif not set(line.replace("|", "").strip()) <= set(":- "):
                rows.append(cells[0])
        elif header is not None:
            found.append((heading, header, rows))
            header, rows = None, []
    return found


def rows_under(md: str, heading_start: str, first_header: str) -> list[str]:
    hits = [rows for h, head, rows in tables(md) if h.startswith(heading_start) and head[0] == first_header]
    assert hits, f"no table with first column {first_header!r} under a heading starting {heading_start!r}"
    return hits[0]


def copy_repo(dst: Path) -> dict[str, str]:
    """Copy the working tree into `dst` (scripts/smoke.py's `copy_repo`); the environment to run there."""
    if shutil.which("git") is None:
        pytest.skip("git is needed to list the repository's files")
    return smoke_script.copy_repo(REPO, dst)


def _status() -> str:
    return subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=all"], cwd=REPO, check=True, capture_output=True, text=True
    ).stdout


@pytest.fixture(scope="module")
def smoke_repo(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """`make smoke` itself (scripts/smoke.py, every stage) into a new folder; the checkout's `git status` (tracked,
    untracked and their contents) is checked unchanged by it in test_make_smoke_leaves_the_checkout_as_it_was."""
    if shutil.which("git") is None:
        pytest.skip("git is needed to list the repository's files")
    dst = tmp_path_factory.mktemp("smoke") / "repo"
    before = _status(), subprocess.run(["git", "diff", "HEAD"], cwd=REPO, capture_output=True).stdout
    _run(
        [sys.executable, str(REPO / "scripts" / "smoke.py"), "--dir", str(dst)],
        REPO,
        smoke_script.copy_env(REPO),
        timeout=1800,
    )
    SMOKE_CHECKOUT["before"] = before
    SMOKE_CHECKOUT["after"] = _status(), subprocess.run(["git", "diff", "HEAD"], cwd=REPO, capture_output=True).stdout
    return dst, smoke_script.copy_env(dst)


SMOKE_CHECKOUT: dict[str, tuple[str, bytes]] = {}  # the checkout's git status and diff around `make smoke`


def test_make_smoke_leaves_the_checkout_as_it_was(smoke_repo):
    """`make smoke && make test` passes and `git status` is clean after smoke (issue 29): no tracked file of the
    checkout changed (params.yaml, conf/config.yaml, reports/, dvc.lock, dvclive/) and none appeared."""
    assert SMOKE_CHECKOUT["after"] == SMOKE_CHECKOUT["before"]
    assert yaml.safe_load((REPO / "params.yaml").read_text())["profile_name"] != "smoke"
    assert yaml.safe_load((smoke_repo[0] / "params.yaml").read_text())["profile_name"] == "smoke"


def test_every_stage_ran_on_the_smoke_profile(smoke_repo):
    dst, env = smoke_repo
    for name in REPORTS:
        assert (dst / "reports" / f"{name}.md").stat().st_size > 0, name
    for name in FIGURES:
        assert (dst / "reports" / "figures" / f"{name}.png").stat().st_size > 1000, name
    for name in METRICS:
        m = json.loads((dst / "reports" / "metrics" / f"{name}.json").read_text())
        assert m["profile"] == "smoke", f"{name}.json was not produced by this run"
    # the default pipeline's stages (optional/dvc.yaml's run only on demand, so `dvc status` lists them as not run)
    assert "changed" not in _run(["dvc", "status", "dvc.yaml"], dst, env), (
        "dvc status: stages left stale after dvc repro"
    )
    _run(["rpod", "report", "--check"], dst, env)


def test_dvc_metrics_and_plots_show_after_repro(smoke_repo):
    """`dvc metrics show` prints one row of every headline number under its readable name; `dvc plots show`
    draws every titled plot (DVCLive's curves and ROC data) and every image plot of dvc.yaml from the outputs
    of this fresh clone's `dvc repro`; pose.pt records the camera of the images it was trained on."""
    from pipeline.formats.models import read_pose
    from stages.pages.summary import DVC_METRICS, HEADLINES

    dst, env = smoke_repo
    summary = json.loads((dst / "reports" / "metrics" / "summary.json").read_text())
    keys = {f"{g}.{k}" for g, group in summary.items() for k in group}
    # on smoke no closed-loop run may meet its attack: a rate over zero runs is left out, never made up
    closed_loop = {"guidance.shipped_docked_pct", "in_loop.shipped_recover_collisions_pct"}
    # an optional headline may be absent from a complete run (stages/pages/summary.py), and an integrity number at
    # an eps the profile's integrity.eps does not fly is left out (smoke flies 0.05 only)
    flown = yaml.safe_load((dst / "params.yaml").read_text())["integrity"]["eps"]
    unflown = {
        h.key for h in HEADLINES if h.key.startswith("integrity.") and "_eps_0_01" in h.key and 0.01 not in flown
    }
    allowed = closed_loop | {h.key for h in HEADLINES if h.optional} | unflown
    assert keys <= set(DVC_METRICS) and set(DVC_METRICS) - keys <= allowed
    assert {"integrity.shipped_clean_availability_pct", "pose.shipped_position_m"} <= keys
    header, row = _run(["dvc", "metrics", "show"], dst, env).splitlines()
    assert header.split()[1:] == sorted(keys) and len(row.split()) == 1 + len(keys)
    _run(["dvc", "plots", "show"], dst, env)
    page = (dst / "dvc_plots" / "index.html").read_text()
    assert "cdn.jsdelivr" not in page and "vegaEmbed(" in page  # offline: conf/plots/offline.html
    for entry in yaml.safe_load((dst / "dvc.yaml").read_text())["plots"]:
        if isinstance(entry, str):  # an image plot: the file, or a folder of them
            images = (
                [entry]
                if entry.endswith(".png")
                else sorted(str(p.relative_to(dst)) for p in (dst / entry).glob("*.png"))
            )
            assert images and all(f"<p>{image}" in page for image in images), entry
            continue
        (plot,) = entry.values()
        assert plot["title"] in page and plot["y_label"] in page, plot["title"]
    K = json.loads((dst / "datasets" / "render" / "meta.json").read_text())["K"]
    assert read_pose(dst / "models" / "pose.pt")["K"] == K


def test_every_table_has_the_expected_rows(smoke_repo):
    dst, _ = smoke_repo
    p = yaml.safe_load((dst / "params.yaml").read_text())
    page = lambda name: (dst / "reports" / f"{name}.md").read_text()  # noqa: E731
    eps = lambda values: [f"{float(v):g}" for v in values]  # noqa: E731

    assert rows_under(page("pose"), "Pose estimator", "split")[:3] == ["train", "val", "test"]
    assert rows_under(page("attack"), "Adversarial attack", "eps") == ["clean", *eps(p["attack"]["eps"])]
    for e in p["guidance"]["eps"]:
        rows = rows_under(page("guidance"), f"eps = {float(e):g}", "S (m)")
        assert rows == [f"{float(s):g}" for s in p["guidance"]["start_ranges"]]
    detectors = rows_under(page("detector"), "Comparison with baselines", "detector")
    assert len(detectors) == 5 and detectors[0].startswith("LSTM")
    assert rows_under(page("integrated"), "Detection accuracy", "eps") == [*eps(p["evaluate"]["eps"]), "average"]
    assert "Not run for this detector" in page("detector_robust") and page("detector_robust").startswith(
        "# Attack detector of the shipped chain (robust model)"
    )
    fused = [r for h, head, r in tables(page("integrated")) if h.startswith("The defended chain") and "chain" in head]
    assert fused and fused[0] == [e for e in eps(p["evaluate"]["eps"]) for _ in range(3)]  # paper's, standard, shipped
    m = json.loads((dst / "reports" / "metrics" / "evaluate.json").read_text())
    assert set(m["fused"]["per_eps"]) == set(m["fused"]["standard_per_eps"]) == set(eps(p["evaluate"]["eps"]))
    assert {"accuracy", "tpr", "fpr", "fpr_clean", "harmful_undetected"} <= set(
        m["fused"]["per_eps"][eps(p["evaluate"]["eps"])[0]]
    )
    variants = rows_under(page("guidance"), "The chain inside the loop", "dynamics")
    assert variants == [d for d in p["guidance"]["dynamics"] for _ in range(1 + len(p["guidance"]["defenses"]))]
    assert rows_under(page("lab"), "Integrated detection", "eps") == [*eps(p["evaluate"]["eps"]), "average"]
    assert rows_under(page("lab"), "FGSM on the lab sequences", "eps") == ["clean", *eps(p["attack"]["eps"])]

    r = p["robustness"]
    rob = json.loads((dst / "reports" / "metrics" / "robustness.json").read_text())
    adaptive = [row for row in rob["rows"] if row["adaptive"] and row["lambda"] is not None]
    assert sorted((row["eps"], row["lambda"]) for row in adaptive) == sorted(
        (float(e), float(v)) for e in r["eps"] for v in r["lambdas"]
    )
    assert {row["attack"] for row in rob["rows"]} >= {*r["transfer"], "adaptive pgd, worst over lambda"}
    assert len(rob["corruptions"]) == 1 + sum(len(v) for v in r["corruptions"].values())
    assert rows_under(page("robustness"), "Benign corruptions", "corruption")[0] == "none"
    i = p["integrity"]
    fused = [(row["eps"], row["lambda"]) for row in rob["fused_rows"]]
    burst = "burst" in i["attackers"]  # the nested burst, per frame, where the profile flies it
    assert fused == ([(e, None) for e in sorted(map(float, i["eps"]))] if burst else [])
    assert all(row["n"] > 0 and row["ci_method"] == "bootstrap over trajectories" for row in rob["fused_rows"])
    names = [
        n
        for a in i["attackers"]
        if a != "burst"
        for n in ([f"{a} {b:g} m" for b in i["capture_initial"]] if a.startswith("capture") else [a])
    ]
    chains = rob["integrity"]["chains"]
    assert set(chains) == {"robust", "standard", "control"} and not chains["control"]["defended"]
    for key, chain in chains.items():  # every planned attacker at every eps the chain flew (its ladder)
        flown = chain["summary"]["eps_flown"]
        assert flown and flown == sorted(flown) and set(flown) <= set(map(float, i["eps"])), key
        assert sorted((row["attacker"], row["eps"]) for row in chain["rows"] if row["attacker"] != "burst") == sorted(
            (n, e) for n in names for e in flown
        ), key
    assert set(rob["integrity"]["worst_hmi"]) == set(eps(chains["robust"]["summary"]["eps_flown"]))
    assert page("robustness").split("\n## ")[1].startswith("Safety evidence that can fail")  # the page leads with it
    assert len(rows_under(page("robustness"), "Breaking point per chain", "chain")) == 3
    assert len(rows_under(page("robustness"), "Shipped (robust model", "attacker")) == len(chains["robust"]["rows"])
    assert len(rows_under(page("robustness"), "Standard (the paper", "attacker")) == len(chains["standard"]["rows"])
    assert rows_under(page("robustness"), "The two pose models", "measure")[0].startswith("clean test position")
    in_loop = rows_under(page("guidance"), "The in-loop attacker", "dynamics")  # true-state dynamics only
    g = p["guidance"]  # the shipped chain undefended and each defense, then the standard chain's variants
    assert in_loop == ["true_state"] * (1 + len(g["defenses"]) + len(g["standard_defenses"])) * len(i["in_loop_eps"])
    runs = json.loads((dst / "reports" / "metrics" / "guidance.json").read_text())["in_loop"]["runs"]
    per_cell = sum(1 if g == "capture" else len(i["in_loop_start_ranges"]) for g in i["in_loop_goals"])
    assert len(runs) == len(in_loop) * per_cell  # the capture attacks from acquisition: one start per cell
    guidance = page("guidance")  # after the unmet-shares banner where smoke's calibration missed one (allow_unmet)
    if guidance.startswith("> **Warning: the defense was calibrated with unmet false-alarm shares"):
        guidance = guidance.split("\n\n", 1)[1]
    assert guidance.startswith("# Closed-loop rendezvous: where the shipped chain docks")

    summary = rows_under(page("README"), "Summary against the paper", "result")
    assert len(summary) == 31 + len(p["guidance"]["standard_defenses"]) and summary[0].startswith("pose")
    # 3 breaking points, error / AL at eps 0.05, 2 + 2 worst-HMI rows (shipped, standard), availability
    assert sum(r.startswith("integrity") for r in summary) == 9
    assert sum(r.startswith("closed loop: ") for r in summary) == 2  # the shipped chain's docking misses
    defended = [r for h, head, r in tables(page("README")) if any(c.startswith("defended chain (or)") for c in head)]
    assert defended and defended[0][0].startswith("integrated accuracy at eps")
    assert sum(r.startswith("closed loop") for r in defended[0]) == len(p["guidance"]["dynamics"])
    changed = subprocess.run(["git", "diff", "--quiet", "--", "README.md"], cwd=dst).returncode
    assert changed == 0, "a smoke run rewrote README.md (only the default profile may)"
    assert "Known differences from the paper" in page("README") and "**Scale.**" in page("README")


def test_each_row_runs_on_its_chain(smoke_repo):
    """The shipped chain is the robust model with its own detector and defense everywhere it is used (robustness,
    evaluate's defended rows, guidance's defended grid and in-loop attacker, lab's shipped section, rpod predict on
    the run); the paper's reproduction rows run on the standard model with its own (hash checks)."""
    from pipeline.formats.models import read_detector
    from pipeline.io.atomic import file_hash
    from rpodguard import load_chain

    dst, _ = smoke_repo
    metrics = lambda name: json.loads((dst / "reports" / "metrics" / f"{name}.json").read_text())  # noqa: E731
    standard, robust = (file_hash(dst / "models" / name) for name in ("pose.pt", "pose_robust.pt"))
    assert standard != robust
    for name, model_hash in (("detector.pt", standard), ("detector_robust.pt", robust)):
        assert read_detector(dst / "models" / name)[1]["pose_model_hash"] == model_hash
    for name, model_hash in (("defense_standard.json", standard), ("defense.json", robust)):
        assert json.loads((dst / "models" / name).read_text())["pose_model_hash"] == model_hash
    ev, gd, lab, rob = (metrics(n) for n in ("evaluate", "guidance", "lab", "robustness"))
    assert (metrics("detect")["model_hash"], metrics("detect_robust")["model_hash"]) == (standard, robust)
    assert (ev["model_hash"], ev["shipped"]["model_hash"]) == (standard, robust)  # paper rows, defended rows
    assert (gd["model_hash"], gd["models"]["shipped"]["model_hash"]) == (standard, robust)
    assert (lab["model_hash"], lab["shipped"]["model_hash"]) == (standard, robust)
    assert (rob["model_hash"], rob["integrity"]["chains"]["standard"]["model_hash"]) == (robust, standard)
    assert rob["integrity"]["chains"]["control"]["model_hash"] == robust
    chain = load_chain(dst)
    assert chain.files == tuple(dst / "models" / n for n in ("pose_robust.pt", "detector_robust.pt", "defense.json"))
    assert chain.safety.calibration.model == "robust" and chain.safety.defended is not None  # its own defense


def test_forced_rerun_leaves_every_report_byte_identical(smoke_repo):
    """Reports depend only on the inputs: no timestamps, no wall-clock times, deterministic training.
    (Last in this module: it re-runs every stage in the shared copy.)"""
    dst, env = smoke_repo
    before = {p.name: p.read_bytes() for p in sorted((dst / "reports").glob("*.md"))}
    _run(["dvc", "repro", "--force"], dst, env)
    after = {p.name: p.read_bytes() for p in sorted((dst / "reports").glob("*.md"))}
    assert after.keys() == before.keys()
    changed = sorted(name for name in before if before[name] != after[name])
    assert not changed, f"reports changed by a forced re-run of an unchanged pipeline: {changed}"
