"""How long a caller waits for the graph by default, in one place (imports no ROS: the pure
parameter dataclasses use it too). Each wait can be given per call; a server that has gone
ends a wait at once (`psl_ros.client.ServerWatch`)."""
SERVICE_TIMEOUT = 10.0   # s for a service's answer (the skill memory, a reset)
GOAL_TIMEOUT = 30.0      # s for an action server to accept a goal
ROLLOUT_TIMEOUT = 120.0  # s for one rollout's result (graph mode)
