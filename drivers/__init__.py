"""armid drivers: see README (this package fills in with its issue)."""
