"""Benchmark: start-up time of `dla --version` and `dla info formats/examples/body.json`.

Each run is a fresh interpreter (`python -c` calling `dlacli.cli.app.main`, as the `dla` entry point
does), so the numbers include Python's own start-up and every import the command pulls in. Also
reports whether torch was imported. Prints one JSON object; not a test (speed is never asserted).

Run: python bench/bench_startup.py [--runs 10]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BODY = ROOT / "formats" / "examples" / "body.json"

# Runs main(argv), swallows its SystemExit, then reports on stderr whether torch got imported.
_PROBE = (
    "import sys\n"
    "from dlacli.cli.app import main\n"
    "try:\n"
    "    main(sys.argv[1:])\n"
    "except SystemExit:\n"
    "    pass\n"
    "print('torch-loaded=' + str('torch' in sys.modules), file=sys.stderr)\n"
)

COMMANDS = {
    "version": ["--version"],
    "info_body_json": ["info", str(BODY)],
}


def _once(argv: list[str]) -> tuple[float, bool]:
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, check=False
    )
    elapsed = time.perf_counter() - start
    if "torch-loaded=" not in done.stderr:
        raise SystemExit(f"probe failed for {argv}: {done.stderr.strip()[-500:]}")
    return elapsed, "torch-loaded=True" in done.stderr


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=10)
    args = parser.parse_args()

    result: dict[str, object] = {"runs": args.runs, "python": sys.version.split()[0]}
    _once(["--version"])  # warm the file-system cache and the .pyc files
    for name, argv in COMMANDS.items():
        times, torch_loaded = [], False
        for _ in range(args.runs):
            elapsed, loaded = _once(argv)
            times.append(elapsed)
            torch_loaded |= loaded
        result[name] = {
            "median_s": round(statistics.median(times), 4),
            "min_s": round(min(times), 4),
            "max_s": round(max(times), 4),
            "torch_loaded": torch_loaded,
        }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
