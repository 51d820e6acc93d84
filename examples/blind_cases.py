#!/usr/bin/env python3
"""Blind cases: data armid did not make, scored against the raw validation torque.

    python examples/blind_cases.py OUT_DIR [--seeds 0 1 2] [--set default|clean|effects|quick|clean20|effects5]
        [--no-diagnose] [--only NAME ...] [--timeout S] [--ptp]

For each seed and each case of the set, ``tests/blindgen.py`` (no armid code) makes a random
arm (generator seed 1000 * seed + the case's index or spec seed) and its recordings in
``OUT_DIR/<case>-s<generator seed>/``; then the plain pipeline
(``../shared/tools/baseline.py --predictions``), ``armid identify --validate --predictions``
(the declared model: the error before diagnosis) and ``armid diagnose --predictions`` (after)
run on it. Every error is computed here, from the predictions files, against the RAW
validation torque (or current times torque constant) at the validation file's own stamps,
beside the noise floor (the noise-free recorded torque against the noisy one). Prints a
markdown table and writes ``OUT_DIR/results.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from blindgen import blind_specs, make_case, relative_error  # noqa: E402

BASELINE = ROOT.parent / "shared" / "tools" / "baseline.py"

# Each case: a name and make_case options. Rates, torque/current, velocity and jitter rotate
# so every effect meets a different sensor; the clean cases span the four rates.
CLEAN = [
    ("clean-100-i-noqd", dict(rate_hz=100, currents=True, velocity=False, noise="medium")),
    ("clean-200-tau-jit", dict(rate_hz=200, currents=False, velocity=True, jitter=0.1, noise="low")),
    ("clean-500-tau-noqd", dict(rate_hz=500, currents=False, velocity=False, noise="medium")),
    ("clean-1k-i-jit", dict(rate_hz=1000, currents=True, velocity=True, jitter=0.1, noise="high")),
]
_SENSORS = [
    dict(rate_hz=500, currents=True, velocity=True),
    dict(rate_hz=100, currents=False, velocity=True),
    dict(rate_hz=1000, currents=False, velocity=False, jitter=0.1),
    dict(rate_hz=200, currents=True, velocity=False),
]
_EFFECTS = ["viscous_friction", "coulomb_friction", "smooth_coulomb", "stribeck_friction", "torque_offset", "rotor_inertia",
            "torque_gain", "time_delay", "cogging", "spring", "gravity_tilt", "load_coulomb", "friction_all"]
EFFECT_CASES = [(e, dict(effect=e, effect_size=0.15, noise="medium", **_SENSORS[k % len(_SENSORS)])) for k, e in enumerate(_EFFECTS)]

def _spec_name(o: dict) -> str:
    sig = "i" if o["currents"] else "tau"
    return f"{o.get('effect') or 'clean'}-{o['rate_hz']:g}-{sig}{'' if o['velocity'] else '-noqd'}{'-jit' if o['jitter'] else ''}-{o['noise']}"


SETS = {
    "default": CLEAN + EFFECT_CASES,
    "clean": CLEAN,
    "effects": EFFECT_CASES,
    "quick": [(n, dict(o, duration_s=20.0, valid_duration_s=10.0)) for n, o in (CLEAN[0], CLEAN[3], EFFECT_CASES[1], EFFECT_CASES[4])],
    # issue 16's sweeps: 20 clean cases across rates and noise levels; each effect on 5 seeds from barely visible to large
    "clean20": [(_spec_name(o), o) for o in blind_specs("clean", 20)],
    "effects5": [(_spec_name(o), o) for o in blind_specs("effects", 5)],
}


def armid_command() -> list[str]:
    """The installed ``armid`` entry point, else the module through this interpreter."""
    exe = shutil.which("armid")
    return [exe] if exe else [sys.executable, "-m", "armid.cli"]


def run(cmd: list[str], log: Path, timeout: float) -> tuple[bool, float]:
    """Run one command, its output to ``log``; (succeeded, seconds)."""
    start = time.monotonic()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        log.write_text(" ".join(map(str, cmd)) + "\n\n" + proc.stdout + proc.stderr)
        ok = proc.returncode == 0
    except subprocess.TimeoutExpired:
        log.write_text(" ".join(map(str, cmd)) + f"\n\ntimed out after {timeout} s\n")
        ok = False
    return ok, time.monotonic() - start


def score(case, predictions: Path, ok: bool) -> dict:
    if not ok or not predictions.exists():
        return {"error": None, "covered": None}
    err, covered = relative_error(case.valid_csv, predictions)
    return {"error": err, "covered": covered}


def one_case(name: str, options: dict, seed: int, out: Path, diagnose: bool, timeout: float, ptp: bool = False) -> dict:
    folder = out / f"{name}-s{seed}"
    case = make_case(seed, folder, **options, ptp=ptp)
    if ptp:  # hold out the point-to-point run instead of the Fourier one
        case.valid_csv, case.valid_clean_csv, case.noise_floor = case.ptp_csv, case.ptp_clean_csv, case.ptp_noise_floor
    files = [str(p) for p in case.ident_csvs]
    res = {"case": name, "seed": seed, "dir": str(folder), "n_joints": case.n_joints, "convention": case.convention,
           "rate_hz": case.rate_hz, "signal": "i" if case.currents else "tau", "velocity": case.velocity, "jitter": case.jitter,
           "noise": case.noise, "effect": case.effect, "expected": case.expected, "joint": case.effect_joint,
           "size": case.effect_size, "realized": case.effect_realized, "distinct": case.effect_distinct,
           "noise_floor": case.noise_floor}
    ok, res["baseline_s"] = run([sys.executable, str(BASELINE), *files, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                                 "--predictions", str(folder / "baseline_pred.csv")], folder / "baseline.log", timeout)
    res["baseline"] = score(case, folder / "baseline_pred.csv", ok)
    armid = armid_command()
    ok, res["identify_s"] = run([*armid, "identify", *files, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                                 "--predictions", str(folder / "identify_pred.csv"), "--json", str(folder / "identify.json")],
                                folder / "identify.log", timeout)
    res["identify"] = score(case, folder / "identify_pred.csv", ok)
    if diagnose:
        ok, res["diagnose_s"] = run([*armid, "diagnose", *files, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                                     "--predictions", str(folder / "diagnose_pred.csv"), "--json", str(folder / "diagnose.json")],
                                    folder / "diagnose.log", timeout)
        res["diagnose"] = score(case, folder / "diagnose_pred.csv", ok)
        found = []
        if ok and (folder / "diagnose.json").exists():
            doc = json.loads((folder / "diagnose.json").read_text())
            found = [{"effect": f.get("effect"), "joint": f.get("joint")} for f in doc.get("found", [])]
        res["found"] = found if ok else None
        res["named"] = named(res)
    return res


def named(res: dict) -> str:
    """'yes' when the diagnosis reports the true effect on its joint (or arm-wide), 'clean' when it reports nothing on clean data."""
    found = res.get("found")
    if found is None:
        return "failed"
    if res["effect"] is None:
        return "clean" if not found else "false"
    hits = [f for f in found if f["effect"] == res["expected"] and (res["joint"] is None or f["joint"] in (res["joint"], None))]
    if hits:
        return "yes" + ("" if len(found) == len(hits) else " +extra")
    return "no"


def pct(x) -> str:
    return "—" if x is None else f"{100 * x:.2f}"


def table(results: list[dict], diagnose: bool) -> str:
    head = ["case", "seed", "arm", "rate", "sig", "qd", "jit", "noise", "effect (joint, size, distinct)", "floor %", "baseline %", "identify %", "cover"]
    if diagnose:
        head += ["diagnose %", "found", "named"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        eff = "—" if r["effect"] is None else f"{r['effect']} ({r['joint'] or 'all'}, {r['size']:.2f}, {r['distinct']:.2f})"
        cover = r["identify"]["covered"]
        row = [r["case"], str(r["seed"]), f"{r['n_joints']}{r['convention']}", f"{r['rate_hz']:g}", r["signal"], "y" if r["velocity"] else "n",
               f"{r['jitter']:.2f}", r["noise"], eff, pct(r["noise_floor"]), pct(r["baseline"]["error"]), pct(r["identify"]["error"]),
               "—" if cover is None else f"{cover:.3f}"]
        if diagnose:
            found = r.get("found")
            row += [pct(r["diagnose"]["error"]), "failed" if found is None else (", ".join(f"{f['effect']}@{f['joint'] or 'all'}" for f in found) or "nothing"),
                    r["named"]]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--set", choices=sorted(SETS), default="default")
    ap.add_argument("--only", nargs="+", help="case names to keep (prefix match)")
    ap.add_argument("--no-diagnose", action="store_true", help="skip armid diagnose")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per command")
    ap.add_argument("--ptp", action="store_true", help="validate on a point-to-point run (quintic moves, dwells)")
    args = ap.parse_args()
    cases = [c for c in SETS[args.set] if not args.only or any(c[0].startswith(o) for o in args.only)]
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for seed in args.seeds:
        for name, options in cases:
            options = dict(options)
            k = [c[0] for c in SETS[args.set]].index(name)
            case_seed = 1000 * seed + options.pop("seed", k)  # a new arm per case
            res = one_case(name, options, case_seed, args.out, not args.no_diagnose, args.timeout, args.ptp)
            results.append(res)
            print(f"{name} s{case_seed}: floor {pct(res['noise_floor'])} %, baseline {pct(res['baseline']['error'])} %, "
                  f"identify {pct(res['identify']['error'])} %" + ("" if args.no_diagnose else f", diagnose {pct(res['diagnose']['error'])} % ({res['named']})"),
                  flush=True)
            (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print()
    print(table(results, not args.no_diagnose))


if __name__ == "__main__":
    main()
