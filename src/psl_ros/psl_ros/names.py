"""Topic, service and action names of the psl graph, written once.

All names are relative, so a whole rollout worker runs under a namespace. A node serving a
name uses the first column; a client in the same namespace the second (the simulator serves
``~/reset``, which the executor calls as ``sim/reset``).
"""
from __future__ import annotations

# the robot loop's topics
JOINT_STATES = 'joint_states'           # sensor_msgs/JointState, the simulator (or robot)
EFFORT_COMMAND = 'effort_command'       # std_msgs/Float64MultiArray, the controller
REFERENCE = 'reference'                 # sensor_msgs/JointState: q_ref, qd_ref, u_ffwd
JOINT_TRAJECTORY = 'joint_trajectory'   # trajectory_msgs/JointTrajectory, the executor
TASK_INSTANCE = 'task_instance'         # psl_msgs/TaskInstance (latched), the simulator
ROLLOUT_EVALUATION = 'rollout_evaluation'   # psl_msgs/RolloutEvaluation, the evaluator
EE_POSE = 'ee_pose'                     # geometry_msgs/PoseStamped, the simulator
SCENE = 'scene'                         # visualization_msgs/MarkerArray (latched), the simulator
LEARNING_PROGRESS = 'learning_progress'  # psl_msgs/LearningProgress, the learner: one per rollout
GOAL_UPDATE = 'goal_update'             # psl_msgs/GoalUpdate: a live new goal for the executor
MATCHED_ENDPOINTS = 'matched_endpoints'  # diagnostic_msgs/DiagnosticStatus (latched), every
                                        # loop node: what its endpoints matched (psl_ros.matching)
CLOCK = '/clock'
DIAGNOSTICS = '/diagnostics'
WORLD_FRAME = 'world'                   # frame_id of ee_pose and of the scene's markers

# services and actions
RESET = 'sim/reset'                     # psl_msgs/ResetTask, the simulator's ~/reset
EXECUTE_ROLLOUT = 'execute_rollout'     # psl_msgs/ExecuteRollout, the executor
GOAL_CHANGE = 'reward_evaluator/goal_change'   # psl_msgs/GoalChange: the executor tells the
                                               # evaluator of a changed goal (its ~/goal_change)
LEARN_SKILL = 'learn_skill'             # psl_msgs/LearnSkill, the learner
SKILL_MEMORY = 'skill_memory'           # the memory node: services skill_memory/<service>

# topic -> (publishers, subscribers) one rollout worker's loop has before its first episode
LOOP_TOPICS = {JOINT_STATES: (1, 2), EFFORT_COMMAND: (1, 1), REFERENCE: (1, 1),
               TASK_INSTANCE: (1, 1), JOINT_TRAJECTORY: (1, 1), ROLLOUT_EVALUATION: (1, 1)}
# the loop's topics a robot offers (a robot psl does not simulate: its joint_state_broadcaster
# and effort forward_command_controller, remapped)
ROBOT_TOPICS = (JOINT_STATES, EFFORT_COMMAND)
# topic -> subscribers a rollout worker's own nodes have on it, beyond LOOP_TOPICS (the
# executor reads /diagnostics)
OWN_SUBSCRIBERS = {**{topic: subs for topic, (_, subs) in LOOP_TOPICS.items()}, DIAGNOSTICS: 1}
# what a recording of the loop holds (psl demo)
RECORDED_TOPICS = (JOINT_STATES, EE_POSE, EFFORT_COMMAND, REFERENCE, JOINT_TRAJECTORY,
                   TASK_INSTANCE, ROLLOUT_EVALUATION, CLOCK, SCENE)


def under(namespace: str, name: str) -> str:
    """`name` relative to a (relative) namespace: under('worker0', 'sim/reset') ==
    'worker0/sim/reset'; under('', name) == name."""
    return '/'.join(filter(None, (namespace.strip('/'), name)))
