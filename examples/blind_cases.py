#!/usr/bin/env python3
"""Blind cases: data armid did not make, scored against the raw validation torque.

    python examples/blind_cases.py OUT_DIR [--seeds 0 1 2] [--set default|clean|effects|quick|clean20|effects5]
        [--count N] [--no-diagnose] [--only NAME ...] [--timeout S] [--ptp] [--from-json]

For each seed and each case of the set, ``tests/blindgen.py`` (no armid code) makes a random
arm (generator seed 1000 * seed + the case's index or spec seed) and its recordings in
``OUT_DIR/<case>-s<generator seed>/``; then the plain pipeline
(``../shared/tools/baseline.py --predictions``), ``armid identify --validate --predictions``
(the declared model: the error before diagnosis) and ``armid diagnose --predictions`` (after)
run on it. Every error is computed here, from the predictions files, against the RAW
validation torque (or current times torque constant) at the validation file's own stamps,
beside the noise floor (the noise-free recorded torque against the noisy one) and the oracle
(least squares on the true kinematics with the declared model, then with the true effect's
column: what is attainable). The effect column gives the joint, the size (relative to the
joint's torque RMS), the distinct fraction (what the declared model cannot absorb) and the
visibility (whole-arm effect torque / torque noise). Prints a markdown table and writes
``OUT_DIR/results.json``.
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
from blindgen import blind_specs, make_case, oracle_error, relative_error  # noqa: E402

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
# a drive gain is a torque constant's error: its case records currents whatever the rotation gives
EFFECT_CASES = [(e, {"effect": e, "effect_size": 0.15, "noise": "medium", **_SENSORS[k % len(_SENSORS)],
                     **({"currents": True} if e == "torque_gain" else {})}) for k, e in enumerate(_EFFECTS)]

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
           "size": case.effect_size, "realized": case.effect_realized, "distinct": case.effect_distinct, "visible": case.effect_visible,
           "noise_floor": case.noise_floor}
    res["oracle"] = oracle_error(case, "ptp" if ptp else "valid")  # perfect kinematics + least squares: what is attainable
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
    return "—" if x is None or x != x else f"{100 * x:.2f}"


def ratio(x, floor) -> str:
    return "—" if x is None or x != x else f"{x / floor:.2f}"


def gap_closed(r: dict) -> float | None:
    """(before - after) / (before - floor): 1 reaches the noise floor, >= 0.5 is issue 16's bar."""
    before, after = r["identify"]["error"], r.get("diagnose", {}).get("error")
    if before is None or after is None or before != before or after != after or before <= r["noise_floor"]:
        return None
    return (before - after) / (before - r["noise_floor"])


def _oracle(r: dict) -> str:
    o = r.get("oracle") or {}
    return pct(o.get("before")) + ("" if o.get("after") is None else f" -> {pct(o['after'])}")


def table(results: list[dict], diagnose: bool) -> str:
    head = ["case", "seed", "arm", "rate", "sig", "qd", "jit", "noise", "effect (joint, size, distinct, visible)", "floor %", "oracle %", "baseline %",
            "identify %", "cover", "base/floor", "id/floor"]
    if diagnose:
        head += ["diagnose %", "gap closed", "found", "named"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        distinct = "—" if r.get("distinct") is None else f"{r['distinct']:.2f}"
        visible = "—" if r.get("visible") is None else f"{r['visible']:.1f}"
        eff = "—" if r["effect"] is None else f"{r['effect']} ({r['joint'] or 'all'}, {r['size']:.2f}, {distinct}, {visible})"
        cover = r["identify"]["covered"]
        row = [r["case"], str(r["seed"]), f"{r['n_joints']}{r['convention']}", f"{r['rate_hz']:g}", r["signal"], "y" if r["velocity"] else "n",
               f"{r['jitter']:.2f}", r["noise"], eff, pct(r["noise_floor"]), _oracle(r), pct(r["baseline"]["error"]), pct(r["identify"]["error"]),
               "—" if cover is None else f"{cover:.3f}", ratio(r["baseline"]["error"], r["noise_floor"]), ratio(r["identify"]["error"], r["noise_floor"])]
        if diagnose:
            found = r.get("found")
            g = gap_closed(r)
            row += [pct(r["diagnose"]["error"]), "—" if g is None else f"{g:.2f}",
                    "failed" if found is None else (", ".join(f"{f['effect']}@{f['joint'] or 'all'}" for f in found) or "nothing"), r["named"]]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def summary(results: list[dict], diagnose: bool) -> str:
    """Issue 15/16's bars, counted: clean cases within 10 % of the floor (>= 99 % of stamps); effects named and half the gap closed."""
    out = []
    clean = [r for r in results if r["effect"] is None]
    if clean:
        def within(res: dict, floor: float) -> bool:
            return res["error"] is not None and res["error"] == res["error"] and (res["covered"] or 0) >= 0.99 and res["error"] <= 1.1 * floor

        for key in ("baseline", "identify") + (("diagnose",) if diagnose else ()):
            n_ok = sum(within(r[key], r["noise_floor"]) for r in clean)
            out.append(f"- clean cases, {key} within 1.1 x noise floor over >= 99 % of the stamps: {n_ok} of {len(clean)}")
        if diagnose:
            out.append(f"- clean cases where diagnose found nothing: {sum(r['named'] == 'clean' for r in clean)} of {len(clean)}")
    effects = [r for r in results if r["effect"] is not None]
    if effects and diagnose:
        named_ok = sum(r["named"].startswith("yes") for r in effects)
        half = sum((gap_closed(r) or 0) >= 0.5 for r in effects)
        out.append(f"- effect cases named (effect and joint): {named_ok} of {len(effects)}; half the gap to the floor closed: {half} of {len(effects)}")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--set", choices=sorted(SETS), default="default")
    ap.add_argument("--only", nargs="+", help="case names to keep (prefix match)")
    ap.add_argument("--no-diagnose", action="store_true", help="skip armid diagnose")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per command")
    ap.add_argument("--ptp", action="store_true", help="validate on a point-to-point run (quintic moves, dwells)")
    ap.add_argument("--count", type=int, help="clean20/effects5: that many clean cases / seeds per effect instead")
    ap.add_argument("--from-json", action="store_true", help="only print the table of OUT_DIR/results.json")
    args = ap.parse_args()
    if args.from_json:
        results = json.loads((args.out / "results.json").read_text())
        diagnose = all("diagnose" in r for r in results)
        print(table(results, diagnose) + "\n\n" + summary(results, diagnose))
        return
    if args.count and args.set in ("clean20", "effects5"):
        SETS[args.set] = [(_spec_name(o), o) for o in blind_specs("clean" if args.set == "clean20" else "effects", args.count)]
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
    print()
    print(summary(results, not args.no_diagnose))


if __name__ == "__main__":
    main()
