"""Topic, service and action names of the psl graph, written once.

All names are relative, so a whole rollout worker runs under a namespace. A node serving a
name uses the first column; a client in the same namespace the second (the simulator serves
``~/reset``, which the executor calls as ``sim/reset``).
"""
from __future__ import annotations

# the robot loop's topics
JOINT_STATES = 'joint_states'           # sensor_msgs/JointState, the simulator (or robot)
EFFORT_COMMAND = 'effort_command'       # std_msgs/Float64MultiArray, psl's controller to psl's
                                        # simulator (or a robot's forward_command_controller)
TASK_INSTANCE = 'task_instance'         # psl_msgs/TaskInstance (latched), the executor
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


def world_pose(body: str) -> str:
    """geometry_msgs/PoseStamped of a body of the world a task observes (reward.observe: a
    ball): the simulator publishes it; on a robot, remap it to a motion capture's topic."""
    return f'world/{body}/pose'


# services and actions
RESET = 'sim/reset'                     # psl_msgs/ResetTask, the simulator's ~/reset
EXECUTE_ROLLOUT = 'execute_rollout'     # psl_msgs/ExecuteRollout, the executor
EVALUATE = 'reward_evaluator/evaluate'  # psl_msgs/EvaluateEpisode: the executor has an episode
                                        # scored (the evaluator's ~/evaluate)
FOLLOW_JOINT_TRAJECTORY = 'follow_joint_trajectory'     # control_msgs/FollowJointTrajectory,
                                        # under a JointTrajectoryController's node
CONTROLLER_STATE = 'controller_state'   # control_msgs/JointTrajectoryControllerState, ditto
PSL_CONTROLLER_STATE = 'pd_controller/' + CONTROLLER_STATE      # psl's controller's
LEARN_SKILL = 'learn_skill'             # psl_msgs/LearnSkill, the learner
SKILL_MEMORY = 'skill_memory'           # the memory node: services skill_memory/<service>

# topic -> (publishers, subscribers) one rollout worker's loop on psl's simulator has before
# its first episode (joint_states: the controller, the executor's link, the evaluator)
LOOP_TOPICS = {JOINT_STATES: (1, 2), EFFORT_COMMAND: (1, 1), TASK_INSTANCE: (1, 1)}
# the loop's topics on a robot's own clock: the robot's joint states (the executor and the
# evaluator read them) and the episodes the executor announces
ROBOT_LOOP_TOPICS = {JOINT_STATES: (1, 2), TASK_INSTANCE: (1, 1)}
# topic -> subscribers a rollout worker's own nodes have on it
OWN_SUBSCRIBERS = {JOINT_STATES: 2, EFFORT_COMMAND: 1, TASK_INSTANCE: 1}
# what a recording of the loop holds (psl demo)
RECORDED_TOPICS = (JOINT_STATES, EE_POSE, EFFORT_COMMAND, TASK_INSTANCE, ROLLOUT_EVALUATION,
                   CLOCK, SCENE)


def under(namespace: str, name: str) -> str:
    """`name` relative to a (relative) namespace: under('worker0', 'sim/reset') ==
    'worker0/sim/reset'; under('', name) == name."""
    return '/'.join(filter(None, (namespace.strip('/'), name)))
