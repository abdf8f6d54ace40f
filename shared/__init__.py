"""What every process of the system shares: the scenario, the world's physics (radio model,
shadowing, kinematics, rewards, outcomes), what a UAV observes and measures, and the transport
(messages, topics, the bus and its access control). How a UAV plans is in ``planning``, which
this package never imports."""
