"""Write the pinned outputs of `tests/test_behaviour_identity.py`: `behaviour_identity.npz` (every
array of every case, keys "case/field") and `behaviour_identity.json` (the static facts).

The committed data were produced at commit b755b61 — the main branch before the engine was
restructured into stepper objects — and are the reference the restructured engine must
reproduce. Do NOT regenerate them after that restructuring to make the test pass. Regenerate
only when the arithmetic is changed deliberately (a new default, a different update formula),
and then say in the commit which cases changed and why.

The cases are `CASES` of the test module (written once, there). Run from the repository root:

    python tests/data/make_behaviour_identity.py [--overwrite]

Existing data are kept unless `--overwrite` is given.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # run as a script: import the test module as `tests.…`

import jax  # noqa: E402

import clebsch_jax  # noqa: E402
from tests.test_behaviour_identity import CASES, JSON_PATH, NPZ_PATH, record  # noqa: E402


def _commit() -> str:
    """The commit the data are produced at (with "+changes" if the work tree differs from it)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "clebsch_jax"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--overwrite", action="store_true", help="replace existing data")
    args = parser.parse_args(argv)
    if (NPZ_PATH.exists() or JSON_PATH.exists()) and not args.overwrite:
        print(
            f"{NPZ_PATH.name} / {JSON_PATH.name} exist; pass --overwrite to replace them "
            "(read this script's docstring first).",
            file=sys.stderr,
        )
        return 1
    arrays, facts = {}, {}
    for case in CASES:
        case_arrays, case_facts = record(case.run())
        arrays.update({f"{case.name}/{key}": value for key, value in case_arrays.items()})
        facts[case.name] = case_facts
        print(f"{case.name}: {len(case_arrays)} arrays, {case_facts.get('form')} march, {case_facts.get('method')!r}")
    meta = {
        "commit": _commit(),
        "clebsch_jax": clebsch_jax.__version__,
        "jax": jax.__version__,
        "numpy": np.__version__,
        "platform": jax.default_backend(),
    }
    NPZ_PATH.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(NPZ_PATH, **arrays)
    JSON_PATH.write_text(json.dumps({"produced_with": meta, "cases": facts}, indent=1, sort_keys=True) + "\n")
    print(f"wrote {len(arrays)} arrays of {len(facts)} cases ({meta['commit']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
