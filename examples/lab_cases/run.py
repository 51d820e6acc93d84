#!/usr/bin/env python3
"""Run the plain pipeline, armid identify and armid diagnose on lab cases and score them here,
from the predictions files, against the raw validation torque at its own stamps.

    python examples/lab_cases/run.py OUT_DIR [--cases c1 c2 ...] [--skip-run]

c1..c8 carry effects the robot file does not declare; d1..d8 are the same cases with only the
declared ones (the default runs c1..c8).

Makes the cases of CASES with gen.py (seeds fixed) in OUT_DIR/cN/ unless they exist, runs the
three pipelines in each and prints a markdown table (results.json per case)."""
import argparse
import json
import pathlib
import subprocess
import sys
import time

import numpy as np
import yaml

BIN = pathlib.Path(sys.executable).parent
HERE = pathlib.Path(__file__).resolve().parent
BASELINE = HERE.parents[2] / "shared" / "tools" / "baseline.py"
CASES = {
    "c1": "--arm ur5 --sensor torque --qd yes --valid fourier --nident 1 --seed 11",
    "c2": "--arm ur5 --sensor current --qd no --valid ptp --nident 2 --seed 12",
    "c3": "--arm kuka --sensor torque --qd no --valid ptp --nident 1 --seed 13",
    "c4": "--arm kuka --sensor current --qd yes --valid fourier --nident 2 --seed 14",
    "c5": "--arm ur5 --sensor torque --qd no --valid ptp --nident 2 --seed 15",
    "c6": "--arm kuka --sensor current --qd no --valid fourier --nident 1 --seed 16",
    "c7": "--arm ur5 --sensor current --qd yes --valid fourier --nident 1 --seed 17",
    "c8": "--arm kuka --sensor torque --qd yes --valid ptp --nident 2 --seed 18",
}
# the same arms, sensors and draws with only the declared effects: held-out error vs the floor
CASES.update({f"d{k[1:]}": f"{v} --effects declared" for k, v in list(CASES.items())})


def load(path):
    a = np.genfromtxt(path, delimiter=",", names=True)
    return a


def raw_tau(a, n, kt):
    if "tau1" in a.dtype.names:
        return np.column_stack([a[f"tau{j + 1}"] for j in range(n)])
    return np.column_stack([a[f"i{j + 1}"] for j in range(n)]) * kt


def score(pred_path, t_v, tau_v, n):
    if not pred_path.exists():
        return dict(error=None, coverage=0.0, note="no predictions file")
    p = load(pred_path)
    names = p.dtype.names
    cols = [f"tau_hat{j + 1}" for j in range(n)]
    miss = [c for c in cols if c not in names]
    if miss or "t" not in names:
        return dict(error=None, coverage=0.0, note=f"columns {names}")
    tp = np.atleast_1d(p["t"])
    th = np.column_stack([np.atleast_1d(p[c]) for c in cols])
    idx = np.clip(np.searchsorted(t_v, tp), 1, len(t_v) - 1)
    left = np.where(np.abs(t_v[idx - 1] - tp) <= np.abs(t_v[idx] - tp), idx - 1, idx)
    dt = np.abs(t_v[left] - tp)
    ok = (dt < 2e-6) & np.isfinite(th).all(axis=1)
    m = left[ok]
    err = np.linalg.norm(tau_v[m] - th[ok]) / np.linalg.norm(tau_v[m])
    per = (np.linalg.norm(tau_v[m] - th[ok], axis=0) / np.linalg.norm(tau_v[m], axis=0)).tolist()
    return dict(error=float(err), coverage=len(np.unique(m)) / len(t_v), rows=len(tp),
                unmatched=int((~ok).sum()), dup=int(len(m) - len(np.unique(m))), per_joint=per)


def run_case(case, skip):
    rob = yaml.safe_load((case / "robot.yaml").read_text())
    n = len(rob["joints"])
    kt = np.array([float(j.get("torque_constant", 1.0)) for j in rob["joints"]])
    ident = sorted(str(p.name) for p in case.glob("ident?.csv"))
    cmds = {
        "baseline": [sys.executable, str(BASELINE), *ident, "--robot", "robot.yaml",
                     "--validate", "valid.csv", "--predictions", "base_pred.csv"],
        "identify": [str(BIN / "armid"), "identify", *ident, "--robot", "robot.yaml", "--validate", "valid.csv",
                     "--predictions", "id_pred.csv", "--json", "id.json"],
        "diagnose": [str(BIN / "armid"), "diagnose", *ident, "--robot", "robot.yaml", "--validate", "valid.csv",
                     "--predictions", "dg_pred.csv", "--json", "dg.json"],
    }
    res = json.loads((case / "results.json").read_text()) if skip and (case / "results.json").exists() else {}
    if not skip:
        for k, c in cmds.items():
            t0 = time.time()
            try:
                r = subprocess.run(c, cwd=case, capture_output=True, text=True, timeout=1200)
                rc, so, se = r.returncode, r.stdout, r.stderr
            except subprocess.TimeoutExpired as e:
                rc, so, se = "timeout", str(e.stdout), str(e.stderr)
            (case / f"{k}.out").write_text(so)
            (case / f"{k}.err").write_text(se)
            res[k] = dict(cmd=f"cd {case} && {' '.join(c)}", rc=rc, seconds=round(time.time() - t0, 1),
                          traceback="Traceback" in se)
            print(k, rc, res[k]["seconds"], "s", flush=True)
    v = load(case / "valid.csv")
    vc = load(case / "valid_clean.csv")
    t_v = v["t"]
    tau_v = raw_tau(v, n, kt)
    tau_c = raw_tau(vc, n, kt)
    res["floor"] = float(np.linalg.norm(tau_c - tau_v) / np.linalg.norm(tau_v))
    for k, f in (("baseline", "base_pred.csv"), ("identify", "id_pred.csv"), ("diagnose", "dg_pred.csv")):
        res.setdefault(k, {}).update(score(case / f, t_v, tau_v, n))
    # what the tools themselves report
    try:
        res["identify"]["reported"] = json.loads((case / "id.json").read_text())["validation"]["relative_error"]
    except Exception as e:
        res["identify"]["reported"] = repr(e)
    try:
        dg = json.loads((case / "dg.json").read_text())
        res["diagnose"]["reported_before"] = dg["before"]["relative_error"]
        res["diagnose"]["reported_after"] = dg["after"]["relative_error"]
        res["diagnose"]["found"] = [(f.get("effect"), f.get("joint"), f.get("explained")) for f in dg["found"]]
    except Exception as e:
        res["diagnose"]["found"] = repr(e)
    (case / "results.json").write_text(json.dumps(res, indent=1))
    return res


def table(out, names):
    print("| case | arm | sensor | rate | qd given | ident runs | validation | noise floor | baseline | identify | diagnose | "
          "coverage b/i/d | diagnose findings (effect@joint) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        c = out / name
        t, r = json.loads((c / "truth.json").read_text()), json.loads((c / "results.json").read_text())
        a = t["args"]

        def pct(k, r=r):
            return f"{100 * r[k]['error']:.2f} %" if r[k].get("error") is not None else "n/a"
        found = r["diagnose"]["found"]
        fs = ", ".join(f"{e}@{j}" for e, j, _ in found) if isinstance(found, list) else found
        print(f"| {name} | {a['arm']} | {a['sensor']} | {int(t['rate'])} Hz | {a['qd']} | {a['nident']} | {a['valid']} | "
              f"{100 * r['floor']:.2f} % | {pct('baseline')} | {pct('identify')} | {pct('diagnose')} | "
              f"{r['baseline']['coverage']:.3f}/{r['identify']['coverage']:.3f}/{r['diagnose']['coverage']:.3f} | {fs} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out")
    ap.add_argument("--cases", nargs="*", default=[c for c in CASES if c.startswith("c")])
    ap.add_argument("--skip-run", action="store_true", help="only score and print what is there")
    args = ap.parse_args()
    out = pathlib.Path(args.out).resolve()
    for name in args.cases:
        case = out / name
        if not (case / "truth.json").exists():
            subprocess.run([sys.executable, str(HERE / "gen.py"), *CASES[name].split(), "--out", str(case)], check=True)
        run_case(case, args.skip_run)
    table(out, args.cases)


if __name__ == "__main__":
    main()
