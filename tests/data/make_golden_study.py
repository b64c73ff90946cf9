"""Writes tests/data/golden_study.json: what fixed seeds, fixed secrets and a fixed chat give.

The file pins the candidates (raw and encoded), the recorded request bodies and the final
evaluation of short runs of several methods, so a refactor of the search core can prove it changes
none of them (tests/test_study.py). Regenerate it only when a change to the searches themselves is
intended, and say so in the commit that does:

    python tests/data/make_golden_study.py
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from golden_cases import CASES, golden_record, run_case  # noqa: E402


def main() -> None:
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in CASES:
            run_dir = Path(tmp) / name
            run_case(name, run_dir)
            out[name] = golden_record(run_dir)
    (HERE / "golden_study.json").write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"wrote {HERE / 'golden_study.json'}: {', '.join(out)}")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
