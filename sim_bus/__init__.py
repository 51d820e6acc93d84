"""armid sim_bus: see README (this package fills in with its issue)."""
