"""armid: command line and reports around the identification core."""
