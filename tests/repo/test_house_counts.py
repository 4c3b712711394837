"""The view path is declared once (issue 36's counts, by scripts/house_counts.py, which the closing note quotes):
one render query type, one reader of a pose's numbers, the outputs and the formats spelt out once each, one
statement of the detail stride's range, no Any field in the view type, no import cycle in runtime/, no sys.path
edit. A second declaration added later fails here, naming where it is."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "house_counts.py"


@pytest.fixture(scope="module")
def counts():
    spec = importlib.util.spec_from_file_location("house_counts", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.counts()


@pytest.mark.parametrize("name, want", [
    ("render_query_declarations", 1), ("pose_matrix_parsers", 1), ("output_format_lists", 2), ("stride_rules", 1),
    ("any_fields_in_view_query", 0), ("runtime_import_cycles", 0), ("sys_path_edits", 0),
])
def test_one_of_each(counts, name, want):
    assert counts[name]["count"] == want, counts[name]["where"]


def test_the_counts_find_what_they_count(tmp_path, counts):
    """The detectors are not blind: the one declaration of each kind is where it should be."""
    assert counts["render_query_declarations"]["where"][0].startswith("common/wire.py:")
    assert counts["pose_matrix_parsers"]["where"][0].startswith("common/poses.py:")
    assert all(w.startswith("common/wire.py:") for w in counts["output_format_lists"]["where"])
    assert counts["stride_rules"]["where"][0].startswith("common/wire.py:")
