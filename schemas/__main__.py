"""Write the JSON Schema file of every stream beside this module."""

import json
from pathlib import Path

from gaitflow.schemas import STREAMS, json_schema


def main() -> None:
    here = Path(__file__).parent
    for name, cls in sorted(STREAMS.items()):
        (here / f"{name}.json").write_text(json.dumps(json_schema(cls), indent=2) + "\n")


if __name__ == "__main__":
    main()
