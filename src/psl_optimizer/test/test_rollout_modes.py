"""One factory of rollouts (psl_optimizer.rollout_modes): a mode's name -> a Rollouts; the
learning loop takes one and imports no implementation."""
import ast
from pathlib import Path

import pytest

import psl_optimizer.learning
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.rollout_modes import make_rollouts
from psl_optimizer.rollouts import MODES
from psl_task.task import load_task


def test_each_mode_has_its_rollouts_and_an_unknown_one_is_refused():
    task = load_task('reach_over_obstacle')
    assert set(MODES) == {'batch', 'graph'}
    assert isinstance(make_rollouts('batch', task), BatchRollouts)
    with pytest.raises(ValueError, match='graph mode needs the rollout workers'):
        make_rollouts('graph', task)
    with pytest.raises(ValueError, match="unknown rollout mode 'sim'; known: batch, graph"):
        make_rollouts('sim', task)


def test_the_learning_loop_requires_rollouts_and_imports_no_implementation(tmp_path):
    with pytest.raises(TypeError, match='rollouts'):
        Learner(load_task('reach_over_obstacle'), LearnSettings(num_tasks=1), tmp_path)
    tree = ast.parse(Path(psl_optimizer.learning.__file__).read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                 for alias in node.names}
    assert not imported & {'psl_optimizer.batch_rollout', 'psl_optimizer.graph_rollout',
                           'psl_optimizer.rollout_modes'}
