"""Excitation design, limit checks, Khosla's single-link sequence, and runs on the drives."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

from armid.cli import main
from armid.daq.excite import ExcitationSession
from armid.demo import true_parameters
from armid.identify import excitation as ex
from armid.identify.excitation import experiment_columns, experiment_regressor
from armid.identify.identification import IdentifyOptions, identify
from armid.identify.preprocess import PrepareOptions, prepare
from armid.identify.single_link import SequenceResult, single_link_sequence
from armid.io.recordings import Recording, read_mcap_arrays
from armid.io.rig_file import load_rig
from armid.io.robot_file import load_robot
from armid.sim_bus.offline import simulate
from armid.sim_bus.physics import simulation_config
from armid.simulated import excitation_session

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / "config" / "rigs" / "sim.yaml"
PUMA = load_robot(ROOT / "config" / "robots" / "puma560.yaml")
HOLD = np.array([0.0, 0.7854, -0.7854, 0.0, 0.0, 0.0])


def test_design_starts_and_ends_at_rest_within_every_limit_and_says_what_it_excites() -> None:
    d = ex.design(PUMA, moving=(4,), q_hold=HOLD, base_frequency_hz=0.5, seed=3)
    q, qd, qdd = d.trajectory.evaluate(np.array([0.0, 2.0]))  # t = 0 and one period
    assert np.allclose(qd, 0.0, atol=1e-12) and np.allclose(qdd, 0.0, atol=1e-9)
    assert np.allclose(q[0], q[1])
    moving = np.ptp(d.trajectory.evaluate(np.linspace(0, 2, 400))[0], axis=0) > 1e-9
    assert moving.tolist() == [False, False, False, False, True, False]
    assert all(max(v) <= 0.8 + 1e-9 for v in d.peak.values())
    assert d.rank == len(d.base) and np.isfinite(d.condition_number)
    assert "m5" in d.unidentifiable  # a single wrist joint never shows its own mass
    p = ex.plan(d, HOLD, ex.Limits.of(PUMA), periods=2)
    peaks = ex.check_plan(PUMA, p, 0.002)
    assert max(peaks["velocity"]) <= 0.8 + 1e-6


def test_a_plan_beyond_a_limit_is_refused_naming_the_first_violation() -> None:
    d = ex.design(PUMA, moving=(1,), q_hold=HOLD, base_frequency_hz=0.5, seed=1)
    fast = dataclasses.replace(d.trajectory, a=d.trajectory.a * 3.0, b=d.trajectory.b * 3.0)
    p = ex.plan(fast, fast.evaluate(np.zeros(1))[0][0], ex.Limits.of(PUMA))
    with pytest.raises(ex.TrajectoryLimitError, match=r"joint 2: (velocity|position|acceleration) .* beyond the limit .* at t = ") as caught:
        ex.check_plan(PUMA, p, 0.002)
    assert caught.value.joint == 1


def _truth(names: list[str]) -> np.ndarray:
    return true_parameters(load_rig(RIG), names)


@functools.cache
def _single_link_sequence(seed: int) -> SequenceResult:
    """Khosla's six single-link experiments on the rig's simulated arm (friction, rotor
    inertia, quantisation, current noise), off the bus; one per seed and process."""
    rig = load_rig(RIG)
    cfg = simulation_config(rig.simulation, 6)
    limits = ex.Limits.of(PUMA)
    experiments = {}
    for k in range(5, -1, -1):
        hold = ex.choose_hold(PUMA, k, HOLD, seed=seed + k)
        d = ex.design(PUMA, moving=(k,), q_hold=hold, base_frequency_hz=0.5, seed=seed + k)
        p = ex.plan(d, HOLD, limits, periods=3)
        run = simulate(PUMA, cfg, p.evaluate, p.duration_s, seed=100 * seed + k)
        t0, t1 = p.excitation_window
        keep = (run.t >= t0) & (run.t <= t1)
        rec = Recording("sim", run.t[keep], run.position[keep], run.torque[keep], run.velocity[keep])
        experiments[k] = [prepare(rec, PUMA, PrepareOptions(lowpass_hz=None, torque_hold=True))]
    return single_link_sequence(PUMA, experiments)


def test_the_held_joints_small_motion_is_carried_at_the_modeled_values_not_absorbed_by_the_fit() -> None:
    """Khosla's combinations come from the ideal motion (held joints still), but held joints
    track their pose only to a few mrad. With torques that are exactly the model's at the
    measured motion (held joint 2 swaying 2 mrad with joint 3's acceleration, as a position
    loop lets it), the sequence must return the true combinations. Before, the torque that
    motion adds through Izz3 against the rotor's ia3 (columns equal only when joint 2 is
    still) went into the fit: fv3 came out 0.8 sigma high on the demo's bus runs."""
    rig = load_rig(RIG)
    cfg = simulation_config(rig.simulation, 6)
    limits = ex.Limits.of(PUMA)
    experiments = {}
    for k in (5, 4, 3, 2):
        hold = ex.choose_hold(PUMA, k, HOLD, seed=k)
        d = ex.design(PUMA, moving=(k,), q_hold=hold, base_frequency_hz=0.5, seed=k)
        p = ex.plan(d, HOLD, limits, periods=2)
        run = simulate(PUMA, cfg, p.evaluate, p.duration_s, seed=k)
        t0, t1 = p.excitation_window
        keep = (run.t >= t0) & (run.t <= t1)
        experiments[k] = [prepare(Recording("sim", run.t[keep], run.position[keep], run.torque[keep], run.velocity[keep]), PUMA,
                                  PrepareOptions(lowpass_hz=None, torque_hold=True))]
    sway = experiments[2][0].segments[0]  # joint 2 held while joint 3 moves: it gives way to the reaction
    gain = -0.002 / np.abs(sway.qdd[:, 2]).max()
    sway.q[:, 1] += gain * sway.qdd[:, 2]
    sway.qd[:, 1] += gain * np.gradient(sway.qdd[:, 2], sway.t)
    sway.qdd[:, 1] += gain * np.gradient(np.gradient(sway.qdd[:, 2], sway.t), sway.t)
    names = experiment_columns(PUMA, (0,))[1]
    phi = _truth(names)
    for runs in experiments.values():
        for seg in runs[0].segments:
            seg.tau = (experiment_regressor(PUMA, tuple(range(6)), seg.q, seg.qd, seg.qdd) @ phi).reshape(-1, 6)
    seq = single_link_sequence(PUMA, experiments, modeled=phi)
    error = seq.beta - np.array([fn.row @ phi for fn in seq.functionals])
    scale = np.array([np.abs(fn.row) @ np.abs(phi) for fn in seq.functionals])
    assert np.abs(error).max() < 1e-9 * scale.max(), [(fn.expression, e) for fn, e in zip(seq.functionals, error) if abs(e) > 1e-9 * scale.max()]
    # with the robot file's modeled rotor inertias (datasheet values, 0.1-0.6 % off the
    # simulator's), what is left is that share of the error a zero rotor inertia leaves
    truth = np.array([fn.row @ phi for fn in seq.functionals])
    no_rotor = phi.copy()
    no_rotor[[names.index(f"ia{j + 1}") for j in range(6)]] = 0.0
    datasheet = np.abs(single_link_sequence(PUMA, experiments).beta - truth)
    zero = np.abs(single_link_sequence(PUMA, experiments, modeled=no_rotor).beta - truth)
    print(datasheet.max() / zero.max(), zero.max())
    assert datasheet.max() < 0.01 * zero.max(), (datasheet.max(), zero.max())


def test_a_direction_an_earlier_link_took_is_not_offered_again_from_its_rounding() -> None:
    """Each step's rows hold their regrouping to 1e-10, so a later step's columns keep that
    much of the directions earlier links took. Scaled to unit norm, such a column looked
    independent and was fitted to the noise: on the simulated KUKA (joint 1's axis vertical),
    link 1's step named Izz5 and Izz6 alone and put them at -5e7 and +5e7. Joint 1 alone shows
    one inertia about its axis, its friction and its offset: four combinations."""
    kuka = load_robot(ROOT / "config" / "robots" / "kuka_lwr4.yaml")
    rig = dataclasses.replace(load_rig(RIG), robot=kuka, simulation={"current_noise_a": 0.005, "substeps": 2, "effects": [
        {"joint": "all", "viscous": 0.5, "coulomb": 0.8}]})
    cfg = simulation_config(rig.simulation, kuka.n_joints)
    hold, limits, experiments = np.zeros(kuka.n_joints), ex.Limits.of(kuka), {}
    for k in range(kuka.n_joints - 1, -1, -1):
        pose = ex.choose_hold(kuka, k, hold, seed=k)
        p = ex.plan(ex.design(kuka, moving=(k,), q_hold=pose, base_frequency_hz=0.5, seed=k), pose, limits, periods=3)
        run = simulate(kuka, cfg, p.evaluate, p.duration_s, seed=k)
        t0, t1 = p.excitation_window
        keep = (run.t >= t0) & (run.t <= t1)
        experiments[k] = [prepare(Recording("sim", run.t[keep], run.position[keep], run.torque[keep], run.velocity[keep]), kuka,
                                  PrepareOptions(lowpass_hz=None, torque_hold=True))]
    seq = single_link_sequence(kuka, experiments)
    assert seq.steps[-1]["link"] == 1 and seq.steps[-1]["identified"] == 4, [fn.expression for fn in seq.functionals if fn.link == 0]
    assert np.all(seq.std > 0), [fn.expression for fn, s in zip(seq.functionals, seq.std) if not s > 0]  # the torques nearly noise-free
    phi = true_parameters(rig, seq.names)
    link1 = [j for j, fn in enumerate(seq.functionals) if fn.link == 0]
    error = seq.beta[link1] - np.array([seq.functionals[j].row @ phi for j in link1])
    scale = np.array([np.abs(seq.functionals[j].row) @ np.abs(phi) for j in link1])
    assert np.all(np.abs(error) < 0.01 * scale.max()), [(seq.functionals[j].expression, e) for j, e in zip(link1, error)]


@pytest.mark.slow
def test_the_single_link_sequence_s_covariance_is_calibrated_against_the_truth() -> None:
    """The error of all 28 estimates, whitened by the reported covariance (cross terms and
    the uncertainty carried from link to link included), must be chi-square with 28 degrees
    of freedom per seed. Pooled over seeds 0, 3 and 7 (84 dof) it must stay below the 99.9 %
    point. With the plain 5-point filter's droop (every inertia read 0.05-0.1 % high, up to
    3 standard deviations of the best-determined combinations) it was 2.10 per dof, above
    the 1.53 allowed; with the sharpened filter 1.38."""
    from scipy.stats import chi2

    total, dof = 0.0, 0
    for seed in (0, 3, 7):
        seq = _single_link_sequence(seed)
        phi = _truth(seq.names)
        error = seq.beta - np.array([fn.row @ phi for fn in seq.functionals])
        total += float(error @ np.linalg.pinv(seq.covariance) @ error)
        dof += error.size
    assert total <= chi2.ppf(0.999, dof), (total / dof, dof)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 3, 7])
def test_single_link_sequence_and_whole_arm_recover_the_combinations_within_their_standard_deviations(seed: int) -> None:
    """The rig's simulated arm (friction, rotor inertia, quantisation, current noise), off the bus.

    About 80 estimates per seed: even unbiased estimates with exact standard deviations
    leave 3 sigma with probability 0.27 % each, so that one seed in five has one outside.
    Strongly correlated pairs (Izz6 and ia6) leave together. What must hold is what a bias
    would break: none beyond 4.5 sigma, at most three beyond 3 (the friction bias fixed in
    issue 6 put 4-6 estimates beyond 3 sigma, up to 5.4 sigma)."""
    rig = load_rig(RIG)
    cfg = simulation_config(rig.simulation, 6)
    limits = ex.Limits.of(PUMA)
    seq = _single_link_sequence(seed)
    phi = _truth(seq.names)
    truth = np.array([fn.row @ phi for fn in seq.functionals])
    z = (seq.beta - truth) / seq.std
    assert len(seq.functionals) >= 25  # Izz-like, gravity and friction terms of every link
    names = [fn.expression for fn in seq.functionals]
    # whole-arm excitation on the same arm, validated on a second run
    prepared = []
    for i in range(2):
        d = ex.design(PUMA, base_frequency_hz=0.2, seed=seed + 50 + i, margin=0.6)
        p = ex.plan(d, HOLD, limits, periods=2 - i)
        run = simulate(PUMA, cfg, p.evaluate, p.duration_s, seed=100 * seed + 50 + i)
        t0, t1 = p.excitation_window
        keep = (run.t >= t0) & (run.t <= t1)
        rec = Recording("sim", run.t[keep], run.position[keep], run.torque[keep], run.velocity[keep])
        prepared.append(prepare(rec, PUMA, PrepareOptions(lowpass_hz=None, torque_hold=True)))
    whole = identify(PUMA, [prepared[0]], [prepared[1]], IdentifyOptions(exclude_reversals=True))
    z_whole = (whole.estimate.beta - whole.base.base_values(_truth(whole.names))) / whole.estimate.std
    exprs = whole.base.expressions()
    z_all = np.concatenate([z, z_whole])
    outside = [(name, round(float(zz), 2)) for name, zz in zip(names + exprs, z_all) if abs(zz) > 3]
    assert np.abs(z_all).max() <= 4.5 and len(outside) <= 3, outside
    # every whole-arm base parameter that the single-link experiments also identify agrees
    both = [c for c in seq.compare(whole) if c["single_link"] is not None]
    assert both
    for c in both:
        gap = abs(c["whole_arm"] - c["single_link"])
        assert gap <= 4.0 * np.hypot(c["whole_arm_std"], c["single_link_std"]) + 1e-9, c


def _session(tmp_path: Path) -> ExcitationSession:
    rig = load_rig(RIG).with_bus(channel=f"armid-ex-{uuid.uuid4().hex[:8]}")
    return excitation_session(rig, simulate=True)


def test_excitation_on_the_bus_runs_records_and_holds(tmp_path: Path) -> None:
    with _session(tmp_path) as s:
        # the caller designs at the ordinary policy, runs at the loop's (SCHED_FIFO where allowed)
        loop = next(t for t in threading.enumerate() if t.name == "armid-acquisition").native_id
        between = [os.sched_getscheduler(0)]
        d = ex.design(s.robot, moving=(5,), q_hold=s.position, base_frequency_hz=0.5, seed=2)
        p = ex.plan(d, s.position, s.limits, periods=2)
        ex.check_plan(s.robot, p, s.rig.period_s)
        during: list[int] = []
        report = s.run(p, tmp_path / "j6", "link6", {"design": d.to_json()}, progress=lambda t, c: during.append(os.sched_getscheduler(0)))
        between.append(os.sched_getscheduler(0))
        loop_policy = os.sched_getscheduler(loop)
    assert between == [os.SCHED_OTHER] * 2 and set(during) == {loop_policy}, (between, during, loop_policy)
    assert report.completed, report.stop_reason
    arrays, metadata, notes = read_mcap_arrays(report.recording)
    assert not notes and np.all(np.diff(arrays["sequence"]) == 1)  # session-wide numbers, no gap
    assert metadata["completed"] == "true" and "stop" not in metadata  # a completed run says so
    assert np.all(np.diff(arrays["cycle"]) == 1)
    assert report.records == arrays["sequence"].size and report.cycles >= p.duration_s / s.rig.period_s - 1
    assert json.loads(metadata["excitation"])["design"]["moving_joints"] == [6]
    assert max(report.peak_torque_fraction) <= 1.0


def test_a_drive_that_stops_following_ends_in_a_quick_stop_within_3_cycles_and_nothing_recorded_is_lost(tmp_path: Path) -> None:
    with _session(tmp_path) as s:
        d = ex.design(s.robot, moving=(2,), q_hold=s.position, base_frequency_hz=0.5, seed=4)
        p = ex.plan(d, s.position, s.limits, periods=2)
        assert s.arm is not None
        threading.Timer(1.5, s.arm.drive(2).stop_following).start()
        report = s.run(p, tmp_path / "j3", "link3")
        states = [dr.state.name for dr in s.arm.drives]
    assert not report.completed and report.stop_reason is not None and "joint 3" in report.stop_reason, report.stop_reason
    assert all(st in ("QUICK_STOP_ACTIVE", "SWITCH_ON_DISABLED") for st in states), states  # stopping, or stopped
    arrays, metadata, notes = read_mcap_arrays(report.recording)
    assert not notes and np.all(np.diff(arrays["sequence"]) == 1)  # session-wide numbers, no gap
    # the recording says how the run ended (issue 62): the line armid excite prints after STOPPED
    assert metadata["completed"] == "false" and metadata["stop"] == report.stop_reason, metadata
    assert metadata["stop_cycle"] == str(report.stop_cycle) and metadata["records"] == str(report.records)
    cycles = arrays["cycle"]
    assert cycles[-1] >= report.stop_cycle  # everything up to the stop is in the file
    stopped_at = cycles[np.all((arrays["status"] & 0x6F) != 0x27, axis=1)]  # CiA 402: no drive operation enabled
    assert stopped_at.size and stopped_at[0] - report.stop_cycle <= 3, (stopped_at[:3], report.stop_cycle)


def test_excite_refuses_a_trajectory_beyond_a_limit_before_enabling_anything(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = ex.design(PUMA, moving=(1,), q_hold=HOLD, base_frequency_hz=0.5, seed=1)
    doc = d.to_json()
    doc["fourier"]["a"] = (np.asarray(doc["fourier"]["a"]) * 4).tolist()  # type: ignore[index]
    doc["fourier"]["b"] = (np.asarray(doc["fourier"]["b"]) * 4).tolist()  # type: ignore[index]
    path = tmp_path / "too_fast.json"
    path.write_text(json.dumps(doc))
    code = main(["excite", "--rig", str(RIG), "--channel", f"armid-ex-{uuid.uuid4().hex[:8]}", "--trajectory", str(path),
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "joint 2:" in err and "beyond the limit" in err, err
    assert not (tmp_path / "out" / "too_fast" / "run.mcap").exists()


def test_the_batched_gradient_is_the_criterion_s_derivative_and_designs_repeat_per_seed() -> None:
    """The gradient L-BFGS-B gets (the regressor's differences weighed by the criterion's
    differential, the candidates in one batch) against central differences of the criterion
    computed one trajectory at a time through the public path (FourierTrajectory.evaluate,
    experiment_regressor, slogdet): a wrong lever, scale or candidate order breaks it.

    The grid is offset by half a step here: at t = 0 a rest-to-rest series has qd = 0 up to
    rounding, and the Coulomb column sign(qd) there flips with the rounding, a step in the
    criterion that no derivative sees."""
    moving, rows, f_hz, margin, samples, harmonics = (0, 1, 2, 3, 4, 5), (0, 1, 2, 3, 4, 5), 0.2, 0.6, 160, 5
    lim = ex.Limits.of(PUMA)
    t = (np.arange(samples) + 0.5) / (samples * f_hz)
    cols, _, base, _ = ex._experiment_base(PUMA, rows, moving, HOLD, lim, np.random.default_rng(0))
    indep = [cols[k] for k in base.independent]
    space = ex._Candidates(PUMA, lim, HOLD, moving, f_hz, margin, t, PUMA.modeled_parameters(), rows, indep)
    k_free = len(moving) * (harmonics - 1)

    def split(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, b = ex._rest_to_rest(x[:, :k_free].reshape(-1, harmonics - 1), x[:, k_free:].reshape(-1, harmonics - 1))
        return a.reshape(x.shape[0], len(moving), -1), b.reshape(x.shape[0], len(moving), -1)

    def criterion(x: np.ndarray) -> float:  # one trajectory, the public way
        q0, a, b, _ = space.scaled(*split(x[None]), lambda w: np.zeros(w.shape[0]))
        q, qd, qdd = ex.FourierTrajectory(q0[0], a[0], b[0], f_hz).evaluate(t)
        w = ex.experiment_regressor(PUMA, rows, q, qd, qdd)[:, indep] / space.scale
        return -float(np.linalg.slogdet(w.T @ w / w.shape[0])[1])

    x = np.random.default_rng(5).normal(size=2 * k_free)
    w0 = space.scaled(*split(x[None]), space.information)[3][0]
    space.scale = np.linalg.norm(w0, axis=0) / np.sqrt(w0.shape[0])
    h = np.full_like(x, 1e-4)
    f, g = space.cost_and_gradient(*split(np.vstack([x, x + np.diag(h)])), (x + h) - x)
    assert f == pytest.approx(criterion(x), rel=1e-9)
    e = 1e-5
    central = np.array([(criterion(x + e * np.eye(x.size)[i]) - criterion(x - e * np.eye(x.size)[i])) / (2 * e) for i in range(x.size)])
    assert np.abs(g - central).max() <= 2e-3 * np.abs(central).max(), np.abs(g - central).max() / np.abs(central).max()
    # the same seed gives the same design, bit for bit
    d1, d2 = (ex.design(PUMA, moving=(3,), q_hold=HOLD, base_frequency_hz=0.5, seed=11) for _ in range(2))
    assert np.array_equal(d1.trajectory.a, d2.trajectory.a) and np.array_equal(d1.trajectory.q0, d2.trajectory.q0)
