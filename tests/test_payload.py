"""On-line payload estimation: RLS on the simulated arm, live over Zenoh, and on replay."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from armid.cli import main
from armid.demo import true_parameters
from daq.excite import ExcitationSession
from daq.payload_service import EstimateStream, PayloadService, wait_for
from daq.stream import Stream, session_config
from drivers.rig import load_rig
from identify import excitation as ex
from identify.differentiation import five_point_derivative
from identify.identification import declared_effects, structural_base
from identify.payload import ArmModel, PayloadRLS, rls_update
from identify.recordings import read_mcap_arrays
from sim_bus.offline import simulate
from sim_bus.physics import Payload, simulation_config

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / "config" / "rigs" / "sim.yaml"
HELPERS = Path(__file__).resolve().parent / "helpers"
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
PAYLOAD = Payload(2.0, (0.02, -0.03, 0.08), (0.004, 0.0, 0.0, 0.004, 0.0, 0.002))  # 2 kg, 8.8 cm from the flange


def _arm_and_design(seed: int = 3) -> tuple[ArmModel, ex.Plan, object]:
    """The arm with its parameters known (the simulator's), its noise level measured on a
    payload-free run of the same motion, and a whole-arm excitation plan."""
    rig = load_rig(RIG)
    robot = rig.robot
    effects = declared_effects(robot)
    base = structural_base(robot, effects)
    names = robot.parameter_names + [label for e in effects for label in e.labels()]
    arm = ArmModel(robot, tuple(effects), base.independent, base.base_values(true_parameters(rig, names)), np.ones(6))
    d = ex.design(robot, base_frequency_hz=0.2, seed=seed, margin=0.6)
    start = np.asarray(rig.simulation["initial_position"], float)
    plan = ex.plan(d, start, ex.Limits.of(robot), periods=2)
    cfg = simulation_config(rig.simulation, 6)
    run = simulate(robot, cfg, plan.evaluate, plan.duration_s, seed=seed + 1)
    qd = five_point_derivative(run.position, 0.002)
    qdd = five_point_derivative(qd, 0.002)
    ok = np.isfinite(qdd).all(axis=1) & (run.t > plan.lead_in_s)
    res = run.torque[ok] - arm.torque(run.position[ok], qd[ok], qdd[ok])
    return dataclasses.replace(arm, joint_sigma=np.sqrt(np.mean(res**2, axis=0))), plan, cfg


def _check_tracking(times: np.ndarray, docs: list[dict], t_on: float, t_off: float) -> None:
    """Within 2 s of the attach: mass within 5 %, COM within 1 cm; within 2 s of the removal: back."""
    def at(t: float) -> dict:
        k = int(np.searchsorted(times, t))
        assert k < len(docs), f"no estimate at t = {t:.2f} s"
        return docs[k]

    for dt in (2.0, 2.5, 3.0):  # and it stays there
        d = at(t_on + dt)
        assert abs(d["mass"] - PAYLOAD.mass) <= 0.05 * PAYLOAD.mass, (dt, d["mass"])
        assert np.linalg.norm(np.array(d["com"]) - PAYLOAD.com) <= 0.01, (dt, d["com"])
    for dt in (2.0, 2.5):
        assert abs(at(t_off + dt)["mass"]) <= 0.05 * PAYLOAD.mass, (dt, at(t_off + dt)["mass"])
    assert abs(at(t_on - 0.5)["mass"]) <= 0.05 * PAYLOAD.mass  # nothing there before


def test_rls_update_equals_batch_least_squares() -> None:
    rng = np.random.default_rng(0)
    h = rng.normal(size=(40, 3, 4))
    theta_true = rng.normal(size=4)
    y = h @ theta_true + 0.01 * rng.normal(size=(40, 3))
    theta, p = np.zeros(4), np.eye(4) * 1e4  # a weak prior: R / P0 = 1e-8
    for k in range(40):
        theta, p, _, _ = rls_update(theta, p, h[k], y[k], np.full(3, 1e-4))
    batch, *_ = np.linalg.lstsq(h.reshape(-1, 4), y.reshape(-1), rcond=None)
    assert np.allclose(theta, batch, atol=1e-6)


def test_compiled_fold_equals_rls_update_step_by_step() -> None:
    from identify.payload import _fold_kernel

    rng = np.random.default_rng(1)
    n = 60
    h = rng.normal(size=(n, 6, 10))
    y = rng.normal(size=(n, 6))
    use = rng.random((n, 6)) > 0.3
    moving = rng.random(n) > 0.5
    r = rng.uniform(0.1, 1.0, 6)
    prior = np.full(10, 4.0)
    theta, p = np.zeros(10), np.diag(prior)
    for k in range(n):
        if use[k].any():
            theta, p, _, _ = rls_update(theta, p, h[k][use[k]], y[k][use[k]], r[use[k]], 0.99 if moving[k] else 1.0)
            if moving[k]:
                scale = np.sqrt(np.where(p.diagonal() > prior, prior / p.diagonal(), 1.0))
                p = p * np.outer(scale, scale)
    state = np.zeros(4, np.int64)
    theta_k, p_k = _fold_kernel(h, y, use, moving, r, np.zeros(10), np.diag(prior), prior, 0.99, np.zeros(10**6), state, 1e300, 0, n)
    assert np.allclose(theta_k, theta, rtol=1e-9, atol=1e-12) and np.allclose(p_k, p, rtol=1e-9, atol=1e-12)
    assert state[3] == int(use.any(axis=1).sum()) and state[2] == 0


def test_payload_attached_and_removed_is_tracked_within_2_s_offline() -> None:
    arm, plan, cfg = _arm_and_design()
    t_on, t_off = plan.lead_in_s + 3.0, plan.lead_in_s + 7.0
    run = simulate(arm.robot, cfg, plan.evaluate, plan.duration_s, payloads=[(t_on, PAYLOAD), (t_off, None)], seed=9)
    est = PayloadRLS(arm, 0.002)
    stream = EstimateStream(est, np.ones(6), publish_every=10)
    docs = stream.feed((k, float(run.t[k]), np.ones(6, bool), run.position[k], run.torque[k]) for k in range(run.t.size))
    times = np.array([d["record_time"] for d in docs])
    assert len(docs) >= run.t.size // 10 - 1  # 50 Hz
    _check_tracking(times, docs, t_on, t_off)
    assert 2 <= est.resets_ <= 4  # the attach and the removal, not the noise
    assert docs[-1]["excited"][0] and docs[-1]["converged"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_live_estimates_over_zenoh_reach_another_process_and_agree_with_replay(tmp_path: Path) -> None:
    import zenoh

    arm, plan, _ = _arm_and_design()
    rig = load_rig(RIG).with_bus(channel=f"armid-pl-{uuid.uuid4().hex[:8]}")
    estimates_endpoint, stream_endpoint = f"tcp/127.0.0.1:{_free_port()}", f"tcp/127.0.0.1:{_free_port()}"
    got = tmp_path / "estimates.jsonl"
    sub = subprocess.Popen([sys.executable, str(HELPERS / "estimate_subscriber.py"), rig.robot.name, estimates_endpoint, str(got), "90"],
                           env=ENV, stdout=subprocess.PIPE, text=True)
    assert sub.stdout is not None and sub.stdout.readline().strip() == "ready"
    publisher = zenoh.open(session_config(listen=[stream_endpoint]))
    estimator = zenoh.open(session_config(connect=[stream_endpoint, estimates_endpoint]))
    kt = np.array([j.torque_constant for j in arm.robot.joints])
    service = PayloadService(estimator, rig.robot.name, EstimateStream(PayloadRLS(arm, 0.002), kt), max_backlog=10**9)
    stream = Stream(publisher, rig.robot.name, "excite", lambda: {})
    cycles: dict[str, int] = {}
    try:
        with ExcitationSession(rig, simulate=True, stream=stream) as s:
            assert s.arm is not None
            arm_sim = s.arm

            def attach(name: str, payload: Payload | None) -> None:
                arm_sim.physics.attach_payload(payload)
                cycles[name] = arm_sim.syncs

            on, off = plan.lead_in_s + 3.0, plan.lead_in_s + 7.0
            report_box: dict[str, object] = {}
            runner = threading.Thread(target=lambda: report_box.update(r=s.run(plan, tmp_path / "run", "payload")))
            runner.start()
            while ("on" not in cycles or "off" not in cycles) and runner.is_alive():
                if "on" not in cycles and s.control.plan_time >= on:
                    attach("on", PAYLOAD)
                if "on" in cycles and "off" not in cycles and s.control.plan_time >= off:
                    attach("off", None)
                time.sleep(0.002)
            runner.join(120)
            report = report_box["r"]
        assert report.completed, report.stop_reason  # type: ignore[attr-defined]
        assert wait_for(lambda: service.backlog == 0, 10.0)
        time.sleep(1.0)
    finally:
        service.close()
        stream.close()
        estimator.close()
        publisher.close()
        sub.send_signal(signal.SIGTERM)
        sub.wait(20)
    live = [json.loads(line) for line in got.read_text().splitlines() if line]
    assert len(live) >= 0.9 * plan.duration_s * 50, len(live)  # 50 Hz, received in another process
    assert service.stream.skipped == 0 and service.stream.lost == 0
    a, _, notes = read_mcap_arrays(tmp_path / "run" / "run.mcap")
    assert not notes
    seq_of_cycle = dict(zip(a["cycle"].tolist(), a["sequence"].tolist()))
    time_of_seq = dict(zip(a["sequence"].tolist(), a["t"].tolist()))
    t_on, t_off = time_of_seq[seq_of_cycle[cycles["on"]]], time_of_seq[seq_of_cycle[cycles["off"]]]
    mine = [d for d in live if d["sequence"] in time_of_seq]
    _check_tracking(np.array([d["record_time"] for d in mine]), mine, t_on, t_off)
    # the same recording on replay: the same estimates, sequence by sequence
    ident = tmp_path / "ident.json"
    ident.write_text(json.dumps({"base_parameters": [{"expression": e, "value": float(v)} for e, v in
                                                     zip(structural_base(arm.robot).expressions(), arm.beta)],
                                 "joint_noise_sigma": arm.joint_sigma.tolist()}))
    out = tmp_path / "replay.jsonl"
    assert main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(ident), "--replay",
                 str(tmp_path / "run" / "run.mcap"), "--out", str(out)]) == 0
    replay = {d["sequence"]: d for d in (json.loads(x) for x in out.read_text().splitlines())}
    both = [d for d in mine if d["sequence"] in replay]
    assert len(both) >= 0.95 * len(mine)
    for d in both:
        r = replay[d["sequence"]]
        assert abs(d["mass"] - r["mass"]) <= 1e-6 * max(1.0, abs(r["mass"])), (d["sequence"], d["mass"], r["mass"])


def test_estimate_refuses_an_identification_of_another_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "ident.json"
    bad.write_text(json.dumps({"base_parameters": [{"expression": "m1 + m2", "value": 1.0}]}))
    data = tmp_path / "x.csv"
    data.write_text("t,q1,q2,q3,q4,q5,q6,tau1,tau2,tau3,tau4,tau5,tau6\n0,0,0,0,0,0,0,0,0,0,0,0,0\n")
    code = main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(bad), "--replay", str(data)])
    err = capsys.readouterr().err
    assert code == 2 and "do not match" in err and "first difference at #1" in err, err
    assert main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(bad)]) == 2
