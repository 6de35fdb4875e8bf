"""The learning identity in the suite: the recorded sessions (docs/learning_identity.json) learn
the same on this machine, whatever its CPU (decisions exactly, computed floats within
RELATIVE_TOLERANCE), and a real change of behaviour fails the check: another seed, a reward
weight changed by 1 %, a decision flipped or a float moved beyond the tolerance."""
import copy
import json
from pathlib import Path

import pytest
import yaml

from psl_bench import learning_identity as identity
from psl_task.task import EMBEDDED_TASKS, load_task

RECORD = Path(__file__).resolve().parents[3] / 'docs' / 'learning_identity.json'


@pytest.fixture(scope='module')
def recorded() -> dict:
    return json.loads(RECORD.read_text())


@pytest.fixture(scope='module')
def kernel(recorded) -> str:
    return identity.check_kernel(recorded['openblas_kernel'])


def arguments(label: str) -> list[str]:
    return list(dict(identity.SESSIONS)[label])


def test_the_recorded_sessions_learn_the_same_here(recorded, kernel):
    now = identity.run_all(kernel)
    assert set(now) == set(recorded['sessions'])
    assert identity.differences(recorded['sessions'], now) == []


def test_another_seed_fails_it(recorded, kernel, tmp_path):
    args = arguments('scratch')
    args[args.index('--seed') + 1] = '4712'
    now = {'scratch': identity.run_session(args, kernel, tmp_path / 'run')}
    found = identity.differences(recorded['sessions'], now)
    assert any('(a decision)' in line for line in found), found


def test_a_reward_weight_changed_by_one_percent_fails_it(recorded, kernel, tmp_path):
    task = load_task('reach_over_obstacle')
    data = yaml.safe_load((EMBEDDED_TASKS / 'reach_over_obstacle.yaml').read_text())
    data['model'] = str(task.model_path)
    data['reward']['weights']['smoothness'] *= 1.01
    path = tmp_path / 'reach_over_obstacle.yaml'
    path.write_text(yaml.safe_dump(data))
    args = arguments('scratch')
    args[args.index('--task') + 1] = str(path)
    now = {'scratch': identity.run_session(args, kernel, tmp_path / 'run')}
    found = identity.differences(recorded['sessions'], now)
    assert any('best_reward' in line for line in found), found


def scaled(fingerprint: dict, factor: float) -> dict:
    """Every computed float of a fingerprint times `factor` (the decisions kept)."""
    out = copy.deepcopy(fingerprint)

    def scale(value):
        if isinstance(value, list):
            return [scale(v) for v in value]
        x = identity._float(value)
        return value if x is None else (x * factor).hex()
    for task in out['tasks']:
        for key in identity.TASK_FLOATS:
            task[key] = scale(task[key])
    for key in out['summary']:
        if key not in identity.SUMMARY_DECISIONS:
            out['summary'][key] = scale(out['summary'][key])
    out['samples']['thetas'] = scale(out['samples']['thetas'])
    return out


def test_last_bits_pass_and_more_fails(recorded):
    sessions = recorded['sessions']
    payload = sessions['payload_ilc']
    assert identity.differences(sessions, {'payload_ilc': scaled(payload, 1 + 1e-12)}) == []
    assert identity.differences(sessions, {'payload_ilc': scaled(payload, 1 + 1e-12)},
                                bit_identical=True)
    assert identity.differences(sessions, {'payload_ilc': scaled(payload, 1 + 1e-7)})
    flipped = copy.deepcopy(payload)
    flipped['tasks'][0]['fulfilled'] = not flipped['tasks'][0]['fulfilled']
    found = identity.differences(sessions, {'payload_ilc': flipped})
    assert found == ['payload_ilc: task 0 fulfilled (a decision): True != False']
    fewer = copy.deepcopy(payload)
    fewer['samples']['count'] -= 1
    assert identity.differences(sessions, {'payload_ilc': fewer})
