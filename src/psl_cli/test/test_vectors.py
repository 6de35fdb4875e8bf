"""`psl_cli.vectors.load_vector`: every form a theta file comes in, psl query's own answers
included (what `psl query` prints, saved to a file, is a theta file)."""
import json

import numpy as np
import pytest

from psl_cli.vectors import load_vector

THETA = [0.25, -1.5, 3e-3, 12.0]


def query_answer_text(theta) -> str:
    """psl query's text answer, as cmd_memory prints it (one `key: value` line each)."""
    result = {'message': 'ok', 'theta': theta, 'variance': [0.1] * len(theta)}
    return ''.join(f'{key}: {value}\n' for key, value in result.items())


@pytest.mark.parametrize('name, content', [
    ('theta.txt', '0.25 -1.5\n0.003 12  # the last two\n'),
    ('theta.json', json.dumps(THETA)),
    ('theta.json', json.dumps([THETA[:2], THETA[2:]])),
    ('answer.json', json.dumps({'message': 'ok', 'theta': THETA, 'variance': [0.1] * 4})),
    ('answer.txt', json.dumps({'message': 'ok', 'theta': THETA})),      # --json > any name
    ('answer.txt', query_answer_text(THETA)),
])
def test_each_form_gives_the_vector(tmp_path, name, content):
    (tmp_path / name).write_text(content)
    np.testing.assert_array_equal(load_vector(tmp_path / name), THETA)


def test_an_npy_file_whatever_its_shape(tmp_path):
    np.save(tmp_path / 'theta.npy', np.array(THETA).reshape(2, 2))
    np.testing.assert_array_equal(load_vector(tmp_path / 'theta.npy'), THETA)


@pytest.mark.parametrize('name, content, words', [
    ('a.json', json.dumps({'message': 'ok', 'variance': [1.0]}), "without 'theta'"),
    ('a.txt', 'theta: [1.0, nan]\n', 'no vector of numbers'),
    ('a.txt', 'garbage 1.0\n', 'no vector of numbers'),
    ('a.txt', '# nothing\n', 'holds no numbers'),
    ('a.json', '[1.0, Infinity]', 'not finite'),
    ('a.npy', 'not numpy', 'no NumPy header'),
])
def test_bad_files_are_refused_naming_the_file(tmp_path, name, content, words):
    (tmp_path / name).write_text(content)
    with pytest.raises(ValueError, match=words) as raised:
        load_vector(tmp_path / name)
    assert name in str(raised.value)
