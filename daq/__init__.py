"""armid daq: acquisition, recording, streaming over Zenoh, the excitation session (docs/architecture.md)."""
