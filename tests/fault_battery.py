"""The fault battery of docs/faults.md: faults and bad inputs a lab meets, each run through the
command line as a user would, and whether the toolkit handled it.

Handled means: the exit code says what happened (2 bad input, 1 a failure, 130 a signal, 0 when
the work could be done), no traceback, the message names the file or device, and nothing already
recorded or computed is lost or silently wrong (each fault checks its own outcome). It is a
measuring script, not a test: the fault-injection tests (`pytest -m faults`) hold each outcome
in detail. It uses only the command line and long-standing helpers, so that the same battery
can be run on an older checkout for a before/after table:

    python tests/fault_battery.py [--only AREA] [--markdown] [--json FILE]

The faults live in faults_capture.py and faults_offline.py; faults_kit.py runs them.
"""


from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

import faults_capture  # noqa: F401  (registers its faults)
import faults_offline  # noqa: F401  (registers its faults)
from faults_kit import _TAKES, FAULTS, Outcome


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", help="run the faults of this area only")
    parser.add_argument("--json", type=Path, help="also write the outcomes here")
    parser.add_argument("--markdown", action="store_true", help="end with the table as markdown")
    args = parser.parse_args()
    rows = []
    for f in FAULTS:
        if args.only and f.area != args.only:
            continue
        with tempfile.TemporaryDirectory(prefix="fault-") as tmp:
            start = time.perf_counter()
            try:
                result = f.run(Path(tmp))
            except Exception as exc:   # the battery's own failure to set a fault up, shown as such
                result = Outcome(False, f"battery error: {type(exc).__name__}: {exc}"[:160]
                                 + ("" if os.environ.get("BATTERY_QUIET") else "\n" + traceback.format_exc()))
        rows.append({"area": f.area, "fault": f.what, "handled": result.handled, "said": result.said,
                     "s": round(time.perf_counter() - start, 1)})
        print(f"{'ok ' if result.handled else 'NO '} {f.area:12s} {f.what}: {result.said}", flush=True)
    handled = sum(r["handled"] for r in rows)
    print(f"\n{handled} of {len(rows)} faults handled")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if args.markdown:
        print("\n| area | fault | handled | what the user sees |\n|---|---|---|---|")
        for r in rows:
            print(f"| {r['area']} | {r['fault']} | {'yes' if r['handled'] else 'NO'} | {r['said'].replace('|', '/')} |")
    for root in _TAKES.values():
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
