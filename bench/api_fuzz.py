"""A longer schemathesis run over the served API than the suite's bounded one (routines included).

    .venv/bin/python bench/api_fuzz.py [--max-examples 100]

Prints schemathesis' summary; the check is 'no server error' (5xx) on any generated request.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--max-examples", type=int, default=100)
    args = ap.parse_args()
    from tests.support.served import start_served, stop_served

    served = start_served(Path(tempfile.mkdtemp(prefix="bench-fuzz-")))
    try:
        st = str(Path(sys.executable).with_name("schemathesis"))
        r = subprocess.run([st, "run", served.base_url + "/openapi.json", "-H",
                            f"Authorization: Bearer {served.token}", "--checks", "not_a_server_error",
                            "--max-examples", str(args.max_examples), "--request-timeout", "60", "--workers", "1"])
    finally:
        stop_served(served)
    sys.exit(r.returncode)


if __name__ == "__main__":
    main()
