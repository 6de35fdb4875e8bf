"""psl bench: the command line of the benchmarks runs them, prints their report, reuses
finished run folders and ends with exit code 2 and the reason for a bad setting."""
import json

from psl_cli.main import main

STRATEGIES = ('scratch', 'bootstrap')
SEEDS = (0, 1)


def test_learn_reuses_finished_runs_and_refuses_other_settings(tmp_path, capsys):
    argv = ['bench', 'learn', '--strategies', *STRATEGIES, '--seeds', *map(str, SEEDS),
            '--tasks', '3', '--budget', '25', '--test-tasks', '3', '--after', '1',
            '--out', str(tmp_path), '--json', '--serial']    # Ray: test_sessions.py
    assert main(argv) == 0
    first = json.loads(capsys.readouterr().out)
    assert not any(run['reused'] for runs in first['runs'].values() for run in runs.values())
    for row in first['strategies'].values():      # the session's share spent simulating
        assert 0.0 < row['simulation_share']['mean'] <= 1.0
        assert row['session_seconds']['mean'] >= row['train_seconds']['mean']
    assert main(argv) == 0
    again = json.loads(capsys.readouterr().out)
    assert all(run['reused'] for runs in again['runs'].values() for run in runs.values())
    assert again['strategies'] == first['strategies']
    argv[argv.index('--budget') + 1] = '26'       # another session into the same folders
    assert main(argv) == 2
    assert 'another or an unfinished' in capsys.readouterr().err


def test_a_bad_setting_ends_with_the_reason(capsys):
    assert main(['bench', 'encodings', '--tasks', '3', '--after', '3']) == 2
    err = capsys.readouterr().err
    assert 'psl bench encodings:' in err and '--after' in err


def test_the_rollout_bench_prints_its_ratio(capsys):
    assert main(['bench', 'rollout', '--population', '4', '--repeats', '1']) == 0
    out = capsys.readouterr().out
    assert 'raw mujoco.rollout' in out and 'ratio' in out


def test_learn_runs_the_baselines_named_by_skill_maps(tmp_path, capsys):
    argv = ['bench', 'learn', '--strategies', 'bootstrap', '--seeds', '0', '--tasks', '2',
            '--budget', '20', '--test-tasks', '2', '--after', '1', '--out', str(tmp_path),
            '--serial', '--skill-maps', 'elm,library', 'gp']    # Ray: test_sessions.py
    assert main(argv + ['--json']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['settings']['skill_maps'] == ['elm', 'library', 'gp']
    assert list(report['strategies']) == ['bootstrap', 'bootstrap-library', 'bootstrap-gp']
    assert main(argv) == 0                              # reused, printed as a table
    out = capsys.readouterr().out
    assert '| bootstrap | gp |' in out and '| bootstrap | library |' in out
    assert main(argv[:-2] + ['magic']) == 2
    assert 'unknown skill maps' in capsys.readouterr().err


def test_json_stays_alone_on_stdout_whatever_prints_meanwhile(monkeypatch, capsys):
    """psl bench ... --json: stdout holds the report alone, whatever prints while the
    benchmark runs (seen: Ray's driver printing a dead worker's notice on stdout, which broke
    the JSON of a sweep that had retried the session and was complete)."""
    from psl_cli import bench_commands

    def noisy(args):
        print('(raylet) A worker died or was killed while executing a task')
        return {'rows': 1}, 'the table\n'
    monkeypatch.setitem(bench_commands.BENCHES, 'learn', noisy)
    assert main(['bench', 'learn', '--json']) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {'rows': 1}
    assert '(raylet)' in err
    assert main(['bench', 'learn']) == 0
    out, _ = capsys.readouterr()
    assert out == 'the table\n'
