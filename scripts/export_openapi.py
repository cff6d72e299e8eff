"""Write the API's OpenAPI schema (what `/api/v1/openapi.json` serves) to a file, without a
server: the dashboard's typed client is generated from it (`web/`, `npm run gen`).

    python scripts/export_openapi.py web/openapi.json
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path


def main(out: str) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from farm.config import Settings
    from services.main import create_app

    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(
            artifact_root=Path(tmp),
            environment="test",
            secret_key="openapi-export-key",
            redis_url="redis://127.0.0.1:1/0",
        )
        spec = create_app(settings, sweeper=False).openapi()
    text = json.dumps(spec, indent=1, sort_keys=True) + "\n"
    Path(out).write_text(text)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: export_openapi.py OUT.json")
    main(sys.argv[1])
