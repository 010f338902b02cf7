import pytest

from pipeline.report.markdown import demote_headings, extract_block, markdown_table, replace_block, replace_section


def test_markdown_table_fixed_decimals_and_order():
    md = markdown_table([{"eps": 0.5, "err": 1.23456, "n": 3}, {"eps": 0.05, "err": 10.0, "n": 4}], decimals=3)
    lines = md.strip().splitlines()
    assert lines[0].split("|")[1].strip() == "eps"
    assert "1.235" in lines[2] and "10.000" in lines[3]
    assert "| 3 " in lines[2] or "|   3 |" in lines[2] or " 3 |" in lines[2]


def test_markdown_table_missing_column():
    with pytest.raises(KeyError, match="lack columns"):
        markdown_table([{"a": 1.0}], columns=["a", "b"])


def test_blocks_and_sections_round_trip():
    text = "# Title\n\nintro\n"
    text = replace_block(text, "results", "| a |\n|---|\n| 1 |")
    assert extract_block(text, "results") == "| a |\n|---|\n| 1 |"
    text2 = replace_block(text, "results", "new")
    assert extract_block(text2, "results") == "new" and text2.count("results:start") == 1
    assert extract_block("nothing", "results") is None

    md = replace_section("", "Rendering", "r1")
    md = replace_section(md, "Training", "t1")
    md = replace_section(md, "Rendering", "r2")
    assert md.index("## Rendering") < md.index("## Training") and "r1" not in md and "r2" in md


def test_demote_headings():
    assert demote_headings("# A\ntext #x\n## B\n") == "## A\ntext #x\n### B\n"
