"""The operator's console: a live map of the fleet, the jammer and the coverage maps in a
browser, with the jammer under the operator's hand (``jamnav console``, started by ``jamnav
up`` unless ``--no-web``)."""
