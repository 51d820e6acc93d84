"""The I/O layer: recordings (CSV, NPZ, MCAP), robot files (YAML, URDF) and rig files in, arrays and descriptions out. ``armid.identify`` never imports it."""
