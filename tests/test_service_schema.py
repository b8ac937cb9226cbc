"""Schemathesis (its CLI, bounded) against the live service's OpenAPI: no 5xx, and answers that
follow the schema (status codes, content types, headers, JSON bodies).

``positive_data_acceptance`` is left out: a schema-valid request may still be refused (a body
that is not a whole number of frames, a centre past the end of the stream, the test server's
small limits), which OpenAPI cannot express.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

MAX_EXAMPLES = 50
SECONDS = 240


def test_openapi_contract(service, tmp_path):
    cli = Path(sys.executable).parent / "schemathesis"
    command = [str(cli), "run", f"{service.url}/openapi.json", "--max-examples", str(MAX_EXAMPLES)]
    command += "--exclude-checks positive_data_acceptance --seed 20241122".split()
    command += "--request-timeout 30 --workers 1 --no-color".split()
    run = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=SECONDS)
    summary = run.stdout[-3000:]
    print("\n" + summary[summary.find("Test cases:") :])
    assert run.returncode == 0, summary
    assert service.get("/healthz").status_code == 200
