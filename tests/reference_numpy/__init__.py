"""Test-only references: numpy code of the project before the compiled core (commit 48f7e03),
kept so that tests can evaluate the previous implementation on the same inputs as the compiled
one. Never imported by production code (``planner``, ``comms``, ``vehicle_sim``, ``missions``)."""
