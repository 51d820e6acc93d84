"""``armid sim``: the simulated arm on a CAN bus, or a Dynamixel chain on a pty, until stopped."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from .arguments import positive_number, seed_number
from .output import inputs_read
from .rig import rig_from_arguments, run_until, stopped_by_signals


def _sim(args: argparse.Namespace) -> int:
    rig = rig_from_arguments(args)
    inputs_read()
    with stopped_by_signals() as stop:
        return _sim_chain(rig, args, stop) if rig.is_serial else _sim_arm(rig, args, stop)


def _sim_arm(rig: Any, args: argparse.Namespace, stop: Any) -> int:
    from armid.sim_bus.arm import SimulatedArm

    arm = SimulatedArm(rig, seed=args.seed, own_process=True)
    where = f"{rig.bus.interface}:{rig.bus.channel}"
    print(f"armid sim: {rig.name}: {rig.n_joints} drives (nodes {', '.join(str(d.node_id) for d in rig.drives)}) "
          f"on {where}, lock-step with SYNC at {rig.period_s * 1000:g} ms (co-simulated: a late "
          f"SYNC pauses the arm); {arm.timing.sentence('simulator threads')}{'' if arm.cpu is None else f' on CPU {arm.cpu}'}", file=sys.stderr, flush=True)
    print(f"armid sim: waiting for a master's SYNC (COB-ID 0x080) on {where}{_reach(rig)}", file=sys.stderr, flush=True)
    if args.ready:
        Path(args.ready).write_text("ready\n")
    started = time.monotonic()
    try:
        first = _wait_for_syncs(arm, stop, args.duration, started, where)
        waited = time.monotonic() - started
    finally:
        arm.close()
        if args.log:
            _write_sim_log(arm, Path(args.log))
    st = arm.status()
    if st["syncs"] == 0:
        print(f"armid sim: no SYNC came on {where} in {waited:.1f} s of waiting: 0 SYNC periods simulated; "
              f"a master (armid record or excite --rig with this bus) sends them{_reach(rig)}", file=sys.stderr)
    else:
        print(f"armid sim: {st['syncs']} SYNC periods simulated ({st['time_s']:.3f} s of arm time); the first SYNC came "
              f"{first:.1f} s after the drives were on {where}, {waited:.1f} s in all", file=sys.stderr)
    return 0


NO_SYNC_NOTE_S = 5.0
"""Without a SYNC this long, ``armid sim`` says once that it is still waiting, and for what."""


def _reach(rig: Any) -> str:
    """Who can reach the simulated drives on the rig's bus, where that is not every process."""
    if rig.bus.interface == "virtual":
        return ("; python-can's virtual bus stays inside this process, so no master in another process reaches it: "
                "--interface udp_multicast (the master too), or armid demo (both in one process)")
    return ""


def _wait_for_syncs(arm: Any, stop: Any, duration: float | None, started: float, where: str) -> float:
    """Until ``stop`` or ``duration``: seconds from ``started`` to the first SYNC (nan when none)."""
    first, said = float("nan"), False
    while not stop.wait(0.05):
        now = time.monotonic() - started
        if first != first and arm.syncs:
            first = now
        elif first != first and not said and now > NO_SYNC_NOTE_S:
            print(f"armid sim: no SYNC on {where} yet after {now:.0f} s; still waiting", file=sys.stderr, flush=True)
            said = True
        if duration and now > duration:
            break
    return first


def _sim_chain(rig: Any, args: argparse.Namespace, stop: Any) -> int:
    """A Dynamixel rig: the simulated servo chain on a pty; the driver opens the printed port."""

    from armid.chain_process import chain_as_hardware

    chain = chain_as_hardware(rig, args.seed)
    print(f"armid sim: {rig.name}: {rig.n_joints} Dynamixel servos (ids {', '.join(str(d.node_id) for d in rig.drives)}) "
          f"at {rig.bus.bitrate:,} baud on {chain.port}", file=sys.stderr, flush=True)
    print(chain.port, flush=True)
    if args.ready:
        Path(args.ready).write_text(chain.port + "\n")
    try:
        run_until(stop, args.duration)
    finally:
        chain.close()
    print(f"armid sim: {chain.periods} periods simulated ({chain.physics.time_s:.3f} s of arm time), "
          f"{chain.instructions} instructions served", file=sys.stderr)
    return 0


def _write_sim_log(arm: object, path: Path) -> None:
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arm.log.arrays())  # type: ignore[attr-defined]


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid sim``: its options."""
    p = sub.add_parser("sim", help="simulated arm on a CAN bus (virtual, udp_multicast, socketcan), or a Dynamixel chain on a pty")
    p.add_argument("--rig", required=True, help="rig file (config/rigs/sim.yaml)")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--seed", type=seed_number, help="override the simulation seed")
    p.add_argument("--duration", type=positive_number, help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--log", metavar="NPZ", help="on exit, write the simulated state per SYNC")
    p.add_argument("--ready", metavar="FILE", help="write this file once the drives are on the bus (a serial chain: its port)")
    p.set_defaults(run=_sim)
