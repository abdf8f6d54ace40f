"""An agent process: one per UAV."""
