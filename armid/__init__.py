"""armid: hardware-in-the-loop acquisition and dynamics identification for robot arms.

One distribution, one top-level name. The layers, bottom to top (``tests/test_layers.py``
reads every import and fails on one against this direction)::

    armid.schema      the joint-state record, its units and codecs, the exception tree
    armid.resources   where the package data (``armid.config``) lies on disk
    armid.identify    the numerical core: arrays in, arrays out (no file, bus or network)
    armid.drivers     the amplifiers (CANopen, Dynamixel) behind one ``Driver``, a registry
    armid.io          reading recordings (CSV, NPZ, MCAP), robot and rig files (uses the rig's types)
    armid.daq         cycles, recording, streaming over Zenoh, the excitation session
    armid.sim_bus     simulated hardware: a peer on the bus, started by the CLI or a test (a rig comes parsed)
    armid.cli (armid.commands), armid.demo, armid.report, ...   the command line and reports, on top

``armid.config`` is package data (robot descriptions, drive dictionaries, rig files).
"""

from __future__ import annotations

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("armid")
except _metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
