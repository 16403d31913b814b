"""The README documents what the repository does, and stays in sync with the graph."""

from pathlib import Path

from gaitflow.stages.graph import load, markdown_table

ROOT = Path(__file__).resolve().parents[1]


def test_readme_graph_table_matches_pipeline_yaml() -> None:
    readme = (ROOT / "README.md").read_text()
    assert markdown_table(load()) in readme, "regenerate: python -m gaitflow.stages.graph"


def test_readme_gives_the_two_commands_and_ci_runs_the_test_one() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "make demo" in readme and "make test" in readme
    ci = (ROOT / ".ci" / "run").read_text()
    assert "make test" in ci
    makefile = (ROOT / "Makefile").read_text()
    assert "\ntest:" in makefile and "\ndemo:" in makefile


def test_readme_gait_parameter_table_matches_the_declaration() -> None:
    from gaitflow.stages import gait

    readme = (ROOT / "README.md").read_text()
    assert gait.PARAMS.table() in readme, "regenerate: gaitflow.stages.gait.PARAMS.table()"
