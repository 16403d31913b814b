"""Assemble README.md from docs/readme/*.md (one fragment per area) and the pipeline graph.

Run from the repository root: ``python docs/assemble_readme.py``.
"""

from pathlib import Path

from gaitflow.stages.graph import load, markdown_table

ROOT = Path(__file__).resolve().parents[1]
ORDER = [
    "_head",
    "_status",
    "_architecture",
    "bus-runtime",
    "recording",
    "simulator",
    "session-io",
    "mocap",
    "labelling",
    "gait",
    "deploy",
    "_development",
]


def main() -> None:
    parts = []
    for name in ORDER:
        path = ROOT / "docs" / "readme" / f"{name}.md"
        if path.exists():
            parts.append(path.read_text().strip())
    text = "\n\n".join(parts) + "\n"
    text = text.replace("GRAPH_TABLE", markdown_table(load()))
    (ROOT / "README.md").write_text(text)


if __name__ == "__main__":
    main()
