"""``psl bench cli``: how long a ``psl`` command that talks to the graph takes end to end, as
the process a user starts, and how much of that comes after its answer.

A skill_memory process is started alone, under its own namespace (`psl_ros.graph.Graph`), with
one skill (so that the answer is a line), and ``psl memory info`` runs `runs` times as a
subprocess (``python -m psl_cli.main``: this package runs the command line, it does not import
it), with ``PYTHONUNBUFFERED=1`` so that its answer reaches the pipe when it is printed. Per
run: the total (start to exit), the time to the answer (start to its first line on stdout) and
the time after it (that line to the exit: closing the client, ending the DDS participant,
interpreter exit). Two references: the same command where nothing answers (a namespace
without a memory and ``--timeout 0.001``: the interpreter, imports, parser, client and exit, no
discovery: what the command costs by itself), run in turn with the command so that both see the
same load; and, after all of them, the same call in this process with a fresh
`psl_ros.client.RosClient` (its own DDS participant: discovery and the call, no interpreter
start and no imports). Not in turn with the processes: a participant ended in this process
delays the discovery of the next process's by about 0.9 s (Fast DDS; measured, not explained).
Discovery of a new participant takes from about 0.1 to 1.2 s here, so the medians of few runs
move by tenths of a second between runs of the benchmark; the minima move less.
"""
from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time

NAMESPACE = 'cli_latency'
COMMAND = ('memory', 'info')            # psl memory info: one service call, a short answer
MEMORY_ONLY = (('skill_memory', 'psl_memory', 'skill_memory'),)
# the one skill the memory holds: psl memory info prints a line per skill, the answer's arrival
SKILL = {'skill': 'bench_cli', 'tau_low': [0.0], 'tau_high': [1.0],
         'theta_reference': [0.0, 0.0, 0.0]}


def _spread(values: list[float]) -> dict:
    """Median, min, max [s] and the values."""
    return {'median': statistics.median(values), 'min': min(values), 'max': max(values),
            'values': values}


def _time_process(command: list[str], timeout: float) -> tuple[float | None, float, int, str]:
    """Run `command`: (seconds to its first line on stdout or None, seconds to its exit,
    exit code, stderr)."""
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env={**os.environ, 'PYTHONUNBUFFERED': '1'})
    try:
        first = process.stdout.readline()
        answered = time.perf_counter() - start if first else None
        _, stderr = process.communicate(timeout=timeout + 30)
        ended = time.perf_counter() - start
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    return answered, ended, process.returncode, stderr


def _psl(namespace: str, timeout: float) -> list[str]:
    return [sys.executable, '-m', 'psl_cli.main', *COMMAND, '--namespace', namespace,
            '--timeout', f'{timeout:g}']


def run_command(namespace: str, timeout: float) -> tuple[float, float]:
    """One ``psl memory info`` as a process: (seconds to its answer, seconds after it).

    Raises:
        RuntimeError: it printed no answer or failed (its last line of stderr says why).
    """
    answered, ended, code, stderr = _time_process(_psl(namespace, timeout), timeout)
    if code != 0 or answered is None:
        why = (stderr.strip().splitlines() or [f'exit code {code}'])[-1]
        raise RuntimeError(f'psl {" ".join(COMMAND)} failed: {why}')
    return answered, ended - answered


def run_unanswered(namespace: str) -> float:
    """``psl memory info`` where no memory answers (`namespace` has none; it waits 1 ms):
    seconds from start to exit.

    Raises:
        RuntimeError: it did not end with exit code 1 and its one line on stderr.
    """
    answered, ended, code, stderr = _time_process(_psl(namespace, 0.001), 0.0)
    if code != 1 or answered is not None or len(stderr.strip().splitlines()) != 1:
        raise RuntimeError(f'psl {" ".join(COMMAND)} without a memory: exit code {code}, '
                           f'stderr {stderr.strip()!r}')
    return ended


def call_in_process(namespace: str, timeout: float) -> tuple[float, float]:
    """The same call with a fresh RosClient in this process: (seconds to the answer, seconds
    to close the client)."""
    from psl_ros.client import RosClient

    start = time.perf_counter()
    client = RosClient(namespace, name='bench_cli')
    try:
        response = client.memory('info', timeout=timeout)
        answered = time.perf_counter()
    finally:
        client.close()
    if not response.success:
        raise RuntimeError(f'the skill memory refused info: {response.message}')
    return answered - start, time.perf_counter() - answered


def measure(runs: int = 10, timeout: float = 10.0) -> dict:
    """Start a skill_memory process, time `runs` ``psl memory info`` processes and `runs` of
    each reference (module docstring), end the memory.

    Returns:
        JSON-able dict: ``runs``, ``command``; per process run ``total_s``, ``answer_s``,
        ``after_answer_s``; ``unanswered_s`` (the command where nothing answers, start to
        exit); in this process ``in_process_answer_s`` and ``in_process_close_s``; each
        as median, min, max and the values [s].

    Raises:
        ValueError: runs < 1 or timeout <= 0; RuntimeError: the memory did not answer.
    """
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph

    if runs < 1 or not timeout > 0:
        raise ValueError(f'need runs >= 1 and timeout > 0, got {runs} and {timeout}')
    with tempfile.TemporaryDirectory(prefix='psl-bench-cli-') as logs:
        with Graph(nodes=MEMORY_ONLY, namespace=NAMESPACE, log_dir=logs):
            with RosClient(NAMESPACE) as probe:     # the memory is up before the clock runs
                try:
                    created = probe.memory('create_skill', timeout=30.0, **SKILL)
                except TimeoutError as exc:
                    raise RuntimeError(f'the skill memory did not come up: {exc}') from None
                if not created.success:
                    raise RuntimeError(f'the skill memory refused a skill: {created.message}')
            processes, unanswered = [], []
            for _ in range(runs):            # in turn: both see the same load
                processes.append(run_command(NAMESPACE, timeout))
                unanswered.append(run_unanswered(f'{NAMESPACE}_nobody'))
            in_process = [call_in_process(NAMESPACE, timeout) for _ in range(runs)]
    return {'runs': runs, 'command': 'psl ' + ' '.join(COMMAND),
            'total_s': _spread([a + b for a, b in processes]),
            'answer_s': _spread([a for a, _ in processes]),
            'after_answer_s': _spread([b for _, b in processes]),
            'unanswered_s': _spread(unanswered),
            'in_process_answer_s': _spread([a for a, _ in in_process]),
            'in_process_close_s': _spread([b for _, b in in_process])}


def format_report(report: dict) -> str:
    """The report as a small table (medians, with min and max)."""
    def row(label: str, key: str) -> str:
        s = report[key]
        return f"  {label:40s} {s['median']:6.3f} s  [{s['min']:.3f}, {s['max']:.3f}]\n"
    return (f"{report['command']}, {report['runs']} runs each (median [min, max]):\n"
            'as a process\n'
            + row('total, start to exit', 'total_s')
            + row('to the answer', 'answer_s')
            + row('after the answer, to exit', 'after_answer_s')
            + row('nothing answers: start to exit', 'unanswered_s')
            + 'in this process, a fresh RosClient per call\n'
            + row('to the answer (discovery and the call)', 'in_process_answer_s')
            + row('close', 'in_process_close_s'))
