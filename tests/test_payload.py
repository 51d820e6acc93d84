"""On-line payload estimation: RLS on the simulated arm, live over Zenoh, and on replay."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from armid.cli import main
from armid.daq.payload_service import EstimateStream, PayloadService, wait_for
from armid.daq.stream import Stream, session_config
from armid.demo import true_parameters
from armid.identify import excitation as ex
from armid.identify.differentiation import derivatives_on_times, five_point_derivative, local_polynomial
from armid.identify.identification import declared_effects, stacked_regressor, structural_base
from armid.identify.payload.projection import phi_of_pseudo
from armid.identify.payload.rls import (
    FORGETTING_STEP_S,
    ArmModel,
    PayloadRLS,
    ReferenceRun,
    identification_document,
    project_feasible,
    project_feasible_many,
    pseudo_inertia,
)
from armid.io.recordings import read_mcap_arrays
from armid.io.rig_file import load_rig
from armid.schema.joint_states import JointStates
from armid.sim_bus.offline import simulate
from armid.sim_bus.physics import Payload, simulation_config
from armid.simulated import excitation_session

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / "config" / "rigs" / "sim.yaml"
HELPERS = Path(__file__).resolve().parent / "helpers"
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONFAULTHANDLER": "1"}  # a child that aborts prints every thread's stack
PAYLOAD = Payload(2.0, (0.02, -0.03, 0.08), (0.004, 0.0, 0.0, 0.004, 0.0, 0.002))  # 2 kg, 8.8 cm from the flange


@functools.cache
def _arm_and_design(seed: int = 3) -> tuple[ArmModel, ex.Plan, object]:
    """(Computed once per seed: the design takes a while.) The arm with its parameters known (the simulator's), its noise level measured on a
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


def test_the_estimators_update_equals_weighted_batch_least_squares() -> None:
    """PayloadRLS's own update (information form, per-joint noise weights, each equation counted
    for its time share, forgetting while moving, the prior centred on the anchor) against the
    least-squares solution of all its equations stacked at once (numpy's lstsq)."""
    robot = load_rig(RIG).robot
    effects = declared_effects(robot)
    base = structural_base(robot, effects)
    arm = ArmModel(robot, tuple(effects), base.independent, np.zeros(base.independent.size), np.ones(6))
    rls = PayloadRLS(arm, forgetting=0.99)
    rls.partial_fit(np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6)))  # started, nothing folded
    rng = np.random.default_rng(0)
    r = rng.uniform(0.5, 2.0, 6) ** 2
    theta_true = rng.normal(size=10) * rls.prior_std
    blocks = []
    for k in range(6):
        m = 12
        h = rng.normal(size=(m, 6, 10))
        y = h @ theta_true + rng.normal(size=(m, 6)) * np.sqrt(r)
        use = rng.uniform(size=(m, 6)) > 0.2
        dts = rng.uniform(0.5e-3, 2e-3, m)
        moving_s = 0.0 if k == 2 else float(dts.sum())
        blocks.append((h, y, use, dts, moving_s))
        theta, p = rls._fold_information(h, y, use, dts, moving_s, r)
    # each block's equations fade by the forgetting of every moving block after it
    tau = float(np.mean(rls.correlation_time_))
    rows, rhs = [np.diag(1.0 / rls.prior_std)], [np.zeros(10)]
    for k, (h, y, use, dts, _) in enumerate(blocks):
        later = sum(b[4] for b in blocks[k + 1:])
        weight = rls.forgetting ** (later / FORGETTING_STEP_S) * dts[:, None] * use / (r * tau)
        rows.append((np.sqrt(weight)[..., None] * h).reshape(-1, 10))
        rhs.append((np.sqrt(weight) * y).reshape(-1))
    a, b = np.vstack(rows), np.concatenate(rhs)
    batch, *_ = np.linalg.lstsq(a, b, rcond=None)
    assert np.allclose(theta, batch, rtol=1e-9, atol=1e-12 * np.abs(batch).max())
    assert np.allclose(p, np.linalg.inv(a.T @ a), rtol=1e-8, atol=1e-14)


def test_arm_model_and_payload_columns_equal_the_regressor() -> None:
    """The estimator's own (uncompiled) backward pass against the tested regressor kernel."""
    robot = load_rig(RIG).robot
    effects = declared_effects(robot)
    base = structural_base(robot, effects)
    rng = np.random.default_rng(0)
    beta = rng.normal(size=base.independent.size)
    arm = ArmModel(robot, tuple(effects), base.independent, beta, np.ones(6))
    q, qd, qdd = rng.normal(size=(3, 40, 6))
    tau, cols = arm.torque_and_payload_columns(q, qd, qdd)
    w = stacked_regressor(robot, effects, q, qd, qdd).reshape(40, 6, -1)
    assert np.allclose(tau, w[:, :, base.independent] @ beta, rtol=1e-9, atol=1e-9 * np.abs(tau).max())
    assert np.allclose(cols, w[:, :, 50:60], rtol=1e-9, atol=1e-9 * np.abs(cols).max())


def test_projection_is_physical_and_the_nearest_in_the_covariance_metric() -> None:
    rng = np.random.default_rng(2)
    scale = np.array([1, 0.1, 0.1, 0.1, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
    for _ in range(40):
        a = rng.normal(size=(10, 10))
        cov = a @ a.T * 10 ** rng.uniform(-6, 0) + np.diag(10 ** rng.uniform(-8, 0, 10))
        theta = rng.normal(size=10) * scale
        x = project_feasible(theta, cov)
        assert np.linalg.eigvalsh(pseudo_inertia(x)).min() >= 0 and x[0] >= 0
        if np.linalg.eigvalsh(pseudo_inertia(theta)).min() >= 0:
            assert np.array_equal(x, theta)
            continue
        # the projection onto a convex set: (y - x)^T W (theta - x) <= 0 for every feasible y
        w = np.linalg.inv(cov)
        for _ in range(100):
            low = np.tril(rng.normal(size=(4, 4)))
            y = x + rng.uniform(0.01, 1) * (phi_of_pseudo(low @ low.T) - x)
            cos = (y - x) @ w @ (theta - x) / np.sqrt(((y - x) @ w @ (y - x)) * ((theta - x) @ w @ (theta - x)))
            assert cos <= 1e-3, cos
    # a point mass at c has the pseudo-inertia m [c; 1][c; 1]^T: on the boundary, kept
    c = np.array([0.02, -0.03, 0.08])
    point = phi_of_pseudo(2.0 * np.outer(np.append(c, 1), np.append(c, 1)))
    assert np.allclose(project_feasible(point, np.eye(10)), point)


def test_many_projections_are_each_the_one_projection() -> None:
    """A replay projects its estimates in one call, the live service a few at a time: each
    answer is the single problem's to the bit, whichever others share the call."""
    rng = np.random.default_rng(5)
    scale = np.array([1, 0.1, 0.1, 0.1, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
    thetas = rng.normal(size=(12, 10)) * scale
    covs = np.array([a @ a.T * 1e-3 + 1e-6 * np.eye(10) for a in rng.normal(size=(12, 10, 10))])
    many = project_feasible_many(thetas, covs, atol=1e-3)
    assert np.array_equal(many, np.array([project_feasible(t, c, atol=1e-3) for t, c in zip(thetas, covs)]))
    assert np.array_equal(project_feasible_many(thetas[::-1], covs[::-1], atol=1e-3), many[::-1])
    assert all(np.linalg.eigvalsh(pseudo_inertia(x)).min() >= 0 for x in many)


def test_derivatives_on_time_stamps() -> None:
    """A degree-4 polynomial over a fixed 100 ms of time: exact for a quartic on uneven,
    jittered steps at any rate; seconds since 1970 as time stamps lose no more than their
    own rounding; a 1 Hz sine's acceleration is within 3e-4 of its amplitude at 1 ms and at
    10 ms alike (the twice-applied 5-point filter: 4.5e-3 at 10 ms)."""
    rng = np.random.default_rng(3)
    for step in (0.001, 0.002, 0.01):
        n = int(0.6 / step)
        tj = np.cumsum(rng.uniform(0.55 * step, 1.45 * step, n))  # jitter of +-45 %
        for offset in (0.0, 1.8e9):
            s = tj - tj[0]
            x = np.column_stack([1.0 - s + 3.0 * s**2 - 5.0 * s**3 + 2.0 * s**4, np.sin(2 * np.pi * s)])
            x0, x1, x2, ok = local_polynomial(tj + offset, x)
            assert ok.sum() >= n - 2 * 0.05 / (0.55 * step) - 2 and not ok[:3].any() and not ok[-3:].any()
            tol = 1e-7 if offset == 0 else 2e-4  # stamps near 1.8e9 s are rounded to 0.24 us
            assert np.allclose(x1[ok, 0], (-1.0 + 6.0 * s - 15.0 * s**2 + 8.0 * s**3)[ok], atol=tol), (step, offset)
            assert np.allclose(x2[ok, 0], (6.0 - 30.0 * s + 24.0 * s**2)[ok], atol=100 * tol), (step, offset)
            w = 2 * np.pi
            assert np.allclose(x2[ok, 1], -w * w * np.sin(w * s[ok]), atol=3e-4 * w * w + 100 * tol), (step, offset)
            qd, qdd = derivatives_on_times(tj + offset, x)
            assert np.array_equal(np.isfinite(qdd[:, 0]), ok)


def test_payload_attached_and_removed_is_tracked_within_2_s_offline() -> None:
    arm, plan, cfg = _arm_and_design()
    t_on, t_off = plan.lead_in_s + 3.0, plan.lead_in_s + 7.0
    run = simulate(arm.robot, cfg, plan.evaluate, plan.duration_s, payloads=[(t_on, PAYLOAD), (t_off, None)], seed=9)
    est = PayloadRLS(arm)
    stream = EstimateStream(est, publish_every=10)
    docs = stream.feed(JointStates.of_log(np.arange(run.t.size), run.t, np.ones(run.position.shape, bool), run.position, run.torque))
    times = np.array([d["record_time"] for d in docs])
    assert len(docs) >= run.t.size // 10 - 1  # 50 Hz
    _check_tracking(times, docs, t_on, t_off)
    assert 2 <= est.resets_ <= 4  # the attach and the removal, not the noise
    assert docs[-1]["excited"][0] and docs[-1]["converged"]
    assert all(d["mass"] is None or d["mass"] >= 0 for d in docs)
    assert not docs[0]["converged"] and docs[0]["mass"] is None and docs[0]["status"] == "not excited"


def test_what_is_published_does_not_depend_on_how_the_records_are_batched() -> None:
    """The live service feeds the records as they arrive (a few at a time), a replay all at
    once: the published (physically possible) estimates are the same. Each projection starts
    cold: started from the last answer, which lies on the boundary, the live path published
    2.054 kg and a centre of mass 1 cm from the replay's 2.011 kg on the same records."""
    arm, plan, cfg = _arm_and_design()
    t_on = plan.lead_in_s + 1.0
    run = simulate(arm.robot, cfg, plan.evaluate, t_on + 2.5, payloads=[(t_on, PAYLOAD)], seed=9)
    rows = JointStates.of_log(np.arange(run.t.size), run.t, np.ones(run.position.shape, bool), run.position, run.torque)
    whole = EstimateStream(PayloadRLS(arm)).feed(rows)
    live_stream = EstimateStream(PayloadRLS(arm))
    live = [d for k in range(0, len(rows), 7) for d in live_stream.feed(rows[k : k + 7])]
    assert [d["sequence"] for d in live] == [d["sequence"] for d in whole] and len(whole) >= run.t.size // 10 - 1
    assert sum(d["mass"] is not None and d["mass"] > 1.0 for d in whole) >= 50  # the payload is on and seen for a while
    for a, b in zip(live, whole):
        assert (a["mass"] is None) == (b["mass"] is None), a["sequence"]
        pa, pb = np.array(a["parameters"]), np.array(b["parameters"])
        assert np.allclose(pa, pb, rtol=1e-6, atol=1e-9), (a["sequence"], pa[:4], pb[:4])


def test_what_is_published_does_not_depend_on_where_the_stream_began() -> None:
    """The live service sees the records from before the recording began (the arm held at
    rest); its replay starts at the recording. The estimates are the same to the last bit,
    also after a bad record restarts the derivatives: each equation stands for the step from
    the record before it. (Before: the first equation after a restart stood for the typical
    step of the stream's first records, so a live estimate drifted 1e-7 kg from its replay
    after a record with a joint flagged invalid, as a loaded machine gives.)"""
    arm, plan, cfg = _arm_and_design()
    t_on = plan.lead_in_s + 1.0
    run = simulate(arm.robot, cfg, plan.evaluate, t_on + 2.5, payloads=[(t_on, PAYLOAD)], seed=9)
    held = 25  # records of the pose held before the recording began
    rng = np.random.default_rng(1)
    t = 1.8e9 + np.concatenate([run.t[0] - 0.002 * np.arange(held, 0, -1), run.t]) + rng.uniform(-2e-4, 2e-4, held + run.t.size)
    q = np.vstack([np.repeat(run.position[:1], held, axis=0), run.position])
    tau = np.vstack([run.torque[0] + 0.01 * rng.standard_normal((held, 6)), run.torque])
    valid = np.ones(q.shape, bool)
    valid[[700, 1100], [2, 4]] = False  # a joint's frame missed: the derivatives restart there
    seq = np.arange(t.size)
    records = JointStates.of_log(seq, t, valid, q, tau)
    live = _feed_states_in_batches(EstimateStream(PayloadRLS(arm)), records)
    replay = EstimateStream(PayloadRLS(arm)).feed(records[held:])
    a, b = {d["sequence"]: d for d in live}, {d["sequence"]: d for d in replay}
    both = [k for k in sorted(set(a) & set(b)) if b[k]["mass"] is not None]
    assert len(both) >= 0.9 * len(b) and max(both) > 1100
    assert all(a[k]["unconstrained"] == b[k]["unconstrained"] for k in both), next(k for k in both if a[k]["unconstrained"] != b[k]["unconstrained"])


def _feed_states_in_batches(stream: EstimateStream, records: JointStates, batch: int = 7) -> list[dict]:
    docs: list[dict] = []
    for a in range(0, len(records), batch):
        docs += stream.feed(records[a : a + batch])
    return docs


def zenoh_open(**endpoints: list[str]) -> object:
    import zenoh

    return zenoh.open(session_config(**endpoints))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _FedStream(EstimateStream):
    """An estimate stream that keeps every record the live service fed it, in order."""

    def __init__(self, estimator: PayloadRLS) -> None:
        super().__init__(estimator)
        self.records: list[JointStates] = []

    def feed(self, records: JointStates) -> list[dict]:
        self.records.append(records)
        return super().feed(records)


@pytest.mark.slow
@pytest.mark.realtime  # a simulated arm on a bus, and a live stream that must skip nothing
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
    fed = _FedStream(PayloadRLS(arm))
    service = PayloadService(estimator, rig.robot.name, fed, max_backlog_s=1e9)
    stream = Stream(publisher, rig.robot.name, "excite", lambda: {})
    cycles: dict[str, int] = {}
    try:
        with excitation_session(rig, simulate=True, stream=stream) as s:
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
    # what the live estimator took is what was recorded, bit for bit (from the recording's first record on)
    taken = JointStates.concat(fed.records)
    live_seq = taken.sequence
    at = np.searchsorted(live_seq, a["sequence"])
    assert np.array_equal(live_seq[np.minimum(at, live_seq.size - 1)], a["sequence"]), "a recorded record the live estimator never took"
    for name, rec in (("time", a["t"]), ("valid", a["valid"]), ("position", a["position"]), ("torque", a["torque"])):
        live_col = getattr(taken, name)[at]
        differ = np.flatnonzero((live_col != rec).reshape(rec.shape[0], -1).any(axis=1))
        assert differ.size == 0, f"live {name} differs from the recording's at records {a['sequence'][differ][:5].tolist()}"
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
    # the replay's last document is the run's final answer ("final": true, least squares over
    # everything since the last restart), stamped with the last record's sequence: not a checkpoint
    replay = {d["sequence"]: d for d in (json.loads(x) for x in out.read_text().splitlines()) if not d.get("final")}
    both = [d for d in mine if d["sequence"] in replay]
    assert len(both) >= 0.95 * len(mine)
    for d in both:
        r = replay[d["sequence"]]
        assert (d["mass"] is None) == (r["mass"] is None), (d["sequence"], d["mass"], r["mass"])  # null: not excited yet
        # the estimator's state to the last bit (the same records, however batched and wherever
        # the stream began: test_what_is_published_does_not_depend_on_where_the_stream_began), and
        # what is published (its projection, from the same cold start live and on replay, one
        # at a time or in a batch: rounding apart) to 1e-6
        assert d["unconstrained"] == r["unconstrained"], (d["sequence"], d["unconstrained"], r["unconstrained"])
        pd, pr = np.array(d["parameters"]), np.array(r["parameters"])
        assert np.allclose(pd, pr, rtol=1e-6, atol=1e-9), (d["sequence"], pd[:4], pr[:4])


def test_the_service_falls_behind_by_time_not_by_record_count() -> None:
    """The live service measures its backlog in the records' own time: 300 records at 1 kHz
    (0.3 s) are within ``max_backlog_s`` (0.5 s). Beyond it, a worker that was stalled (held,
    not computing) catches up: 80 records at 100 Hz (0.8 s) cost it milliseconds, nothing is
    skipped. A slow worker (each estimate takes 50 ms of its CPU, the records come every 10 ms)
    could not catch up: it skips to the newest and says so with the figures. Real Zenoh
    sessions, peer to peer on loopback; the worker is held inside its publishing callback
    while the records queue."""
    from armid.schema.joint_state import Sample
    from armid.schema.joint_states import JointStates

    arm, _, _ = _arm_and_design()
    robot = arm.robot.name
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    publisher = zenoh_open(listen=[endpoint])
    estimator = zenoh_open(connect=[endpoint])
    hold, held, release, slow = threading.Event(), threading.Event(), threading.Event(), threading.Event()

    def on_estimate(doc: dict) -> None:
        if slow.is_set():  # a slow estimator: 50 ms of this thread's CPU per estimate
            began = time.thread_time()
            while time.thread_time() - began < 0.05:
                pass
        if hold.is_set():
            hold.clear()
            held.set()
            release.wait(30)
            release.clear()

    notes: list[str] = []
    service = PayloadService(estimator, robot, EstimateStream(PayloadRLS(arm), publish_every=1), max_backlog_s=0.5,
                             on_estimate=on_estimate, log=notes.append)
    stream = Stream(publisher, robot, "test", lambda: {})
    start = np.asarray(load_rig(RIG).simulation["initial_position"], float)
    state = {"seq": 0, "t": 0.0}

    def send(count: int, step: float) -> None:
        for _ in range(count):
            state["t"] += step
            t = state["t"]
            q = start + 0.2 * np.sin(2 * np.pi * 0.5 * t + np.arange(6))
            s = Sample(state["seq"], t, np.ones(6, bool), q, np.zeros(6), np.ones(6, bool), np.zeros(6), np.zeros(6), np.zeros(6, np.int64),
                       torque=np.zeros(6))
            stream.publish(JointStates.of_sample(state["seq"], s))
            state["seq"] += 1

    def queue_while_held(first: int, count: int, step: float) -> None:
        hold.set()
        send(first, step)  # the worker estimates, then is held in its callback
        assert held.wait(30)
        held.clear()
        send(count, step)
        assert wait_for(lambda: service.backlog >= count, 10.0), service.backlog
        time.sleep(0.3)  # held a while longer: not computing
        release.set()

    try:
        assert wait_for(lambda: any(r.ok is not None for r in publisher.liveliness().get(  # type: ignore[attr-defined]
            f"armid/{robot}/alive/payload_estimator", timeout=1.0)), 10.0)
        queue_while_held(200, 300, 0.001)  # 0.3 s of the arm's time queued: more records than the old 250, less time than 0.5 s
        assert wait_for(lambda: service.backlog == 0 and service.last is not None and service.last["sequence"] == 499, 20.0)
        assert (service.behind, service.caught_up, service.stream.skipped, service.stream.lost) == (0, 0, 0, 0)
        queue_while_held(20, 80, 0.01)  # 0.8 s at 100 Hz queued: fewer records, more time than 0.5 s; a stall
        assert wait_for(lambda: service.backlog == 0 and service.last is not None and service.last["sequence"] == 599, 20.0)
        assert (service.behind, service.caught_up, service.stream.skipped, service.stream.lost) == (0, 1, 0, 0)
        assert notes == [], notes
        slow.set()
        send(40, 0.01)  # 2 s of its CPU for 0.4 s of the arm's: now it knows it is slow
        assert wait_for(lambda: service.backlog == 0 and service.last is not None and service.last["sequence"] == 639, 30.0)
        queue_while_held(1, 80, 0.01)
        assert wait_for(lambda: service.backlog == 0 and service.behind == 1, 30.0)
        assert service.stream.lost == 0 and service.stream.skipped >= 79, service.stream.skipped
        assert not service.errors, service.errors
        # the skip is said, with what catching up would have cost and how the batch before went
        assert len(notes) == 1, notes
        said = re.fullmatch(r"(\S+) s of the arm's time behind: skipped (\d+) records to the newest \(catching up would take (\S+) s of "
                            r"its CPU time\); the oldest waited \S+ s here; the batch before took (\S+) s, (\S+) s of it computing "
                            r"\(this process's threads \S+ s\), and ended \S+ s ago; load average \S+ on \d+ CPUs", notes[0])
        assert said is not None, notes[0]
        assert float(said[1]) > 0.5 and int(said[2]) == service.stream.skipped and float(said[3]) > 0.5, notes[0]
    finally:
        release.set()
        service.close()
        stream.close()
        estimator.close()
        publisher.close()


def test_estimate_refuses_an_identification_of_another_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "ident.json"
    bad.write_text(json.dumps({"base_parameters": [{"expression": "m1 + m2", "value": 1.0}]}))
    data = tmp_path / "x.csv"
    data.write_text("t,q1,q2,q3,q4,q5,q6,tau1,tau2,tau3,tau4,tau5,tau6\n0,0,0,0,0,0,0,0,0,0,0,0,0\n")
    code = main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(bad), "--replay", str(data)])
    err = capsys.readouterr().err
    assert code == 2 and "do not match" in err and "first difference at #1" in err, err
    assert main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(bad)]) == 2


def _ident_doc(arm: ArmModel, path: Path) -> Path:
    path.write_text(json.dumps({"base_parameters": [{"expression": e, "value": float(v)} for e, v in
                                                    zip(structural_base(arm.robot).expressions(), arm.beta)],
                                "joint_noise_sigma": [float(x) for x in arm.joint_sigma]}))
    return path


def _write_csv(path: Path, t: np.ndarray, q: np.ndarray, tau: np.ndarray) -> Path:
    n = q.shape[1]
    header = ["t"] + [f"q{j + 1}" for j in range(n)] + [f"tau{j + 1}" for j in range(n)]
    np.savetxt(path, np.column_stack([t, q, tau]), delimiter=",", header=",".join(header), comments="", fmt="%.10g")
    return path


def _strict_json(line: str) -> dict:
    def refuse(name: str) -> None:
        raise AssertionError(f"not JSON: {name}")

    return json.loads(line, parse_constant=refuse)


@functools.cache
def _run_at_1_ms() -> object:
    arm, plan, cfg = _arm_and_design()
    return simulate(arm.robot, cfg, plan.evaluate, plan.duration_s, period_s=0.001, payloads=[(0.0, PAYLOAD)], seed=4)  # type: ignore[arg-type]


def test_the_same_run_at_1_2_and_10_ms_replayed_without_a_period_agrees(tmp_path: Path) -> None:
    """One simulated run with the payload on, recorded at 1 ms, and the same run kept every
    2nd and 10th record: ``armid estimate --replay`` with no period option (issue 22). Every
    pair of final estimates agrees within the sum of their standard deviations, the mass and
    each axis of the centre of mass (the 5-point filter twice gave 2.015 +- 0.006 kg at 10 ms
    against 1.994 +- 0.005 kg at 1 ms); 10 ms is also within 2 % and 1 cm of 1 ms; all three
    are right within 5 %."""
    arm, plan, cfg = _arm_and_design()
    ident = _ident_doc(arm, tmp_path / "ident.json")
    run = _run_at_1_ms()
    finals, lasts = {}, {}
    for every in (1, 2, 10):
        data = _write_csv(tmp_path / f"run_{every}.csv", run.t[::every], run.position[::every], run.torque[::every])  # type: ignore[attr-defined]
        out = tmp_path / f"est_{every}.jsonl"
        assert main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(ident), "--replay", str(data),
                     "--out", str(out)]) == 0
        *_, lasts[every], finals[every] = [_strict_json(line) for line in out.read_text().splitlines()]
        assert finals[every]["final"] and not lasts[every].get("final")
    for a, b in ((1, 2), (1, 10), (2, 10)):  # the last published estimates (a second's memory)
        da, db = lasts[a], lasts[b]
        # one recording's torque constants for all three: only the data's parts differ
        assert abs(da["mass"] - db["mass"]) <= da["mass_std_data"] + db["mass_std_data"], (a, b, da["mass"], db["mass"])
        gap = np.abs(np.array(da["com"]) - np.array(db["com"]))
        assert np.all(gap <= np.array(da["com_std_data"]) + np.array(db["com_std_data"])), (a, b, da["com"], db["com"])
    da = finals[1]
    assert abs(finals[10]["mass"] - da["mass"]) <= 0.02 * PAYLOAD.mass
    assert np.linalg.norm(np.array(finals[10]["com"]) - np.array(da["com"])) <= 0.01
    for d in finals.values():  # and they are right
        assert abs(d["mass"] - PAYLOAD.mass) <= 0.05 * PAYLOAD.mass and d["converged"], d
    assert finals[1]["rate_changes"] == 0 and finals[10]["rate_changes"] == 0
    # a recording whose rate changes half way (2 ms, then 10 ms): handled, and said
    half = run.t.size // 2
    keep = np.concatenate([np.arange(0, half, 2), np.arange(half - half % 10 + 10, run.t.size, 10)])
    data = _write_csv(tmp_path / "changing.csv", run.t[keep], run.position[keep], run.torque[keep])
    out = tmp_path / "changing.jsonl"
    assert main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(ident), "--replay", str(data),
                 "--out", str(out)]) == 0
    d = _strict_json(out.read_text().splitlines()[-2])  # the last published estimate
    assert d["rate_changes"] == 1 and abs(d["mass"] - lasts[10]["mass"]) <= d["mass_std_data"] + lasts[10]["mass_std_data"], d


@pytest.mark.parametrize("switch", range(0, 20))
def test_a_rate_change_is_counted_once_wherever_it_falls_and_jitter_never(switch: int) -> None:
    """Stamps every 2 ms, then every 10 ms from a record ``switch`` ms later (the step across
    the switch anywhere from 2 to 12 ms): one rate change, in any batching. A window across the
    switch has a median between the two rates (4 ms), which is neither. 10 ms stamps moved by
    up to +-4 ms each: no rate change and no gap."""
    from armid.identify.payload.filter import StreamFilter

    t = np.concatenate([np.arange(0, 3.0, 0.002), 3.0 + 0.002 * (switch // 2) + 0.001 * (switch % 2) + np.arange(0, 3.0, 0.01)])
    for batch in (1, 7, t.size):
        f = StreamFilter()
        for a in range(0, t.size, batch):
            f._steps(t[a:a + batch])
        assert f.rate_changes == 1, (switch, batch, f.rate_changes)
    rng = np.random.default_rng(switch)
    jittered = np.sort(np.arange(0, 6.0, 0.01) + rng.uniform(-0.004, 0.004, 600))
    f = StreamFilter()
    gaps = f._steps(jittered)
    assert f.rate_changes == 0 and not gaps.any()


@pytest.mark.parametrize("extra, message", [
    (["--period", "0"], "--period must be a positive number of seconds"),
    (["--publish-every", "0"], "--publish-every must be a whole number of records >= 1"),
    (["--forgetting", "2"], "--forgetting must be in (0, 1]"),
    (["--period", "0.002"], "its time stamps say a 10 ms period, --period says 2 ms"),
])
def test_estimate_refuses_bad_options_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str) -> None:
    arm, _, _ = _arm_and_design()
    ident = _ident_doc(arm, tmp_path / "ident.json")
    t = np.arange(50) * 0.01
    tau = np.random.default_rng(0).normal(size=(50, 6))  # a torque: all zero or constant is refused as not wired
    data = _write_csv(tmp_path / "x.csv", t, np.zeros((50, 6)), tau)
    code = main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(ident), "--replay", str(data), *extra])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def test_estimate_refuses_bad_identification_and_reversed_time(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    arm, _, _ = _arm_and_design()
    robot = str(ROOT / "config/robots/puma560.yaml")
    t = np.arange(50) * 0.002
    data = _write_csv(tmp_path / "x.csv", t, np.zeros((50, 6)), np.zeros((50, 6)))
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2, 3]")
    assert main(["estimate", "--robot", robot, "--params", str(listed), "--replay", str(data)]) == 2
    err = capsys.readouterr().err
    assert "must be a JSON object" in err and "got a JSON list" in err and len(err.strip().splitlines()) == 1, err
    ident = _ident_doc(arm, tmp_path / "ident.json")
    reversed_csv = _write_csv(tmp_path / "rev.csv", t[::-1], np.zeros((50, 6)), np.zeros((50, 6)))
    assert main(["estimate", "--robot", robot, "--params", str(ident), "--replay", str(reversed_csv)]) == 2
    err = capsys.readouterr().err
    assert "column t: time runs backwards on 49 of 49 steps" in err and len(err.strip().splitlines()) == 1, err  # identify's check


def test_a_replay_without_motion_says_not_excited_in_valid_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    arm, _, _ = _arm_and_design()
    ident = _ident_doc(arm, tmp_path / "ident.json")
    t = np.arange(2000) * 0.002
    q = np.tile(np.asarray(load_rig(RIG).simulation["initial_position"], float), (2000, 1))
    rng = np.random.default_rng(5)
    tau = arm.torque(q, np.zeros_like(q), np.zeros_like(q)) + 0.05 * rng.normal(size=q.shape)
    data = _write_csv(tmp_path / "still.csv", t, q, tau)
    out = tmp_path / "est.jsonl"
    assert main(["estimate", "--robot", str(ROOT / "config/robots/puma560.yaml"), "--params", str(ident), "--replay", str(data),
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "mass not excited" in err and "0.000 kg" not in err, err
    docs = [_strict_json(line) for line in out.read_text().splitlines()]
    assert docs and all(d["mass"] is None and d["com"] is None and not d["converged"] and d["status"] == "not excited" for d in docs)


def _with_errors(cfg: object, gain: bool = True, offset: bool = True, load: bool = True) -> object:
    """The errors a real arm has and its model lacks: torque constants 2-4 % off, an unmodeled
    torque offset (a cable, a counterbalance) and Coulomb friction growing 2 % of the
    transmitted torque (a loaded gear)."""
    gains, offsets = [1.03, 0.97, 1.04, 0.98, 1.02, 0.96], [0.3, 1.0, -0.6, 0.1, -0.1, 0.05]
    joints = tuple(dataclasses.replace(e, torque_gain=gains[k] if gain else 1.0, offset=offsets[k] if offset else 0.0,
                                       load_friction=0.02 if load else 0.0) for k, e in enumerate(cfg.joints))  # type: ignore[attr-defined]
    return dataclasses.replace(cfg, joints=joints)  # type: ignore[type-var]


@functools.cache  # two tests read the default case; neither changes what it returns
def robustness_runs(gain: bool = True, offset: bool = True, load: bool = True, design_seed: int = 3, sim_seed: int = 9,
                    modes: tuple[str, ...] = ("alone", "reference")) -> dict[str, list[dict]]:
    """The arm identified (``identify``, declared friction) on an unloaded run of the simulated
    arm with the model errors; then the same trajectory with 2 kg attached 3 s in, estimated
    alone and against an unloaded run of it (reference mode), as ``modes`` ask. Returns the
    published documents and the attach time."""
    from armid.identify.identification import IdentifyOptions, identify
    from armid.identify.preprocess import PrepareOptions, prepare

    arm0, plan, cfg0 = _arm_and_design(design_seed)
    cfg = _with_errors(cfg0, gain, offset, load)
    robot = arm0.robot
    unloaded_id = simulate(robot, cfg, plan.evaluate, plan.duration_s, seed=sim_seed + 2)  # type: ignore[arg-type]
    res = identify(robot, [prepare(unloaded_id.recording(), robot, PrepareOptions(lowpass_hz=None))], None, IdentifyOptions(exclude_reversals=True))
    arm = ArmModel(robot, tuple(res.effects), res.base.independent, res.estimate.beta, res.estimate.joint_sigma)
    t_on = plan.lead_in_s + 3.0
    loaded = simulate(robot, cfg, plan.evaluate, plan.duration_s, payloads=[(t_on, PAYLOAD)], seed=sim_seed)  # type: ignore[arg-type]
    unloaded = simulate(robot, cfg, plan.evaluate, plan.duration_s, seed=sim_seed + 1)  # type: ignore[arg-type]
    out: dict[str, list[dict]] = {}
    references = {"alone": None, "reference": ReferenceRun(arm, unloaded.t, unloaded.position, unloaded.torque)}
    for name in modes:
        stream = EstimateStream(PayloadRLS(arm, reference=references[name]))
        out[name] = stream.feed(JointStates.of_log(np.arange(loaded.t.size), loaded.t, np.ones(loaded.position.shape, bool), loaded.position,
                                                   loaded.torque))
        out[f"{name}_final"] = [stream.final()]
    out["t_on"] = [{"t": t_on}]
    return out


def test_payload_with_the_model_errors_of_a_real_arm_alone_and_against_a_reference() -> None:
    """Issue 22: with those errors, 2 kg attached: never a negative mass; not converged while
    the motion does not excite it; 2 s after the attach the mass within 10 % and the centre
    of mass within 2 cm, and with a reference run within 5 % and 1 cm."""
    runs = robustness_runs()
    t_on = runs["t_on"][0]["t"]
    for name, mass_tol, com_tol in (("alone", 0.10, 0.02), ("reference", 0.05, 0.01)):
        docs = runs[name]
        assert all(d["mass"] is None or d["mass"] >= 0 for d in docs), name
        assert all(d["unconstrained"]["mass"] is not None for d in docs)
        unexcited = [d for d in docs if not d["excited"][0]]
        assert unexcited and not any(d["converged"] for d in unexcited), name  # at rest in the lead-in
        times = np.array([d["record_time"] for d in docs])
        for dt in (2.0, 2.5, 3.0):
            d = docs[int(np.searchsorted(times, t_on + dt))]
            assert abs(d["mass"] - PAYLOAD.mass) <= mass_tol * PAYLOAD.mass, (name, dt, d["mass"])
            assert np.linalg.norm(np.array(d["com"]) - PAYLOAD.com) <= com_tol, (name, dt, d["com"])


def test_the_run_s_final_answer_and_its_band_hold_the_truth_which_the_noise_alone_does_not() -> None:
    """Issue 33: against a reference run, torque constants 2-4 % off read 2 kg about 3 % low, an
    error no unloaded run sees. The run's final answer (every equation since the attach) is
    within 5 %; its band (2 sigma, the torque constants' part included) holds the truth, where
    the data's part alone does not; every estimate that said ``converged`` about this payload
    holds the final answer in its band."""
    runs = robustness_runs()
    for name, tol in (("alone", 0.10), ("reference", 0.05)):
        final = runs[f"{name}_final"][0]
        assert final["final"] and final["excited_s"] > 3.0, final
        assert abs(final["mass"] - PAYLOAD.mass) <= tol * PAYLOAD.mass, (name, final["mass"])
        assert abs(final["mass"] - PAYLOAD.mass) <= 2 * final["mass_std"], (name, final["mass"], final["mass_std"])
        assert final["mass_std"] ** 2 == pytest.approx(final["mass_std_data"] ** 2 + final["mass_std_torque_constants"] ** 2)
        same = [d for d in runs[name] if d["converged"] and d["resets"] == final["resets"]]
        assert all(abs(d["mass"] - final["mass"]) <= 2 * d["mass_std"] for d in same), name
    reference = runs["reference_final"][0]
    assert abs(reference["mass"] - PAYLOAD.mass) > 2 * reference["mass_std_data"], reference  # what the term is for


def test_the_torque_constants_term_is_what_a_scaled_constant_does_to_least_squares() -> None:
    """``torque_constant_covariance`` against the estimate itself: least squares on per-joint
    equations ``y_j = h_j theta``, refitted with joint j's torque scaled by ``1 + s``, moves by
    ``g``; the term with std ``s`` on joint j alone is ``g g^T`` (exact: least squares is
    linear in the torque)."""
    from armid.identify.payload.band import torque_constant_covariance

    rng = np.random.default_rng(5)
    h = rng.normal(size=(400, 3, 10))
    w = rng.uniform(0.5, 2.0, 3)
    theta = rng.normal(size=10)
    y = np.einsum("mjk,k->mj", h, theta)
    info = np.einsum("mjk,mjl,j->jkl", h, h, w)
    p = np.linalg.inv(info.sum(axis=0))

    def fit(scale: np.ndarray) -> np.ndarray:
        return p @ np.einsum("mjk,mj,j->k", h, y * scale, w)

    for j in range(3):
        s = np.zeros(3)
        s[j] = 0.05
        g = fit(1.0 + s) - fit(np.ones(3))
        np.testing.assert_allclose(torque_constant_covariance(p, info, theta, s), np.outer(g, g), rtol=1e-9, atol=1e-15)


def test_an_arm_coming_to_rest_is_not_a_new_payload() -> None:
    """Issue 33: as the arm stops at the end of a run its joints stop one after another, and a
    derivative window (+-50 ms) that reaches a stop holds the friction's step smeared across
    it. Equations taken 25 ms before a stop made a jump of 20 times the noise, read as a new
    payload 0.5 s before the end: the covariance reset, and the run's final answer was "not
    excited" (robustness case, design seed 4, against a reference run). Now the attach is the
    one reset, and the final answer is the payload within 5 %."""
    runs = robustness_runs(design_seed=4, sim_seed=409, modes=("reference",))
    docs, t_on = runs["reference"], runs["t_on"][0]["t"]
    resets = [d["record_time"] for d, before in zip(docs[1:], docs) if d["resets"] > before["resets"]]
    assert len(resets) == 1 and t_on <= resets[0] <= t_on + 0.5, (t_on, resets)
    assert docs[-1]["mass"] is not None and abs(docs[-1]["mass"] - PAYLOAD.mass) <= 0.05 * PAYLOAD.mass, docs[-1]["mass"]


def test_reversals_of_an_unloaded_arm_are_not_new_payloads(tmp_path: Path) -> None:
    """Issue 33: the shipped validation recording (no payload; Coulomb friction with a sharp
    sign) replayed against the arm identified on the excitation recording. The friction's step
    smeared through the derivative windows around each reversal reset the covariance 30 times
    in 10 s, each time throwing the estimate away; no reset now, and the run ends converged at
    no payload."""
    ident = tmp_path / "ident.json"
    robot = str(ROOT / "config/robots/puma560.yaml")
    assert main(["identify", str(ROOT / "examples/puma560_excitation.csv"), "--robot", robot, "--json", str(ident)]) == 0
    out = tmp_path / "e.jsonl"
    assert main(["estimate", "--robot", robot, "--params", str(ident), "--replay", str(ROOT / "examples/puma560_validation.csv"),
                 "--out", str(out)]) == 0
    last = _strict_json(out.read_text().splitlines()[-1])
    assert last["resets"] == 0 and last["converged"] and abs(last["mass"]) <= 3 * last["mass_std"], last


def _jittered_100_hz_csv(run: object, path: Path, seed: int) -> Path:
    """A 1 ms run as a real arm's log: every 10th record moved by up to 4 records (stamps
    10 ms +- 4 ms apart), seconds since 1970 rounded to the microsecond, motor currents."""
    rng = np.random.default_rng(seed)
    t = run.t  # type: ignore[attr-defined]
    idx = np.arange(0, t.size - 5, 10)
    idx = np.unique(np.clip(idx + np.clip(np.round(rng.normal(0, 2.0, idx.size)), -4, 4).astype(int), 0, t.size - 1))
    cols = ["t"] + [f"q{j + 1}" for j in range(6)] + [f"i{j + 1}" for j in range(6)]
    data = np.column_stack([np.round(t[idx] + 1.7e9, 6), run.position[idx], run.current[idx]])  # type: ignore[attr-defined]
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt=["%.6f"] + ["%.10g"] * 12)
    return path


def test_the_users_command_line_on_100_hz_logs_with_jittered_stamps(tmp_path: Path) -> None:
    """What the project will run on real logs, with no option but the files: motor currents at
    100 Hz with jittered stamps, the arm (with the model errors of a real one) identified by
    ``armid identify`` on an unloaded run, then ``armid estimate --replay`` alone and with
    ``--reference``: issue 22's lines hold (2 s after the attach mass within 10 % / 5 %,
    centre of mass within 2 cm / 1 cm; never negative; not converged before the motion
    excites the mass), and the jitter is taken for neither a gap nor a rate change."""
    arm0, plan, cfg0 = _arm_and_design()
    cfg = _with_errors(cfg0)
    robot_file = str(ROOT / "config/robots/puma560.yaml")
    t_on = plan.lead_in_s + 3.0
    runs = {"ident": simulate(arm0.robot, cfg, plan.evaluate, plan.duration_s, period_s=0.001, seed=21),  # type: ignore[arg-type]
            "loaded": simulate(arm0.robot, cfg, plan.evaluate, plan.duration_s, period_s=0.001, payloads=[(t_on, PAYLOAD)],  # type: ignore[arg-type]
                               seed=22),
            "unloaded": simulate(arm0.robot, cfg, plan.evaluate, plan.duration_s, period_s=0.001, seed=23)}  # type: ignore[arg-type]
    csv = {name: _jittered_100_hz_csv(run, tmp_path / f"{name}.csv", seed) for seed, (name, run) in enumerate(runs.items())}
    ident = tmp_path / "ident.json"
    assert main(["identify", str(csv["ident"]), "--robot", robot_file, "--json", str(ident)]) == 0
    for extra, mass_tol, com_tol in (([], 0.10, 0.02), (["--reference", str(csv["unloaded"])], 0.05, 0.01)):
        out = tmp_path / "est.jsonl"
        assert main(["estimate", "--robot", robot_file, "--params", str(ident), "--replay", str(csv["loaded"]), "--out", str(out),
                     *extra]) == 0
        docs = [_strict_json(line) for line in out.read_text().splitlines()]
        assert all(d["mass"] is None or d["mass"] >= 0 for d in docs)
        assert not any(d["converged"] for d in docs if not d["excited"][0])
        assert docs[-1]["rate_changes"] == 0
        times = np.array([d["record_time"] for d in docs]) - 1.7e9
        for dt in (2.0, 2.5, 3.0):
            d = docs[int(np.searchsorted(times, t_on + dt))]
            assert abs(d["mass"] - PAYLOAD.mass) <= mass_tol * PAYLOAD.mass, (extra, dt, d["mass"])
            assert np.linalg.norm(np.array(d["com"]) - PAYLOAD.com) <= com_tol, (extra, dt, d["com"])


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.alone  # an estimator process that must keep up with the live stream (beside a second test worker it skipped records)
def test_the_demo_payload_phase_from_a_cold_start(tmp_path: Path) -> None:
    """Issue 19: the demo's payload phase in a fresh process with an empty numba cache; the
    estimator is ``armid estimate live`` in a process of its own (issue 31). Events on the
    arm's clock: the payload is on for 4 s of record time; 2 s after the attach the mass
    within 5 % and the centre of mass within 1 cm; 2 s after the removal within 0.1 kg."""
    import pickle

    arm, plan, _ = _arm_and_design()
    pkl = tmp_path / "arm.pkl"
    pkl.write_bytes(pickle.dumps((arm, plan.trajectory)))
    env = {**ENV, "NUMBA_CACHE_DIR": str(tmp_path / "numba_cache")}
    done = subprocess.run([sys.executable, str(HELPERS / "payload_phase.py"), str(pkl), str(tmp_path / "out")], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    r = _strict_json(done.stdout.strip().splitlines()[-1])
    assert abs(r["on_for_s"] - 4.0) <= 0.005, r["on_for_s"]
    assert r["negative_mass_published"] == 0 and r["skipped"] == 0
    a2, off = r["after_attach_2s"], r["after_removal_2s"]
    assert abs(a2["mass"] - 2.0) <= 0.1 and a2["com_error_m"] <= 0.01, a2
    assert off["mass"] is not None and abs(off["mass"]) <= 0.1, off


def _ignore_sigint() -> None:
    """As a shell's background job starts a process: SIGINT ignored (inherited across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_live_estimator_started_in_the_background_stops_on_its_signal(tmp_path: Path, sig: int) -> None:
    """``armid estimate live`` started with SIGINT ignored, as a script's background job (the
    demo's processes inherit it too), stops on SIGINT and SIGTERM and exits 0. Before, it
    heard neither: the demo's stop waited 30 s for it, then killed it, in every demo run from a
    script."""
    arm, _, _ = _arm_and_design()
    params = tmp_path / "arm.json"
    params.write_text(json.dumps(identification_document(arm)))
    cmd = [sys.executable, "-m", "armid.cli", "estimate", "live", "--robot", str(load_rig(RIG).robot.source), "--params", str(params),
           "--out", str(tmp_path / "estimates.jsonl"), "--zenoh-listen", f"tcp/127.0.0.1:{_free_port()}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stderr=subprocess.PIPE, text=True, preexec_fn=_ignore_sigint)
    try:
        assert proc.stderr is not None
        listening = any("listening" in line for line in proc.stderr)  # stops reading at the first
        assert listening, "the estimator ended before it listened"
        proc.send_signal(sig)
        assert proc.wait(timeout=60) == 0, proc.stderr.read()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@functools.cache
def _loaded_run_2_ms() -> object:
    arm, plan, cfg = _arm_and_design()
    return simulate(arm.robot, cfg, plan.evaluate, plan.duration_s, payloads=[(0.0, PAYLOAD)], seed=4)  # type: ignore[arg-type]


def _feed_in_batches(stream: EstimateStream, seq: np.ndarray, t: np.ndarray, q: np.ndarray, tau: np.ndarray, batch: int = 7) -> list[dict]:
    return _feed_states_in_batches(stream, JointStates.of_log(seq, t, np.ones(q.shape, bool), q, tau), batch)


def test_bad_records_in_a_live_stream_are_dropped_counted_and_the_estimate_goes_on() -> None:
    """Issue 35: a live stream (batches of 7) with 10 records whose positions are NaN (valid
    flags set), a NaN torque, an infinite torque, one record stamped 10^6 s ahead, and a clock
    that steps 5 s back for the rest of the run. Each bad record is dropped and counted by
    reason, estimates are published to the end, and the final estimate is the clean run's
    within its standard deviation. (Before: nothing was published after the first of them.)"""
    arm, _, _ = _arm_and_design()
    run = _loaded_run_2_ms()
    t, q, tau = run.t.copy(), run.position.copy(), run.torque.copy()  # type: ignore[attr-defined]
    seq = np.arange(t.size)
    clean = _feed_in_batches(EstimateStream(PayloadRLS(arm)), seq, t, q, tau)
    q[1500:1510, 2] = np.nan
    tau[2000, 1] = np.nan
    tau[2500, 4] = np.inf
    t[3000] += 1e6
    step_back = 3500
    t[step_back:] -= 5.0
    stream = EstimateStream(PayloadRLS(arm))
    docs = _feed_in_batches(stream, seq, t, q, tau)
    assert stream.dropped == {"not finite": 12, "time": 11}, stream.dropped
    assert stream.resyncs == 1 and stream.time_faults == 11 and stream.lost == 0
    assert "clock stepped" in (stream.last_drop or ""), stream.last_drop
    assert len(docs) >= 0.97 * len(clean), (len(docs), len(clean))
    assert docs[-1]["sequence"] >= seq[-1] - 10  # published to the end
    published = np.array([d["sequence"] for d in docs])
    for k in (1510, 2001, 2501, 3001, step_back + 10):
        assert (published > k).any() and (published < k + 60).any()  # nothing stops at a bad record
    a, b = docs[-1], clean[-1]
    assert a["dropped"] == stream.dropped and a["last_drop"] == stream.last_drop
    assert abs(a["mass"] - b["mass"]) <= a["mass_std_data"], (a["mass"], b["mass"], a["mass_std_data"])  # the same torque constants
    assert np.all(np.abs(np.array(a["com"]) - np.array(b["com"])) <= np.array(a["com_std_data"])), (a["com"], b["com"])


def test_the_service_drops_unreadable_foreign_and_late_records_and_goes_on() -> None:
    """Issue 35, over real Zenoh sessions on loopback: after every 100 good records a garbage
    payload and a truncated one, after every 500 a record of a 5-joint arm, and the records sent
    in reversed groups of 4. The service publishes estimates to the end, counts each class in its
    status and documents, and has no error of its own."""
    from armid.schema.joint_state import Sample
    from armid.schema.joint_states import JointStates

    arm, _, _ = _arm_and_design()
    robot = arm.robot.name
    run = _loaded_run_2_ms()
    n = 3000
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    publisher = zenoh_open(listen=[endpoint])
    estimator = zenoh_open(connect=[endpoint])
    service = PayloadService(estimator, robot, EstimateStream(PayloadRLS(arm)), max_backlog_s=1e9)
    stream = Stream(publisher, robot, "test", lambda: {})

    def record(k: int, joints: int = 6) -> bytes:
        z = np.zeros(joints)
        s = Sample(k, float(run.t[k]), np.ones(joints, bool), run.position[k, :joints], z, np.ones(joints, bool), z, z,  # type: ignore[attr-defined]
                   np.zeros(joints, np.int64), torque=run.torque[k, :joints])  # type: ignore[attr-defined]
        return JointStates.of_sample(k, s).pack()

    try:
        assert wait_for(lambda: any(r.ok is not None for r in publisher.liveliness().get(  # type: ignore[attr-defined]
            f"armid/{robot}/alive/payload_estimator", timeout=1.0)), 10.0)
        good = [record(k) for k in range(n)]
        for a in range(0, n, 4):
            for b in reversed(good[a:a + 4]):
                stream._pub.put(b)
            if a % 100 == 0 and a:
                stream._pub.put(b"not a record at all")
                stream._pub.put(good[a][: len(good[a]) // 2])
            if a % 500 == 0 and a:
                stream._pub.put(record(a, joints=5))
            time.sleep(0.002)
        assert wait_for(lambda: service.backlog == 0 and service.last is not None and service.last["sequence"] >= n - 10, 60.0), service.last
        dropped = service.stream.dropped
        assert dropped.get("malformed") == 2 * 29 and dropped.get("joints") == 5, dropped
        assert service.published >= 0.9 * n / 10, service.published
        import zenoh

        status = [json.loads(r.ok.payload.to_bytes()) for r in publisher.get(f"armid/{robot}/status", target=zenoh.QueryTarget.ALL,
                                                                             consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0) if r.ok]
        mine = next(d for d in status if d.get("component") == "payload_estimator")
        assert mine["dropped"]["malformed"] == 58 and mine["last_drop"], mine
        assert service.last["dropped"]["joints"] == 5
        assert not service.errors, service.errors
    finally:
        service.close()
        stream.close()
        estimator.close()
        publisher.close()


def test_a_replay_gets_identifys_checks_and_names_an_input_it_cannot_use(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 35: ms stamps and degrees were refused by identify but replayed; mN*m, all-NaN
    positions ended in 'no estimate' with exit 0 (or an internal error); a garbage row (an extra
    field) stopped the replay as 'time nan is not after the line before'. The shipped example
    recordings, changed as a logger would get them wrong."""
    ident = tmp_path / "ident.json"
    robot = str(ROOT / "config/robots/puma560.yaml")
    assert main(["identify", str(ROOT / "examples/puma560_excitation.csv"), "--robot", robot, "--json", str(ident)]) == 0
    lines = (ROOT / "examples/puma560_validation.csv").read_text().splitlines()
    header = lines[0].split(",")
    q = [i for i, h in enumerate(header) if h.startswith("q") and not h.startswith("qd")]
    tau = [i for i, h in enumerate(header) if h.startswith("tau")]

    def changed(name: str, change: Callable[[int, str], str], extra_field_at: int | None = None) -> Path:
        rows = [",".join(change(i, v) for i, v in enumerate(line.split(","))) for line in lines[1:]]
        if extra_field_at is not None:
            rows[extra_field_at] += "," + "1" * 131_000
        path = tmp_path / f"{name}.csv"
        path.write_text("\n".join([lines[0], *rows]) + "\n")
        return path

    cases = {
        "ms": (changed("ms", lambda i, v: str(float(v) * 1000) if i == 0 else v), "look like milliseconds"),
        "degrees": (changed("deg", lambda i, v: str(np.degrees(float(v))) if i in q else v), "look like degrees"),
        "mNm": (changed("mnm", lambda i, v: str(float(v) * 1000) if i in tau else v), "gross outliers against the identified arm: is the torque in N*m"),
        "NaN positions": (changed("nan", lambda i, v: "nan" if i in q else v), "no estimate from 5000 records (5000 dropped: 5000 not finite"),
    }
    for name, (path, said) in cases.items():
        assert main(["estimate", "--robot", robot, "--params", str(ident), "--replay", str(path), "--out", str(tmp_path / "e.jsonl")]) == 2, name
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err and "internal error" not in err, (name, err)
    long_line = changed("long", lambda i, v: v, extra_field_at=100)
    assert main(["estimate", "--robot", robot, "--params", str(ident), "--replay", str(long_line), "--out", str(tmp_path / "e.jsonl")]) == 0
    err = capsys.readouterr().err
    assert "left out 1 row(s) without a time stamp (line 102)" in err and "converged" in err, err
