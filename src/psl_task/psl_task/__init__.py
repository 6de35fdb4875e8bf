"""psl_task: the task model of psl (schema, bindings, model building, arm model, reward geometry,
safety check, inverse kinematics). Imports no ROS."""

DEFAULT_TASK = 'reach_over_obstacle'    # the embedded task every node and command starts with
