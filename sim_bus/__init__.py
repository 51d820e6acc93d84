"""armid sim_bus: simulated hardware, a peer on the bus: the arm on CAN, the Dynamixel chain, off-line (docs/architecture.md)."""
