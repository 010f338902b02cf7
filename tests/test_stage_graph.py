"""The README's stage graph is generated from `dvc dag` (scripts/stage_graph.py) and matches it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("stage_graph", REPO / "scripts" / "stage_graph.py")
stage_graph = importlib.util.module_from_spec(spec)
spec.loader.exec_module(stage_graph)


@pytest.mark.skipif(not stage_graph.DVC.exists(), reason="dvc not installed beside python")
def test_the_readme_graph_is_the_dvc_dag():
    edges = stage_graph.dag_edges()
    assert ("render", "label") in edges and ("evaluate", "lab") not in edges
    assert ("label", "surrogate") in edges and ("train", "surrogate") not in edges
    text = stage_graph.README.read_text()
    assert stage_graph.rewrite(text, stage_graph.block(edges)) == text, (
        "README.md's stage graph differs from `dvc dag`: run `python scripts/stage_graph.py`"
    )


def test_the_reduction_keeps_paths_and_drops_implied_edges():
    edges = {("a", "b"), ("b", "c"), ("a", "c"), ("c", "d"), ("a", "d"), ("x", "d")}
    assert stage_graph.reduce(edges) == {("a", "b"), ("b", "c"), ("c", "d"), ("x", "d")}


def test_a_readme_without_markers_is_refused():
    with pytest.raises(ValueError, match="stage-graph:start"):
        stage_graph.rewrite("no graph here\n", "x")
