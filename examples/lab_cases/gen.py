#!/usr/bin/env python3
"""Independent 'real arm' log generator (Pinocchio), written from a brief by a helper session
that did not read armid or tests/blindgen.py (no shared code): URDF arms (UR5, KUKA LWR4+)
with perturbed inertials, friction on every joint (Coulomb, viscous, offset, load-dependent
Coulomb), rotor inertia, Stribeck on two joints, 1 kHz torque sensors or 100 Hz quantised
currents with a few % torque-constant error, encoders, jittery stamps; the robot file declares
Coulomb, viscous and offset only.

python gen.py --arm ur5|kuka --sensor torque|current --qd yes|no --valid fourier|ptp
              --nident 1|2 --seed N [--effects all|declared] --out DIR
--tool-kg M fixes an undeclared tool of M kg (a 6 cm cube, its centre drawn within 10 cm of the
last joint's frame, from a stream of its own: the other draws stay the same) to the last link
for the valid run only, as a lab that mounts a tool after identifying (``armid check``).
--effects declared keeps only what the robot file declares (no load-dependent Coulomb, rotor
inertia, Stribeck or torque-constant error; the same random draws otherwise): the clean case,
where the held-out error can reach the noise floor.
Writes in DIR: robot.yaml (+ URDF copy, nominal values), identN.csv / identN_clean.csv,
valid.csv / valid_clean.csv, truth.json.
"""
import argparse
import json
import pathlib
import shutil

import numpy as np
import pinocchio as pin
import yaml

ROBOTS = pathlib.Path(__file__).resolve().parents[2] / "config" / "robots"
ARMS = {
    "ur5": dict(urdf="ur5.urdf",
                joints=["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                        "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"],
                kt=[13.3, 13.3, 9.3, 4.2, 4.2, 4.2],
                lim=[2.8] * 6,             # used position range (the URDF allows +-2 pi)
                center=[0.0, -1.57, 1.2, -1.57, 0.0, 0.0]),
    "kuka": dict(urdf="kuka_lwr4.urdf",
                 joints=[f"lwr_{i}_joint" for i in range(7)],
                 kt=[9.0, 9.0, 6.0, 6.0, 3.0, 1.2, 0.8],
                 lim=None, center=[0.0] * 7),
}
TANH_V = 0.02


def load_model(arm):
    spec = ARMS[arm]
    model = pin.buildModelFromUrdf(str(ROBOTS / spec["urdf"]))
    lock = [model.getJointId(n) for n in model.names[1:] if n not in spec["joints"]]
    if lock:
        model = pin.buildReducedModel(model, lock, pin.neutral(model))
    assert list(model.names[1:]) == spec["joints"], model.names
    return model


def rand_rot(rng, max_deg):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return pin.exp3(axis * np.deg2rad(rng.uniform(0, max_deg)))


def perturb(model, rng):
    """TRUE arm: mass, com and rotational inertia (about com) changed by 10-30 %."""
    true = model.copy()
    log = []
    for i in range(1, model.njoints):
        inertia = model.inertias[i]

        def sgn():
            return rng.choice([-1.0, 1.0])
        m = inertia.mass * (1 + sgn() * rng.uniform(0.1, 0.3))
        c = inertia.lever.copy()
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        c = c + d * max(rng.uniform(0.1, 0.3) * np.linalg.norm(c), rng.uniform(0.005, 0.02))
        Ic = inertia.inertia.copy()
        w, V = np.linalg.eigh(Ic)
        for _ in range(1000):
            w2 = w * (1 + np.array([sgn() for _ in range(3)]) * rng.uniform(0.1, 0.3, 3))
            s = np.sort(w2)
            if s[0] + s[1] >= 1.02 * s[2] and s.min() > 0:
                break
        else:  # fall back: uniform scaling keeps the triangle inequality
            w2 = w * (1 + sgn() * rng.uniform(0.1, 0.3))
        R = rand_rot(rng, 10.0)
        Ic2 = R @ V @ np.diag(w2) @ V.T @ R.T
        Ic2 = 0.5 * (Ic2 + Ic2.T)
        true.inertias[i] = pin.Inertia(m, c, Ic2)
        log.append(dict(joint=model.names[i], mass=[inertia.mass, m], com=[inertia.lever.tolist(), c.tolist()],
                        Ic_nominal=Ic.tolist(), Ic_true=Ic2.tolist()))
    return true, log


# ---------------------------------------------------------------- trajectories
def fourier(rng, n, f0, dur, center, amp, vmax, amax, H=5):
    w = 2 * np.pi * f0
    k = np.arange(1, H + 1)
    a = rng.normal(size=(n, H)) / k
    b = rng.normal(size=(n, H)) / k
    a[:, 0] -= a.sum(axis=1)                     # qd(0) = sum a_k = 0
    b[:, 0] -= (b * k).sum(axis=1)               # qdd(0) = w sum k b_k = 0

    def ev(t, a=a, b=b):
        t = np.asarray(t)[:, None, None]
        wk = w * k[None, None, :]
        s, c = np.sin(wk * t), np.cos(wk * t)
        q = (a / wk * s - b / wk * c).sum(-1)
        qd = (a * c + b * s).sum(-1)
        qdd = (-a * wk * s + b * wk * c).sum(-1)
        return q, qd, qdd

    tt = np.linspace(0, 1 / f0, 4000)
    q, qd, qdd = ev(tt)
    q0 = q.mean(axis=0)
    dev = np.abs(q - q0).max(axis=0)
    scale = np.minimum.reduce([amp / dev, vmax / np.abs(qd).max(axis=0), amax / np.abs(qdd).max(axis=0)])
    a, b = a * scale[:, None], b * scale[:, None]
    off = center - q0 * scale

    def traj(t):
        q, qd, qdd = ev(t, a, b)
        return q + off, qd, qdd
    return traj


def ptp(rng, n, dur, center, amp, vmax, amax):
    pts, segs, t = [center + rng.uniform(-amp, amp)], [], 0.0
    while t < dur:
        dwell = rng.uniform(0.5, 2.0)
        segs.append((t, dwell, pts[-1], pts[-1]))
        t += dwell
        nxt = center + rng.uniform(-amp, amp)
        dq = np.abs(nxt - pts[-1])
        T = max(1.0, (15 / 8 * dq / vmax).max(), np.sqrt(5.78 * dq / amax).max())
        segs.append((t, T, pts[-1], nxt))
        t += T
        pts.append(nxt)

    starts = np.array([s[0] for s in segs])

    def traj(tv):
        tv = np.asarray(tv)
        q = np.empty((len(tv), n))
        qd = np.zeros_like(q)
        qdd = np.zeros_like(q)
        idx = np.clip(np.searchsorted(starts, tv, side="right") - 1, 0, len(segs) - 1)
        for j, (t0, T, p0, p1) in enumerate(segs):
            m = idx == j
            if not m.any():
                continue
            s = np.clip((tv[m] - t0) / T, 0, 1)[:, None]
            d = (p1 - p0)[None, :]
            q[m] = p0 + d * (10 * s**3 - 15 * s**4 + 6 * s**5)
            qd[m] = d * (30 * s**2 - 60 * s**3 + 30 * s**4) / T
            qdd[m] = d * (60 * s - 180 * s**2 + 120 * s**3) / T**2
        return q, qd, qdd
    return traj


# ---------------------------------------------------------------- torque
def torques(true, fr, q, qd, qdd):
    data = true.createData()
    rig = np.array([pin.rnea(true, data, q[k], qd[k], qdd[k]).copy() for k in range(len(q))])
    sg = np.tanh(qd / TANH_V)
    tau = (rig + fr["fc"] * sg + fr["fv"] * qd + fr["off"] + fr["fl"] * np.abs(rig) * sg
           + fr["Ia"] * qdd + fr["fs"] * np.exp(-(qd / fr["vs"]) ** 2) * sg)
    return tau, rig


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--arm", required=True, choices=ARMS)
    ap.add_argument("--sensor", required=True, choices=["torque", "current"])
    ap.add_argument("--qd", required=True, choices=["yes", "no"])
    ap.add_argument("--valid", required=True, choices=["fourier", "ptp"])
    ap.add_argument("--nident", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effects", choices=["all", "declared"], default="all")
    ap.add_argument("--tool-kg", type=float, default=0.0)
    ap.add_argument("--out", required=True)
    A = ap.parse_args()
    rng = np.random.default_rng(A.seed)
    out = pathlib.Path(A.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = ARMS[A.arm]
    nom = load_model(A.arm)
    n = nom.nv
    true, inert_log = perturb(nom, rng)

    lo, hi = nom.lowerPositionLimit.copy(), nom.upperPositionLimit.copy()
    if spec["lim"] is not None:
        lo, hi = np.maximum(lo, -np.array(spec["lim"])), np.minimum(hi, spec["lim"])
    center = np.clip(np.array(spec["center"]) + rng.uniform(-0.3, 0.3, n), lo + 1.0, hi - 1.0)
    amp = np.minimum(np.minimum(center - lo, hi - center) * 0.9, 1.4)
    vmax = 0.6 * nom.velocityLimit
    amax = np.full(n, 5.0)
    effort = nom.effortLimit.copy()
    big = effort >= 100

    # friction and drive effects, per joint
    fr = dict(fc=rng.uniform(0.01, 0.04, n) * effort,
              fv=rng.uniform(0.01, 0.04, n) * effort,
              off=rng.uniform(-0.01, 0.01, n) * effort,
              fl=rng.uniform(0.02, 0.1, n),
              Ia=np.where(big, rng.uniform(0.05, 1.0, n), rng.uniform(0.005, 0.05, n)),
              fs=np.zeros(n), vs=np.full(n, 0.05))
    strib = rng.choice(n, size=2, replace=False)
    fr["fs"][strib] = rng.uniform(0.3, 0.8, 2) * fr["fc"][strib]
    fr["vs"][strib] = rng.uniform(0.02, 0.1, 2)

    rate = 1000.0 if A.sensor == "torque" else 100.0
    kt_true = np.array(spec["kt"]) * rng.uniform(0.97, 1.03, n)
    kt_file = kt_true.copy()
    wrong = rng.choice(n, size=rng.integers(1, 3), replace=False)
    kt_file[wrong] *= 1 + rng.choice([-1, 1], len(wrong)) * rng.uniform(0.03, 0.06, len(wrong))
    if A.effects == "declared":
        kt_true = np.round(kt_true, 3)
        kt_file, wrong, strib = kt_true.copy(), np.array([], dtype=int), strib[:0]
        for k in ("fl", "Ia", "fs"):
            fr[k][:] = 0.0
    kt_file = np.round(kt_file, 3)
    jitter = rng.uniform(0.05, 0.10)
    enc = 2 * np.pi / 2**17
    v_std = rng.uniform(2e-3, 1e-2)
    i_q = rng.choice([1e-3, 2e-3, 5e-3, 1e-2])
    noise_rel = rng.uniform(0.01, 0.02)

    true_valid, tool = true, None
    if A.tool_kg > 0:
        r_tool = np.random.default_rng([A.seed, 7])
        com = r_tool.uniform(-0.05, 0.05, 3) + np.array([0.0, 0.0, 0.05])
        true_valid = true.copy()
        true_valid.inertias[n] = true.inertias[n] + pin.Inertia(A.tool_kg, com, np.eye(3) * A.tool_kg * 0.06**2 / 6)
        tool = dict(mass_kg=A.tool_kg, com_m=com.tolist(), frame="the last joint's (the URDF child link's) frame")

    runs = []
    f_used = []
    for r in range(A.nident):
        f0 = rng.uniform(0.05, 0.2)
        f_used.append(f0)
        dur = min(60.0, max(30.0, np.ceil(30 * f0) / f0))
        runs.append((f"ident{r + 1}", dur, fourier(rng, n, f0, dur, center, amp, vmax, amax)))
    if A.valid == "fourier":
        while True:
            f0 = rng.uniform(0.05, 0.2)
            if min(abs(f0 - f) for f in f_used) > 0.02:
                break
        dur = min(60.0, max(30.0, np.ceil(30 * f0) / f0))
        runs.append(("valid", dur, fourier(rng, n, f0, dur, center, amp, vmax, amax)))
        vinfo = dict(kind="fourier", f0=f0, dur=dur)
    else:
        dur = rng.uniform(30, 45)
        runs.append(("valid", dur, ptp(rng, n, dur, center, amp * 0.9, vmax, amax)))
        vinfo = dict(kind="ptp", dur=dur)

    stats = {}
    for name, dur, traj in runs:
        N = int(dur * rate)
        t = np.arange(N) / rate + np.clip(rng.normal(0, jitter / rate, N), -0.45 / rate, 0.45 / rate)
        t[0] = 0.0
        q, qd, qdd = traj(t)
        assert (q >= lo - 1e-9).all() and (q <= hi + 1e-9).all(), name
        tau, rig = torques(true_valid if name == "valid" else true, fr, q, qd, qdd)
        rms = np.sqrt((tau**2).mean(axis=0))
        qm = np.round(q / enc) * enc
        qdm = qd + rng.normal(0, v_std, qd.shape)
        cols_c = [t, q] + ([qd] if A.qd == "yes" else [])
        cols_n = [t, qm] + ([qdm] if A.qd == "yes" else [])
        hdr = ["t"] + [f"q{j + 1}" for j in range(n)] + ([f"qd{j + 1}" for j in range(n)] if A.qd == "yes" else [])
        if A.sensor == "torque":
            tau_n = tau + rng.normal(0, 1, tau.shape) * noise_rel * rms
            cols_c.append(tau)
            cols_n.append(tau_n)
            hdr += [f"tau{j + 1}" for j in range(n)]
        else:
            cur = tau / kt_true
            cur_n = np.round((cur + rng.normal(0, 1, cur.shape) * noise_rel * rms / kt_true) / i_q) * i_q
            cols_c.append(cur)
            cols_n.append(cur_n)
            hdr += [f"i{j + 1}" for j in range(n)]
        for suffix, cols in (("_clean", cols_c), ("", cols_n)):
            arr = np.column_stack(cols)
            np.savetxt(out / f"{name}{suffix}.csv", arr, delimiter=",", header=",".join(hdr),
                       comments="", fmt=["%.7f"] + ["%.10g"] * (arr.shape[1] - 1))
        stats[name] = dict(samples=N, dur=dur, tau_rms=rms.tolist(), tau_max=np.abs(tau).max(axis=0).tolist(),
                           rigid_rms=np.sqrt((rig**2).mean(axis=0)).tolist(),
                           qd_max=np.abs(qd).max(axis=0).tolist(),
                           over_effort=bool((np.abs(tau) > effort).any()))

    shutil.copy(ROBOTS / spec["urdf"], out / spec["urdf"])
    joints = [{"name": nm} for nm in spec["joints"]]
    if A.sensor == "current":
        for j, d in enumerate(joints):
            d["torque_constant"] = float(kt_file[j])
    doc = dict(name=f"{A.arm}_lab", gravity=[0.0, 0.0, -9.81], urdf=spec["urdf"], joints=joints,
               effects=[{"effect": e, "joint": None} for e in ("viscous_friction", "coulomb_friction", "torque_offset")])
    (out / "robot.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    truth = dict(args=vars(A), rate=rate, jitter_rel=jitter, encoder_counts=2**17,
                 velocity_noise_std=v_std if A.qd == "yes" else None,
                 current_quantum=i_q if A.sensor == "current" else None, noise_rel_rms=noise_rel,
                 kt_true=kt_true.tolist(), kt_file=kt_file.tolist() if A.sensor == "current" else None,
                 kt_wrong_joints=(wrong + 1).tolist() if A.sensor == "current" else None,
                 friction={k: v.tolist() for k, v in fr.items()}, stribeck_joints=(strib + 1).tolist(),
                 ident_f0=f_used, valid=vinfo, inertial=inert_log, runs=stats,
                 center=center.tolist(), amp=amp.tolist(), tool=tool)
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    print(json.dumps({k: truth[k] for k in ("rate", "jitter_rel", "kt_wrong_joints", "stribeck_joints",
                                            "ident_f0", "valid")}),
          {k: (round(max(v["tau_rms"]), 2), v["over_effort"]) for k, v in stats.items()})


if __name__ == "__main__":
    main()
