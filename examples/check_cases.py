#!/usr/bin/env python3
"""``armid check`` on an undeclared tool: each arm identified without it, then checked on runs
with a tool of 0, 0.5, 1, 2 and 5 kg on its last link (``tests/checkgen.py``, no armid code).

    python examples/check_cases.py OUT_DIR [--seeds 0 1 ...] [--families dh6 mdh6]

For each case it prints whether check says the model holds, the load it names (mass and centre
of mass against the truth), the other changes it names, and the error before and after; then a
summary: tools found within 10 % of their mass and 2 cm of their centre, and tool-free runs
that hold with nothing found. Writes ``OUT_DIR/results.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from checkgen import FAMILIES, make_check_case  # noqa: E402


def run_case(seed: int, family: str, out: Path) -> list[dict]:
    case = make_check_case(seed, family, out / f"{family}_s{seed}")
    model = case.folder / "model.json"
    subprocess.run(["armid", "identify", str(case.ident), "--robot", str(case.robot), "--json", str(model)], check=True,
                   capture_output=True, text=True)
    rows = []
    for mass, path in case.checks.items():
        doc_path = case.folder / f"check_{mass:g}.json"
        subprocess.run(["armid", "check", str(path), "--robot", str(case.robot), "--model", str(model), "--json", str(doc_path)],
                       check=True, capture_output=True, text=True)
        doc = json.loads(doc_path.read_text())
        load = next((f for f in doc["found"] if f["effect"] == "payload"), None)
        row = {"family": family, "seed": seed, "mass": mass, "holds": doc["holds"], "before": doc["before"]["relative_error"],
               "after": doc["after"]["relative_error"], "floor": doc["noise_floor"]["relative_error"],
               "others": [f"{f['effect']}@{f['joint']}" for f in doc["found"] if f["effect"] != "payload"],
               "found_mass": None if load is None else load["parameters"]["m"],
               "mass_std": None if load is None else load["std"]["m"], "com_error_m": None}
        if load is not None and load["parameters"].get("cx") is not None:
            c = [load["parameters"][k] for k in ("cx", "cy", "cz")]
            row["com_error_m"] = float(sum((a - b) ** 2 for a, b in zip(c, case.offset_m)) ** 0.5)
        rows.append(row)
        print(f"{family} s{seed} tool {mass:g} kg: holds {row['holds']}, error {100 * row['before']:.2f} % -> {100 * row['after']:.2f} % "
              f"(floor {100 * (row['floor'] or 0):.2f} %), load {row['found_mass']} kg, centre off by {row['com_error_m']} m, "
              f"other changes {row['others']}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(FAMILIES))
    args = ap.parse_args()
    rows = [r for fam in args.families for s in args.seeds for r in run_case(s, fam, args.out)]
    tools = [r for r in rows if r["mass"] > 0]
    right = [r for r in tools if r["found_mass"] is not None and abs(r["found_mass"] - r["mass"]) <= 0.1 * r["mass"]
             and r["com_error_m"] is not None and r["com_error_m"] <= 0.02]
    clean = [r for r in rows if r["mass"] == 0]
    quiet = [r for r in clean if r["holds"] and r["found_mass"] is None and not r["others"]]
    print(f"tools found within 10 % and 2 cm: {len(right)} of {len(tools)}; tool-free runs that hold with nothing found: "
          f"{len(quiet)} of {len(clean)}; tool runs with another change named beside the load: {sum(bool(r['others']) for r in tools)}")
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
