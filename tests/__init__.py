"""The test suite: a package, so its modules share helpers as ``tests.<module>``."""
