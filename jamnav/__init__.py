"""The ``jamnav`` command line and the supervisor of the distributed system."""
