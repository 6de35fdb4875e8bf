"""A binding kind added from outside psl (psl_task.bindings): one class and one registry entry,
used by a task file and learned in batch mode, no other module touched."""
from typing import ClassVar

import mujoco
import numpy as np
import pytest
import yaml

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_task import bindings
from psl_task.arm_model import ArmModel
from psl_task.task import EMBEDDED_TASKS, TaskError, load_task


class JointDamping(bindings.Binding):
    """A joint's viscous damping [N m s / rad] (a worn gearbox): changes the model."""

    kind: ClassVar[str] = 'joint_damping'
    changes_model: ClassVar[bool] = True
    joint: str

    def check_range(self, name: str, low: float, high: float) -> None:
        if not low >= 0.0:
            raise ValueError(f'task parameter {name!r} binds a damping: it stays >= 0')

    def applier(self, arm):
        joint = mujoco.mj_name2id(arm.model, mujoco.mjtObj.mjOBJ_JOINT, self.joint)
        if joint < 0:
            raise TaskError(f'{arm.task.model_path}: no joint named {self.joint!r}')
        dof, offset = int(arm.model.jnt_dofadr[joint]), self.offset

        def apply(model, data, value):
            model.dof_damping[dof] = value + offset
        return apply


@pytest.fixture
def damped_task(tmp_path, monkeypatch):
    """reach_over_obstacle with a third task parameter: joint2's damping."""
    monkeypatch.setitem(bindings.BINDINGS, JointDamping.kind, JointDamping)   # the one entry
    data = yaml.safe_load((EMBEDDED_TASKS / 'reach_over_obstacle.yaml').read_text())
    data['model'] = str(EMBEDDED_TASKS / data['model'])
    data['task_parameters'].append({'name': 'wear', 'unit': 'N m s/rad', 'low': 0.2,
                                    'high': 4.0, 'default': 0.2,
                                    'binds': {'kind': 'joint_damping', 'joint': 'joint2'}})
    path = tmp_path / 'worn_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_a_kind_the_registry_lacks_is_refused(tmp_path):
    data = yaml.safe_load((EMBEDDED_TASKS / 'reach_over_obstacle.yaml').read_text())
    data['model'] = str(EMBEDDED_TASKS / data['model'])
    data['task_parameters'][0]['binds'] = {'kind': 'joint_damping', 'joint': 'joint2'}
    path = tmp_path / 'unregistered.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(TaskError, match="kind must be one of .*got 'joint_damping'"):
        load_task(str(path))


def test_a_new_binding_kind_reaches_the_model_and_is_learned(damped_task, tmp_path):
    task = damped_task
    assert isinstance(task.parameters[2].binds, JointDamping)
    arm = ArmModel(task)
    assert arm.changes_model
    dof = arm.dof_adr[1]
    arm.apply_tau(np.array([0.675, 0.16, 3.0]))
    assert arm.model.dof_damping[dof] == 3.0
    # the damping reaches the dynamics: the same policy tracks worse on a worn joint
    evaluator = BatchRollouts(task)
    theta = policy_for(task).default_theta
    fresh, worn = evaluator.run(np.array([theta, theta]),
                                np.array([[0.675, 0.16, 0.2], [0.675, 0.16, 4.0]]))
    assert fresh.evaluation.reward != worn.evaluation.reward
    # and a session learns the task in batch mode
    settings = LearnSettings(strategy='bootstrap', num_tasks=3, seed=5, num_test=2,
                             search=SearchSettings(max_rollouts=40))
    metrics = Learner(task, settings, tmp_path / 'session', evaluator).run().to_dict()
    assert len(metrics['tasks']) == 3 and metrics['complete']
    assert all(len(record['tau']) == 3 for record in metrics['tasks'])
