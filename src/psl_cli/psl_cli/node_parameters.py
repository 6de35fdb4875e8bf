"""Which parameter dataclasses each node declares (`psl_ros.parameters.declare`), and a ROS
parameter file generated from them (`psl params`): the defaults live in the dataclasses only.
`test/test_node_parameters.py` holds this table to what the running nodes declare."""
from __future__ import annotations

import dataclasses
import textwrap

import yaml


def node_parameters() -> dict[str, tuple[type, ...]]:
    """Node name -> the dataclasses whose fields are its parameters, in declaration order."""
    from psl_controller.parameters import ControllerParameters, ExecutorParameters
    from psl_memory.memory_directory import MemoryFiles
    from psl_memory.memory_limits import MemoryLimits
    from psl_memory.skill_config import SkillConfig
    from psl_optimizer.learner_parameters import LearnerParameters
    from psl_sim.sim_parameters import SimParameters
    from psl_ros.view_parameters import ViewParameters
    from psl_sim.standard_robot_parameters import StandardRobotParameters

    return {'sim': (SimParameters,), 'pd_controller': (ControllerParameters,),
            'dmp_executor': (ExecutorParameters,),
            'skill_memory': (SkillConfig, MemoryLimits, MemoryFiles),
            'learner': (LearnerParameters,), 'reward_evaluator': (),
            'standard_robot': (StandardRobotParameters,), 'view': (ViewParameters,)}


def reported_parameters() -> dict[str, tuple[str, ...]]:
    """Node name -> the read-only parameters it declares besides its dataclasses' fields: what a
    JointTrajectoryController says of itself (its joints and command interfaces, from its
    task), not settings."""
    from psl_controller.follow_joint_trajectory import REPORTED
    return {'pd_controller': REPORTED, 'standard_robot': REPORTED}


def parameter_file(node: str) -> str:
    """A ``--params-file`` for `node` with every parameter at its default, each described."""
    lines = [f'# Parameters of the {node} node at their defaults (psl params {node}); '
             'pass with --ros-args --params-file.', '/**:', '  ros__parameters:']
    for cls in node_parameters()[node]:
        for field in dataclasses.fields(cls):
            default = field.default if field.default is not dataclasses.MISSING \
                else field.default_factory()
            value = yaml.safe_dump(list(default) if isinstance(default, tuple) else default,
                                   default_flow_style=True, width=1000).strip()
            value = value.removesuffix('\n...').removesuffix('...').strip()
            for text in textwrap.wrap(field.metadata.get('doc', ''), 90):
                lines.append(f'    # {text}')
            lines.append(f'    {field.name}: {value}')
    return '\n'.join(lines) + '\n'
