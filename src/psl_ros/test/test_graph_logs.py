"""Where a graph's node logs go (psl_ros.graph): the folder given, else a new folder named by
the start time under $PSL_LOG_DIR, else under ./log/graph of the current working directory
(not the checkout). No process is started."""
from pathlib import Path

from psl_ros.graph import LOG_ROOT_VARIABLE, Graph


def test_the_default_is_under_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.delenv(LOG_ROOT_VARIABLE, raising=False)
    monkeypatch.chdir(tmp_path)
    log_dir = Graph().log_dir
    assert log_dir.parent == tmp_path.resolve() / 'log' / 'graph'
    assert log_dir.name[:8].isdigit()             # the start time, YYYYmmdd-HHMMSS


def test_psl_log_dir_is_the_root_of_the_log_folders(tmp_path, monkeypatch):
    monkeypatch.setenv(LOG_ROOT_VARIABLE, str(tmp_path / 'logs'))
    assert Graph().log_dir.parent == tmp_path / 'logs'
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(LOG_ROOT_VARIABLE, 'relative')
    assert Graph().log_dir.parent == tmp_path.resolve() / 'relative'


def test_a_given_folder_is_used_as_it_is(tmp_path, monkeypatch):
    monkeypatch.setenv(LOG_ROOT_VARIABLE, str(tmp_path / 'elsewhere'))
    assert Graph(log_dir=tmp_path / 'mine').log_dir == tmp_path / 'mine'
    monkeypatch.chdir(tmp_path)
    assert Graph(log_dir='here').log_dir == Path(tmp_path.resolve() / 'here')
