"""The documented commands as a reader types them: every ``bash`` block of README.md and
docs/*.md, found, parsed and run line by line, in the order written, from an empty folder of
the document's own, against the graph the document starts (``python test/docs_commands.py``
lists them). The tests: test_docs*.py, a file per group of documents (`GROUPS`), so that the
suite's two workers share them.

A document is one test: its commands build on each other (a learned memory loaded, then
queried). A command the docs mark as not run is a skipped test of its own (test_docs.py), its
reason printed by ``make test`` (-rs). Each document runs on this test run's ROS domain (the root
conftest.py), its view on a free port (``PSL_VIEW_PORT``), its logs in its folder.

sybil's markdown lexer finds every fenced ``bash`` block of README.md and docs/*.md; this module
turns a block into commands and says how each one runs. The rules, which the docs follow:

- each line of a block is one command; a line ending in ``\\`` goes on in the next; a line that
  is only a comment is prose, but an indented one right after a command goes on with its
  comment;
- a command that runs until Ctrl-C (``psl up``, ``psl view`` without ``--layout``) runs in the
  background, as in a second shell, until the document ends or the same command runs again;
  the next command waits until it is ready (``graph ready``, the view serving);
- a command carrying ``[not run by the docs test: WHY]`` in its comment is not run, and the
  test run prints WHY (a skipped test); the next command of its block is its fast form, which
  runs, unless WHY names the test file that runs it (``test/test_demo.py``);
- a here-document (``python - <<'PY'`` ... ``PY``) is one command with its lines;
- a command carrying ``[prints: TEXT]`` must print TEXT (a figure quoted beside it), each number
  in it within `FIGURE_RTOL` of the one printed: the seeds are fixed, but another CPU's last
  bits of floating point may turn a search another way;
- a command carrying ``[exits N]`` must end with exit code N (a refusal the docs show); every
  other command must end with 0.
"""
from __future__ import annotations

import dataclasses
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from sybil import Document
from sybil.parsers.markdown import CodeBlockParser

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = ('README.md', *sorted(str(p.relative_to(ROOT)) for p in (ROOT / 'docs').glob('*.md')))
NOT_RUN_MARK = re.compile(r'\[not run by the docs test: ([^\]]+)\]')
HEREDOC = re.compile(r"<<-?\s*'?(\w+)'?")
PRINTS = re.compile(r'\[prints: ([^\]]+)\]')
NUMBER = re.compile(r'-?\d+(?:\.\d+)?')
FIGURE_RTOL = 0.1           # a quoted figure against the one printed, relative
EXITS = re.compile(r'\[exits (\d+)\]')
TEST_FILE = re.compile(r'\b((?:test|src/\w+/test)/test_\w+\.py)\b')
# the test file that runs each document with commands (the heavy ones apart, to share the
# suite's workers); test_docs.py checks that every document with commands is in one
GROUPS = {'test_docs.py': ('README.md', 'docs/getting_started.md', 'docs/skill_memory.md',
                           'docs/tasks.md'),
          'test_docs_learning.py': ('docs/learning.md', 'docs/viewing_and_recording.md'),
          'test_docs_your_robot.py': ('docs/your_robot.md',),
          'test_docs_benchmarks.py': ('docs/benchmarks.md',)}
# commands that run until Ctrl-C, and what each prints once it is ready
SERVERS = {('psl', 'up'): re.compile(r'^graph ready$', re.MULTILINE),
           ('psl', 'view'): re.compile(r'serving Foxglove on ws://')}


@dataclasses.dataclass(frozen=True)
class Command:
    """One command of a document, where it is written and how the test treats it."""

    document: str
    line: int               # its first line in the document, 1-based
    text: str               # as typed (continuations joined), its comment included
    not_run: str | None     # why the test does not run it, None: it runs
    exits: int              # the exit code it must end with
    prints: str | None = None   # what it must print, its numbers within FIGURE_RTOL

    @property
    def where(self) -> str:
        return f'{self.document}:{self.line}'

    @property
    def words(self) -> list[str]:
        """Its words as bash splits them, without the comment."""
        return shlex.split(self.text, comments=True)

    @property
    def ready(self) -> re.Pattern | None:
        """A command that runs until Ctrl-C: what it prints once ready; None for the others."""
        words = self.words
        if '--layout' in words:           # psl view --layout FILE writes a file and ends
            return None
        return SERVERS.get(tuple(words[:2]))


def _blocks(path: Path) -> list[tuple[int, str]]:
    """The document's ``bash`` blocks: (the line of its first command, its text)."""
    parsed = Document.parse(str(path),
                            CodeBlockParser(language='bash', evaluator=lambda example: None))
    # an example's line is its fence's; its text starts on the next line
    return [(example.line + 1, example.parsed) for example in parsed.examples()]


def commands(document: str, root: Path = ROOT) -> list[list[Command]]:
    """The document's commands, block by block, in the order written."""
    result = []
    for first_line, text in _blocks(root / document):
        written: list[list] = []            # [first line, text] of each command
        pending, heredoc, follows = '', None, False
        for line_number, line in enumerate(text.splitlines(), first_line):
            if heredoc:                     # a here-document: its lines up to the terminator
                written[-1][1] += '\n' + line
                heredoc = None if line.strip() == heredoc else heredoc
                continue
            stripped = line.rstrip()
            if not pending and stripped.lstrip().startswith('#'):
                if follows and line[:1].isspace():  # an indented comment goes on with the last
                    written[-1][1] += '\n' + stripped
                continue
            if not stripped:
                follows = False
                continue
            if not pending:
                written.append([line_number, ''])
            if stripped.endswith('\\'):
                pending = 'yes'
                written[-1][1] += stripped[:-1] + ' '
                continue
            pending, follows = '', True
            written[-1][1] += stripped
            heredoc = (opened := HEREDOC.search(stripped)) and opened.group(1)
        result.append([_command(document, start, whole) for start, whole in written])
    return result


def _command(document: str, line: int, text: str) -> Command:
    not_run, exits, prints = (NOT_RUN_MARK.search(text), EXITS.search(text),
                              PRINTS.search(text))
    return Command(document, line, text.strip(),
                   ' '.join(not_run.group(1).split()) if not_run else None,
                   int(exits.group(1)) if exits else 0,
                   ' '.join(prints.group(1).split()) if prints else None)


def figure_printed(quoted: str, output: str) -> bool:
    """Whether `output` prints `quoted`: its words as quoted (any run of spaces alike), each of
    its numbers within `FIGURE_RTOL` of the one in the same place."""
    parts = re.split(f'({NUMBER.pattern})', quoted.strip())
    pattern = ''.join(f'({NUMBER.pattern})' if k % 2 else
                      r'\s+'.join(re.escape(w) for w in re.split(r'\s+', part))
                      for k, part in enumerate(parts))
    expected = [float(n) for n in parts[1::2]]
    return any(all(abs(float(p) - e) <= FIGURE_RTOL * abs(e)
                   for p, e in zip(found.groups(), expected))
               for found in re.finditer(pattern, output))


def fast_form_missing(block: list[Command]) -> list[Command]:
    """The commands of `block` not run whose fast form is missing: neither the next command
    runs, nor does the reason name the test that runs them."""
    missing = []
    for k, command in enumerate(block):
        if command.not_run is None or TEST_FILE.search(command.not_run):
            continue
        following = block[k + 1] if k + 1 < len(block) else None
        if following is None or following.not_run is not None:
            missing.append(command)
    return missing



STARTED = re.compile(r'^(?:re)?started (\S+) +pid (\d+)$', re.MULTILINE)   # psl up's nodes
COMMAND_TIMEOUT = 300.0     # s, a backstop for one command (the docs' commands take seconds)
READY_TIMEOUT = 120.0       # s, for a background command to say it is ready
END_TIMEOUT = 30.0          # s, for a background command to end after Ctrl-C



def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class Background:
    """A command that runs until Ctrl-C, in its own process group, its output in a file."""

    def __init__(self, command: Command, folder: Path, env: dict, log: Path):
        self.command, self.log = command, log
        with open(log, 'w') as out:
            self.process = subprocess.Popen(['bash', '-c', command.text], cwd=folder, env=env,
                                            stdout=out, stderr=subprocess.STDOUT,
                                            start_new_session=True)

    def output(self) -> str:
        return self.log.read_text(errors='replace')

    def wait_ready(self) -> None:
        deadline = time.monotonic() + READY_TIMEOUT
        while not self.command.ready.search(self.output()):
            assert self.process.poll() is None, (
                f'{self.command.where} `{self.command.text}` ended with exit code '
                f'{self.process.returncode} before it was ready:\n{self.output()}')
            assert time.monotonic() < deadline, (
                f'{self.command.where} `{self.command.text}` not ready after '
                f'{READY_TIMEOUT:.0f} s:\n{self.output()}')
            time.sleep(0.05)

    def end(self) -> list[str]:
        """Ctrl-C, as in its shell: its process group gets SIGINT; killed if it does not end,
        and so is every process it said it started (``psl up``: one per node, in sessions of
        their own) that outlived it. Returns those left behind, which it killed: a graph left
        on this run's ROS domain would answer the next test's rollouts."""
        if self.process.poll() is None:
            try:
                os.killpg(self.process.pid, signal.SIGINT)
                self.process.wait(timeout=END_TIMEOUT)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(self.process.pid, signal.SIGKILL)     # whatever of it is left
        except ProcessLookupError:
            pass
        self.process.wait()
        left = []
        for name, pid in STARTED.findall(self.output()):
            try:    # still that node (a PID is reused): a process of ROS arguments
                if b'--ros-args' in Path(f'/proc/{pid}/cmdline').read_bytes().split(b'\0'):
                    os.kill(int(pid), signal.SIGKILL)
                    left.append(f'{name} (pid {pid})')
            except (FileNotFoundError, ProcessLookupError):
                pass
        return left


def _run(command: Command, folder: Path, env: dict) -> str:
    process = subprocess.Popen(['bash', '-c', command.text], cwd=folder, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               start_new_session=True)
    try:
        out, _ = process.communicate(timeout=COMMAND_TIMEOUT)
    except subprocess.TimeoutExpired:
        out = ''
        pytest.fail(f'{command.where} `{command.text}` still running after '
                    f'{COMMAND_TIMEOUT:.0f} s')
    finally:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        process.wait()
    assert process.returncode == command.exits, (
        f'{command.where} `{command.text}` ended with exit code {process.returncode}, '
        f'not {command.exits}:\n{out}')
    assert command.prints is None or figure_printed(command.prints, out), (
        f'{command.where} quotes "{command.prints}", the command printed:\n{out}')
    return out


def run_document(document: str, tmp_path: Path) -> None:
    """Run the document's commands as a reader types them, in `tmp_path`/reader (empty), the
    background ones ended at the end whatever happens; fails on the first that does not do
    what the document says."""
    folder = tmp_path / 'reader'
    folder.mkdir()
    (tmp_path / 'tmp').mkdir()
    # its temporary files in its folder too (TMPDIR: `psl bench dynamics` keeps a folder there)
    env = dict(os.environ, PSL_VIEW_PORT=str(_free_port()), PSL_LOG_DIR=str(tmp_path / 'logs'),
               TMPDIR=str(tmp_path / 'tmp'))
    env.pop('PSL_MEMORY_DIR', None)     # the graph keeps its memory files where it was started
    background: dict[tuple, Background] = {}
    left: list[str] = []        # processes a background command left behind (killed)
    took = []                   # (seconds, command): `pytest -s` prints where the time goes
    try:
        for k, command in enumerate(c for block in commands(document) for c in block):
            if command.not_run:
                continue
            start = time.monotonic()
            if command.ready:
                kind = tuple(command.words[:2])
                if kind in background:            # the same command again: the first one ends
                    ended = background.pop(kind)
                    left += [f'{ended.command.where}: {name}' for name in ended.end()]
                started = Background(command, folder, env, tmp_path / f'background{k}.log')
                background[kind] = started
                started.wait_ready()
            else:
                _run(command, folder, env)
            took.append((time.monotonic() - start, command))
    finally:
        start = time.monotonic()
        left += [f'{started.command.where}: {name}' for started in background.values()
                 for name in started.end()]
        took.append((time.monotonic() - start, None))
        print(f'\n{document}: {sum(t for t, _ in took):.1f} s')
        for seconds, command in took:
            print(f'  {seconds:6.1f} s  ' + (
                f'{command.where} {command.text[:70]}' if command
                else 'Ctrl-C to what runs in the background'))
    assert not left, f'left behind after Ctrl-C (killed now): {left}'


def main() -> int:
    for document in DOCUMENTS:
        blocks = commands(document)
        if not any(blocks):
            continue
        print(f'{document}:')
        for block in blocks:
            for c in block:
                how = f'not run: {c.not_run}' if c.not_run else (
                    'in the background' if c.ready else 'runs')
                print(f'  {c.line:4d}  {how:<28.28}  {c.text[:80]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
