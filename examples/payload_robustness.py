"""Payload estimation against the model errors of a real arm, alone and with a reference run.

The simulated PUMA 560 with, one at a time and together: torque constants 2-4 % off, an
unmodeled torque offset per joint, and Coulomb friction growing 2 % of the transmitted
torque. The arm is identified (``identify``, declared viscous and Coulomb friction) on an
unloaded run of another trajectory; a 2 kg payload is attached 3 s into a second
trajectory, and estimated alone and against an unloaded run of that trajectory
(``armid estimate --reference``). Prints the mass and centre-of-mass error 1, 2, 3 and 5 s
after the attach. The last case has all the errors and is recorded as a real arm's logs are:
at 100 Hz with jittered steps (the 1 ms simulation sampled 10 ms +- 4 ms apart).

    python examples/payload_robustness.py
"""

import dataclasses
import time
from pathlib import Path

import numpy as np

from armid.daq.payload_service import EstimateStream
from armid.identify import excitation as ex
from armid.identify.identification import IdentifyOptions, identify
from armid.identify.payload.rls import ArmModel, PayloadRLS, ReferenceRun
from armid.identify.preprocess import PrepareOptions, prepare
from armid.io.rig_file import load_rig
from armid.schema.joint_states import JointStates
from armid.sim_bus.offline import simulate
from armid.sim_bus.physics import Payload, simulation_config

ROOT = str(Path(__file__).resolve().parent.parent)
rig = load_rig(ROOT + '/config/rigs/sim.yaml')
robot = rig.robot
PAYLOAD = Payload(2.0, (0.02, -0.03, 0.08), (0.004, 0.0, 0.0, 0.004, 0.0, 0.002))
base_cfg = simulation_config(rig.simulation, 6)
def with_errors(cfg, gain=True, offset=True, load=True):
    gains = [1.03, 0.97, 1.04, 0.98, 1.02, 0.96]
    offs = [0.3, 1.0, -0.6, 0.1, -0.1, 0.05]
    j = []
    for k, e in enumerate(cfg.joints):
        j.append(dataclasses.replace(e, torque_gain=gains[k] if gain else 1.0, offset=offs[k] if offset else 0.0, load_friction=0.02 if load else 0.0))
    return dataclasses.replace(cfg, joints=tuple(j))
t0=time.time()
d_id = ex.design(robot, base_frequency_hz=0.2, seed=5, margin=0.6)
d = ex.design(robot, base_frequency_hz=0.2, seed=3, margin=0.6)
start = np.asarray(rig.simulation["initial_position"], float)
lim = ex.Limits.of(robot)
plan_id = ex.plan(d_id, start, lim, periods=3)
plan = ex.plan(d, start, lim, periods=2)
print('designs', time.time()-t0)
kt = np.array([j.torque_constant for j in robot.joints])
rng = np.random.default_rng(7)


def jittered_100_hz(run):
    """Every 10th record of a 1 ms run, each moved by up to 4 records (std 2): stamps 10 ms apart, +-40 %."""
    idx = np.arange(0, run.t.size - 5, 10)
    idx = np.unique(np.clip(idx + np.clip(np.round(rng.normal(0, 2.0, idx.size)), -4, 4).astype(int), 0, run.t.size - 1))
    return dataclasses.replace(run, t=run.t[idx], position=run.position[idx], torque=run.torque[idx])


for label, kw in [("none", dict(gain=False, offset=False, load=False)), ("gain", dict(gain=True, offset=False, load=False)),
                  ("offset", dict(gain=False, offset=True, load=False)), ("load friction", dict(gain=False, offset=False, load=True)),
                  ("all", dict()), ("all, 100 Hz jitter", dict())]:
    jitter = "jitter" in label
    cfg = with_errors(base_cfg, **kw)
    run_id = simulate(robot, cfg, plan_id.evaluate, plan_id.duration_s, seed=11)
    res = identify(robot, [prepare(run_id.recording(), robot, PrepareOptions(lowpass_hz=None))], None, IdentifyOptions(exclude_reversals=True))
    arm = ArmModel(robot, tuple(res.effects), res.base.independent, res.estimate.beta, res.estimate.joint_sigma)
    t_on = plan.lead_in_s + 3.0
    period = dict(period_s=0.001) if jitter else {}
    loaded = simulate(robot, cfg, plan.evaluate, plan.duration_s, payloads=[(t_on, PAYLOAD)], seed=9, **period)
    unloaded = simulate(robot, cfg, plan.evaluate, plan.duration_s, seed=10, **period)
    if jitter:
        loaded, unloaded = jittered_100_hz(loaded), jittered_100_hz(unloaded)
    for ref in (None, ReferenceRun(arm, unloaded.t, unloaded.position, unloaded.torque)):
        est = PayloadRLS(arm, reference=ref)
        st = EstimateStream(est)
        docs = st.feed(JointStates.of_log(np.arange(loaded.t.size), loaded.t, np.ones((loaded.t.size, 6), bool), loaded.position, loaded.torque))
        tt = np.array([x['record_time'] for x in docs])
        neg = sum(1 for x in docs if x['mass'] is not None and x['mass'] < 0)
        out=[]
        for dt in (1.0, 2.0, 3.0, 5.0):
            x = docs[int(np.searchsorted(tt, t_on + dt))]
            ce = None if x['com'] is None else 100*np.linalg.norm(np.array(x['com']) - PAYLOAD.com)
            m = None if x['mass'] is None else f"{x['mass']:.3f}+-{x['mass_std']:.3f}"
            out.append(f"{dt:.0f}s: {m} com {None if ce is None else round(ce,2)}cm {x['status']}")
        pre = docs[int(np.searchsorted(tt, t_on - 0.3))]
        print(f"{label:14s} ref={ref is not None}: neg={neg} before: {pre['mass']} {pre['status']} | " + " | ".join(out), flush=True)
print(time.time()-t0)
