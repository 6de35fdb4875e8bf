"""Tests of ModelError (psl_task/model_error.py): the wrong model of a sim-to-real measurement,
against properties of the rigid-body equations: the joint-space inertia is linear in the
bodies' masses and inertias (armature aside), viscous damping adds -d * qd to the passive
force, and the identity changes nothing."""

import mujoco
import numpy as np
import pytest

from psl_task.arm_model import ArmModel
from psl_task.model_error import ModelError
from psl_task.task import load_task

REL = 1e-12     # relative, the same products in another order


@pytest.fixture(params=['reach_over_obstacle', 'payload_transport'])
def arm(request):
    return ArmModel(load_task(request.param))


def mass_matrix(model: mujoco.MjModel, q: np.ndarray, qpos_adr) -> np.ndarray:
    data = mujoco.MjData(model)
    data.qpos[qpos_adr] = q
    mujoco.mj_forward(model, data)
    dense = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, dense)
    return dense


def test_the_identity_changes_nothing(arm):
    model = arm.model
    before = {name: getattr(model, name).copy()
              for name in ('body_mass', 'body_inertia', 'dof_damping', 'dof_frictionloss')}
    ModelError().apply(model, arm.joint_ids)
    for name, value in before.items():
        assert np.array_equal(getattr(model, name), value), name


def test_heavier_bodies_scale_the_inertia_matrix_and_damping_adds_a_passive_force(arm):
    rng = np.random.default_rng(5)
    q = arm.task.start_posture + rng.uniform(-0.3, 0.3, arm.task.n_joints)
    nominal = mass_matrix(arm.model, q, arm.qpos_adr)
    armature = np.diag(arm.model.dof_armature)
    real = ArmModel(arm.task).model
    error = ModelError(mass_scale=1.3, frictionloss=0.05, damping=0.3)
    error.apply(real, arm.joint_ids)
    heavier = mass_matrix(real, q, arm.qpos_adr)
    dofs = real.jnt_dofadr[arm.joint_ids]
    sub = np.ix_(dofs, dofs)
    # every body below a driven joint is the robot's: M - armature scales by mass_scale
    expected = 1.3 * (nominal - armature)[sub] + armature[sub]
    assert np.allclose(heavier[sub], expected, rtol=REL, atol=REL * np.abs(nominal).max())
    assert np.allclose(real.dof_frictionloss[dofs], arm.model.dof_frictionloss[dofs] + 0.05)
    # passive force at a velocity: -(d0 + 0.3) qd on the driven joints
    qd = rng.uniform(-1.0, 1.0, arm.task.n_joints)
    forces = []
    for model in (arm.model, real):
        data = mujoco.MjData(model)
        data.qpos[arm.qpos_adr] = q
        data.qvel[dofs] = qd
        mujoco.mj_forward(model, data)
        forces.append(data.qfrc_passive[dofs].copy())
    assert np.allclose(forces[1] - forces[0], -0.3 * qd, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('text, values', [
    ('', ModelError()),
    ('mass_scale=1.3, frictionloss=0.05,damping=0.3', ModelError(1.3, 0.05, 0.3)),
    ('damping=1', ModelError(damping=1.0)),
])
def test_parse(text, values):
    assert ModelError.parse(text) == values


@pytest.mark.parametrize('text, says', [
    ('mass=1.3', 'KEY=VALUE'), ('mass_scale', 'KEY=VALUE'), ('damping=x', 'not a number'),
    ('mass_scale=0', '> 0'), ('damping=-1', '>= 0'), ('frictionloss=nan', 'finite'),
    ('mass_scale=inf', 'finite'),
])
def test_parse_refuses_with_a_reason(text, says):
    with pytest.raises(ValueError, match=says):
        ModelError.parse(text)
