"""Package data (robot descriptions, drive dictionaries, rig files, Zenoh configurations): no logic. Found with ``armid.resources.config_file``."""
