"""A robot psl does not simulate, for the tests: a few dozen lines of rclpy and MuJoCo that
offer what a ros2_control robot offers and nothing else.

It publishes sensor_msgs/JointState on /joint_states (its own joint order, one extra joint,
wall-clock stamps, 1 mrad of noise, effort = the torque applied) and takes
std_msgs/Float64MultiArray torques on /effort_controller/commands (its own order). Its masses
are 30 % above the model's, its joints have damping (+0.3 N m s/rad) and friction (0.05 N m)
the model lacks, a command acts one period after it came, and it applies zero torque when
commands stop for 5 periods. Its brakes hold the arm until the first command. Its loop runs
with real-time scheduling where the machine allows it. It offers no service (no parameter
services either). SIGUSR1 makes its joint states stop for ``--silence`` seconds (a cable
pulled).

    python minimal_robot.py --model M.xml --joints j3 j2 j1 --start 0.1 0.2 0.3
"""
import argparse
import os
import signal
import threading
import time

import mujoco
import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

args = argparse.ArgumentParser()
args.add_argument('--model', required=True)
args.add_argument('--joints', nargs='+', required=True)
args.add_argument('--start', nargs='+', type=float, required=True)
args.add_argument('--silence', type=float, default=0.0)
a = args.parse_args()

model = mujoco.MjModel.from_xml_path(a.model)
model.body_mass[1:] *= 1.3
model.body_inertia[1:] *= 1.3
ids = [model.joint(name).id for name in a.joints]
qpos, dofs = model.jnt_qposadr[ids], model.jnt_dofadr[ids]
model.dof_damping[dofs] += 0.3          # N m s/rad: joints the model does not know
model.dof_frictionloss[dofs] += 0.05    # N m
data = mujoco.MjData(model)
data.qpos[qpos] = a.start
mujoco.mj_forward(model, data)
period, n = model.opt.timestep, len(ids)
rng = np.random.default_rng(0)

rclpy.init()
node = Node('minimal_robot', start_parameter_services=False, parameter_overrides=[
    Parameter('start_type_description_service', value=False)])
states = node.create_publisher(JointState, '/joint_states', 10)
command = {'u': np.zeros(n), 'at': -1.0}


def on_command(msg: Float64MultiArray) -> None:
    u = np.asarray(msg.data, dtype=float)
    if u.shape == (n,) and np.all(np.isfinite(u)):
        command['u'], command['at'] = u, time.monotonic()


node.create_subscription(Float64MultiArray, '/effort_controller/commands', on_command, 10)
silent_until = [0.0]
signal.signal(signal.SIGUSR1, lambda *_: silent_until.__setitem__(
    0, time.monotonic() + a.silence))
try:        # as a robot's loop: real-time scheduling where allowed (the spin thread inherits it)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
except PermissionError:
    pass
threading.Thread(target=rclpy.spin, args=(node,), daemon=True).start()

applied = np.zeros(n)
deadline = time.monotonic()
try:
    while rclpy.ok():
        if command['at'] < 0:           # brakes on until the first command
            data.qpos[qpos], data.qvel[dofs] = a.start, 0.0
            mujoco.mj_forward(model, data)
        else:
            data.qfrc_applied[dofs] = applied
            mujoco.mj_step(model, data)
        now = time.monotonic()
        # one period of latency; zero torque once commands stop for 5 periods
        applied = command['u'] if now - command['at'] < 5 * period else np.zeros(n)
        if now >= silent_until[0]:
            msg = JointState(name=list(a.joints) + ['gripper_finger'])
            msg.header.stamp = node.get_clock().now().to_msg()
            msg.position = (data.qpos[qpos] + rng.normal(0, 1e-3, n)).tolist() + [0.0]
            msg.velocity = (data.qvel[dofs] + rng.normal(0, 1e-2, n)).tolist() + [0.0]
            msg.effort = data.qfrc_applied[dofs].tolist() + [0.0]
            states.publish(msg)
        deadline = max(deadline + period, now - 10 * period)   # late: no burst to catch up
        time.sleep(max(0.0, deadline - time.monotonic()))
except KeyboardInterrupt:
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
